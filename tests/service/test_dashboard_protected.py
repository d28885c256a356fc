"""The page on cells other than the default one, in headless Chromium (as
``test_dashboard_browser``): a cell with a token (``TESTCELL_TOKEN``) whose engine has
tripped, its ``/docs`` with the network blocked, and a cell on a user's bus (``--no-sim
--dbc``). One live cell for the module, each page loaded once.
"""

from __future__ import annotations

import time
from pathlib import Path
from urllib.parse import urlparse

import httpx
import pytest

from .livecell import live_cell
from .test_dashboard_browser import chromium  # noqa: F401  (the module's browser fixture)

pytestmark = pytest.mark.browser

TOKEN = "cell-token-4f0c2a"
USER_DBC = Path(__file__).resolve().parents[1] / "data" / "dbc" / "user.dbc"
#: the engine protection's level, and the margin below it a reset needs (the plant's)
BP_LIMIT, RESET_MARGIN = 250.0, 100.0


@pytest.fixture(scope="module")
def tripped(tmp_path_factory):
    """A cell with a token, its valves nearly shut so that the engine trips within seconds."""
    with live_cell(tmp_path_factory.mktemp("tripped"), duty="rated", speed=2.0, token=TOKEN,
                   plant={"valve": 5.0, "bp_limit": BP_LIMIT}) as (url, cell):
        deadline = time.monotonic() + 60
        while httpx.get(url + "/health", timeout=5).json()["trip"] is None:
            assert time.monotonic() < deadline, "the engine did not trip"
            time.sleep(0.2)
        yield url, cell


def _value(cell, name):
    with cell.runtime.lock:
        return cell.runtime.channels[name].value


def test_with_a_token_changes_from_the_page_fail_until_it_is_entered_and_the_reset_takes_two_steps(
        chromium, tripped):  # noqa: F811
    url, cell = tripped
    context = chromium("token-change-profile")
    try:
        page = context.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("dialog", lambda d: d.accept())  # the reset button asks the operator first
        page.goto(url + "/")
        page.wait_for_function("window.TC && TC.ready && TC.messages > 2", timeout=30_000)
        page.wait_for_selector("#trip:not([hidden])")
        assert "EXH_BP_LIMIT" in page.inner_text("#trip-text")
        before = httpx.get(url + "/filters/EXH_BP_R_Kalman", timeout=5).json()["params"]
        card = page.locator('.block[data-block="EXH_BP_R_Kalman"]')

        # before the token: the tuning change and the reset are refused, and nothing changed
        card.locator('input[data-param="Q"]').fill("2e-6")
        card.locator("button.apply").click()
        card.locator(".msg.error").wait_for()
        assert "refused (401)" in card.locator(".msg").inner_text()
        page.click("#reset-trip")
        page.wait_for_selector("#reset-msg.error")
        assert "refused (401)" in page.inner_text("#reset-msg")
        assert "needs its token" in page.inner_text("#token-msg")
        assert httpx.get(url + "/filters/EXH_BP_R_Kalman", timeout=5).json()["params"] == before
        assert _value(cell, "RESET_STATE") != 2 and httpx.get(url + "/health", timeout=5).json()["trip"]

        # the token entered: kept for the tab, sent as a bearer token and on the stream
        page.fill("#token", TOKEN)
        page.click("#token-use")
        assert page.evaluate("sessionStorage.getItem('testcell-token')") == TOKEN
        page.wait_for_function(f"TC.ws.readyState === 1 && TC.ws.protocol === 'token.{TOKEN}'")
        card.locator("button.apply").click()
        page.wait_for_function("""document.querySelector('.block[data-block="EXH_BP_R_Kalman"] .msg')
                                  .textContent.startsWith('applied')""")
        assert httpx.get(url + "/filters/EXH_BP_R_Kalman", timeout=5).json()["params"]["Q"] == 2e-6

        # the engine runs down until the trip's cause has cleared (both banks well below the
        # limit); then the page's button resets it: the request, then the confirm with its
        # challenge, which the simulator answers with DONE and a running engine
        deadline = time.monotonic() + 60
        clear = BP_LIMIT - RESET_MARGIN - 20
        while max(_value(cell, "EXH_BP_L_TRUE"), _value(cell, "EXH_BP_R_TRUE")) > clear:
            assert time.monotonic() < deadline, "the trip's cause did not clear"
            time.sleep(0.2)
        page.click("#reset-trip")
        page.wait_for_selector("#reset-msg.ok")
        assert page.inner_text("#reset-msg") == "reset sent (request and confirm)"
        deadline, seen = time.monotonic() + 10, set()
        while not {"DONE", "RUNNING"} <= seen:
            assert time.monotonic() < deadline, f"the reset did not clear the trip (saw {seen})"
            if _value(cell, "RESET_STATE") == 2:
                seen.add("DONE")
            if _value(cell, "ENGINE_STATE") == 1:
                seen.add("RUNNING")
            time.sleep(0.02)
        assert errors == []
        httpx.patch(url + "/filters/EXH_BP_R_Kalman", json={"Q": before["Q"]}, timeout=5,
                    headers={"Authorization": f"Bearer {TOKEN}"}).raise_for_status()
    finally:
        context.close()


