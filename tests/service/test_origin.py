"""Origin checks, on by default: a foreign ``Host`` gets 400 (DNS rebinding), a write from a
foreign ``Origin`` 403 and a write that is not JSON 415, each changing nothing; the
WebSocket takes its token as a subprotocol, never in the query string."""

import pytest
from starlette.websockets import WebSocketDisconnect

from service.security import allowed_hosts, content_type_refusal
from tests.helpers.client import LOCAL_URL

from .test_security import GOOD, TOKEN, make, state_of

OWN = {"Origin": LOCAL_URL}
FOREIGN = {"Origin": "http://evil.example"}


def test_a_foreign_host_gets_400_for_reads_and_writes(db, tmp_path):
    rt, store, mgr, c = make(db, tmp_path)
    before = state_of(rt, store, mgr)
    assert c.get("/health").status_code == 200
    for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example"):
        assert c.get("/health", headers={"Host": host}).status_code == 400
        r = c.patch("/filters/EXH_BP_R_Kalman", json={"Q": 4e-6}, headers={"Host": host})
        assert r.status_code == 400, r.text
        r = c.put("/scripts/mine.fdv", content="[formulas]\npublic Y\nY = EXH_BP_R * 2\n",
                  headers={"Host": host, "Content-Type": "text/plain"})
        assert r.status_code == 400
    assert state_of(rt, store, mgr) == before
    for host in ("localhost", "localhost:8000", "127.0.0.1:8000", "[::1]:8000"):
        assert c.get("/health", headers={"Host": host}).status_code == 200, host


def test_a_cross_origin_text_plain_reset_is_refused_and_sends_nothing(db, tmp_path):
    """What any web page could do with no preflight: reset a trip of the engine."""
    rt, store, mgr, c = make(db, tmp_path)
    outbox = len(rt.outbox)
    r = c.post("/engine/reset", content="{}", headers={**FOREIGN, "Content-Type": "text/plain"})
    assert r.status_code == 403 and "evil.example" in r.json()["detail"]
    r = c.post("/engine/reset", json={}, headers=FOREIGN)  # a JSON one from abroad too
    assert r.status_code == 403
    assert len(rt.outbox) == outbox
    # the cell's own page (its own origin) and a tool without an Origin may reset
    assert c.post("/engine/reset", json={}, headers=OWN).status_code == 200
    assert c.post("/engine/reset", json={}).status_code == 200
    assert len(rt.outbox) == outbox + 2


@pytest.mark.parametrize("ctype", [None, "text/plain", "application/x-www-form-urlencoded",
                                   "multipart/form-data; boundary=x"])
def test_a_patch_that_is_not_json_gets_415_naming_the_type(db, tmp_path, ctype):
    rt, store, mgr, c = make(db, tmp_path)
    before = state_of(rt, store, mgr)
    headers = {"Content-Type": ctype} if ctype else {}
    r = c.patch("/filters/EXH_BP_R_Kalman", content='{"Q": 4e-6}', headers=headers)
    assert r.status_code == 415, r.text
    detail = r.json()["detail"]
    assert "application/json" in detail and (repr(ctype) if ctype else "got none") in detail
    assert state_of(rt, store, mgr) == before
    r = c.patch("/filters/EXH_BP_R_Kalman", content='{"Q": 4e-6}',
                headers={"Content-Type": "application/json; charset=utf-8"})
    assert r.status_code == 200 and rt.blocks["EXH_BP_R_Kalman"].params()["Q"] == 4e-6


def test_scripts_upload_as_text_from_the_cell_but_not_from_abroad(db, tmp_path):
    rt, store, mgr, c = make(db, tmp_path)
    text = "[formulas]\npublic Y\nY = EXH_BP_R * 2\n"
    r = c.put("/scripts/far.fdv", content=text, headers={**FOREIGN, "Content-Type": "text/plain"})
    assert r.status_code == 403 and "far.fdv" not in mgr.names()
    r = c.put("/scripts/odd.fdv", content=text, headers={"Content-Type": "image/png"})
    assert r.status_code == 415 and "text/plain" in r.json()["detail"]
    # the page's way (text/plain, own origin) and curl --data-binary's default type
    assert c.put("/scripts/mine.fdv", content=text,
                 headers={**OWN, "Content-Type": "text/plain"}).status_code == 201
    assert c.put("/scripts/curl.fdv", content=text.replace("Y", "Z"),
                 headers={"Content-Type": "application/x-www-form-urlencoded"}).status_code == 201
    # a DELETE has no body: it needs no type, but still a local origin
    assert c.delete("/scripts/curl.fdv", headers=FOREIGN).status_code == 403
    assert c.delete("/scripts/curl.fdv").status_code == 204 and "curl.fdv" not in mgr.names()


def test_content_type_rule_by_method():
    json_ = {"content-type": "application/json"}
    assert content_type_refusal("GET", "/channels", {}) is None
    assert content_type_refusal("POST", "/engine/reset", json_) is None
    assert "got none" in content_type_refusal("POST", "/engine/reset", {})
    assert content_type_refusal("DELETE", "/scripts/x", {}) is None
    assert content_type_refusal("DELETE", "/scripts/x", {"content-length": "3"}) is not None
    assert content_type_refusal("PUT", "/scripts/x", {"content-type": "text/plain"}) is None
    assert content_type_refusal("PATCH", "/scripts/x", {"content-type": "text/plain"}) is not None


def test_allowed_hosts_are_the_configured_host_the_local_names_and_the_extra_ones():
    assert allowed_hosts("127.0.0.1", env={}) == ("127.0.0.1", "localhost", "[::1]")
    assert allowed_hosts("cell-3.lab", env={"TESTCELL_ALLOWED_HOSTS": "cell-3, Proxy.lab"}) == (
        "cell-3.lab", "localhost", "127.0.0.1", "[::1]", "cell-3", "proxy.lab")
    assert allowed_hosts("::1", env={})[0] == "[::1]"
    import socket
    assert socket.gethostname().lower() in allowed_hosts("0.0.0.0", env={})


# -- the WebSocket token ----------------------------------------------------------------------
def test_stream_takes_the_token_as_a_subprotocol_and_echoes_it(db, tmp_path):
    *_, c = make(db, tmp_path, token=TOKEN, protect_reads=True)
    proto = f"token.{TOKEN}"
    with c.websocket_connect("/stream", subprotocols=["json", proto]) as ws:
        assert ws.accepted_subprotocol == proto
        assert ws.receive_json()["type"] == "hello"
    with c.websocket_connect("/stream", headers=GOOD) as ws:
        assert ws.receive_json()["type"] == "hello"
    with pytest.raises(WebSocketDisconnect) as refused:  # no token at all
        with c.websocket_connect("/stream") as ws:
            ws.receive_json()
    assert refused.value.code == 1008


@pytest.mark.parametrize("protect_reads", [True, False])
def test_a_token_in_the_query_string_is_refused_with_the_reason(db, tmp_path, protect_reads):
    *_, c = make(db, tmp_path, token=TOKEN, protect_reads=protect_reads)
    with pytest.raises(WebSocketDisconnect) as refused:
        with c.websocket_connect(f"/stream?token={TOKEN}") as ws:
            ws.receive_json()
    assert refused.value.code == 1008
    assert "query string" in refused.value.reason and "token.<TOKEN>" in refused.value.reason


def test_a_websocket_from_a_foreign_page_is_refused(db, tmp_path):
    *_, c = make(db, tmp_path)
    with pytest.raises(WebSocketDisconnect) as refused:
        with c.websocket_connect("/stream", headers=FOREIGN) as ws:
            ws.receive_json()
    assert refused.value.code == 1008 and "evil.example" in refused.value.reason
    with c.websocket_connect("/stream", headers=OWN) as ws:  # the cell's own page
        assert ws.receive_json()["type"] == "hello"


def test_the_pages_own_files_load_without_the_token_but_nothing_else_does(db, tmp_path):
    """A browser sends no Authorization header for ``<script src>``: with reads protected,
    the page and its static files still load (and then ask for the token), the API does not."""
    *_, c = make(db, tmp_path, token=TOKEN, protect_reads=True)
    assert c.get("/").status_code == 200
    assert c.get("/static/dashboard.js").status_code == 200
    assert c.get("/channels").status_code == 401
    assert c.get("/channels", headers=GOOD).status_code == 200