def test_docs_render_with_the_network_blocked(chromium, tripped):  # noqa: F811
    url, _ = tripped
    context = chromium("docs-offline-profile")
    asked_outside: list[str] = []

    def only_the_cell(route):
        if urlparse(route.request.url).hostname == "127.0.0.1":
            route.continue_()
        else:
            asked_outside.append(route.request.url)
            route.abort()

    try:
        page = context.new_page()
        page.route("**/*", only_the_cell)
        page.goto(url + "/docs")
        page.wait_for_selector(".opblock-summary", timeout=30_000)
        spec = httpx.get(url + "/openapi.json", timeout=5).json()
        operations = sum(1 for ops in spec["paths"].values() for m in ops
                         if m in ("get", "put", "post", "patch", "delete"))
        shown = page.eval_on_selector_all(".opblock-summary-path", "es => es.map(e => e.textContent)")
        assert len(shown) == operations and "/channels/{name}" in [s.replace("\u200b", "") for s in shown]
        assert asked_outside == []  # nothing beyond the cell was even asked for
    finally:
        context.close()


def test_on_a_users_bus_the_page_shows_the_users_messages_not_the_engines_empty_panels(chromium, tmp_path):  # noqa: F811
    """``--no-sim --dbc user.dbc``: only the user's frames come; the page shows a panel per
    message of the user's file and none of the engine's blocks, whose inputs never came."""
    from cell.app.cell import Cell
    from cell.bus.dbc import load
    from cell.core.settings import Settings
    from cell.estimators.backpressure import native_filters
    from cell.runtime.scheduler import Runtime
    from service.main import create_app

    from .served import served

    db = load([USER_DBC])
    rt = Runtime(db, native_filters())
    t = 0.0
    while t < 3.0:
        rt.ingest(db.encode("EEC1", {"ECU_ENGINE_SPEED": 1200 + 100 * t}, t))
        if round(t * 100) % 10 == 0:
            rt.ingest(db.encode("DAQ_TEMPS", {"DAQ_OIL_TEMP": 90 + t, "DAQ_COOLANT_TEMP": 85.0}, t))
        t = round(t + 0.01, 6)
    rt.advance(t)
    settings = Settings(dbc=(str(USER_DBC),), no_sim=True, state=tmp_path / "tuning.json")
    context = chromium("user-bus-profile")
    with served(create_app(Cell(runtime=rt, bus="virtual:test", settings=settings))) as url:
        try:
            messages = {m["name"]: m for m in httpx.get(url + "/messages", timeout=5).json()}
            assert messages["EEC1"]["user"] and messages["DAQ_TEMPS"]["user"]
            assert messages["EEC1"]["file"] == "user.dbc" and not messages["EXH_BP"]["user"]
            assert messages["DAQ_TEMPS"]["channels"] == ["DAQ_OIL_TEMP", "DAQ_COOLANT_TEMP"]
            page = context.new_page()
            page.goto(url + "/")
            page.wait_for_function("window.TC && TC.ready")
            shown = page.eval_on_selector_all(".panel:not([hidden])", "es => es.map(e => e.dataset.panel)")
            assert shown == ["message-DAQ_TEMPS", "message-EEC1"]
            hidden = page.eval_on_selector_all(".panel[hidden]", "es => es.map(e => e.dataset.panel)")
            assert {"filters-EXH_BP_L", "filters-EXH_BP_R"} <= set(hidden)
            legend = page.inner_text('[data-panel="message-DAQ_TEMPS"] .legend')
            assert "DAQ_OIL_TEMP [degC]" in legend and "DAQ_COOLANT_TEMP [degC]" in legend
            assert page.evaluate("TC.store.count('ECU_ENGINE_SPEED')") > 10
            # no simulator of the cell's own: no scenario keys are offered as the engine's
            assert all(k["read_by_engine"] is None for k in httpx.get(url + "/scenario", timeout=5).json())
        finally:
            context.close()
