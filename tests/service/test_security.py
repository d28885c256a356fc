"""Security: loopback by default, a token for every change (and optionally reads), compared in
constant time; 401 changes nothing; bodies and scripts over their limits get 413."""

import hmac
import json

import pytest
from fastapi import FastAPI, WebSocket
from tests.helpers.client import local_client

from cell.app.cli import main
from cell.app.cell import Cell
from cell.core.errors import ConfigError
from cell.estimators.backpressure import native_filters
from cell.runtime.scheduler import Runtime
from cell.scripts.manager import ScriptManager
from cell.core.settings import Settings
from cell.app.tuning import TuningStore
from service import security as sec_mod
from service.main import create_app
from service.security import Security, check_bind, websocket_may_command
from tests.helpers.frames import feed as bp_feed
from tests.helpers.frames import steady, wavy

TOKEN = "s3cret-token-for-tests"
GOOD = {"Authorization": f"Bearer {TOKEN}"}
BAD = {"Authorization": "Bearer s3cret-token-for-tesTs"}


def feed(rt, db, t0, t1):
    bp_feed(rt, db, t0, t1, left=steady(600.0), right=wavy(600.0))


def make(db, tmp_path, **security):
    rt = Runtime(db, native_filters(), history_s=600)
    store = TuningStore(tmp_path / "tuning.json")
    mgr = ScriptManager(rt, store)
    mgr.load_defaults()
    feed(rt, db, 0.0, 5.0)
    cell = Cell(runtime=rt, tuning=store, scripts=mgr)
    return rt, store, mgr, local_client(create_app(cell, Security(**security)))


def state_of(rt, store, mgr):
    return (json.dumps({n: b.params() for n, b in rt.blocks.items() if b.family != "script"},
                       sort_keys=True, default=str),
            store.path.read_text() if store.path.exists() else None,
            sorted(mgr.names()), len(rt.outbox))


WRITES = [
    ("patch", "/filters/EXH_BP_R_Kalman", {"json": {"Q": 4e-6}}),
    ("patch", "/filters/EXH_BP_R_MAF", {"json": {"samples": 50}}),
    ("put", "/scripts/mine.fdv", {"content": "[formulas]\npublic Y\nY = EXH_BP_R * 2\n"}),
    ("patch", "/scripts/kalman.fdv", {"json": {"constants": {"Q_EXH_BP_R": 4e-6}}}),
    ("delete", "/scripts/maf.fdv", {}),
    ("post", "/filters/EXH_BP_R_Kalman/autotune", {"json": {"minutes": 1}}),
    ("post", "/engine/reset", {"json": {}}),
]


@pytest.mark.parametrize("method, path, kw", WRITES, ids=[f"{m} {p}" for m, p, _ in WRITES])
def test_changes_need_the_token_and_a_refusal_changes_nothing(db, tmp_path, method, path, kw):
    rt, store, mgr, c = make(db, tmp_path, token=TOKEN)
    before = state_of(rt, store, mgr)
    for headers in ({}, BAD, {"Authorization": TOKEN}, {"Authorization": "Basic " + TOKEN}):
        r = getattr(c, method)(path, headers=headers, **kw)
        assert r.status_code == 401, (headers, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
        assert state_of(rt, store, mgr) == before
    r = getattr(c, method)(path, headers=GOOD, **kw)
    assert r.status_code < 400 or r.status_code == 422, r.text  # autotune may find too little data


def test_reads_are_open_by_default_and_can_be_protected(db, tmp_path):
    *_, c = make(db, tmp_path, token=TOKEN)
    assert c.get("/channels").status_code == 200 and c.get("/health").status_code == 200
    *_, c = make(db, tmp_path, token=TOKEN, protect_reads=True)
    for path in ("/channels", "/health", "/filters", "/scripts", "/openapi.json"):
        assert c.get(path).status_code == 401
        assert c.get(path, headers=BAD).status_code == 401
        assert c.get(path, headers=GOOD).status_code == 200


def test_without_a_token_the_loopback_cell_is_open(db, tmp_path):
    *_, c = make(db, tmp_path)
    assert c.patch("/filters/EXH_BP_R_Kalman", json={"Q": 4e-6}).status_code == 200


def test_tokens_are_compared_in_constant_time(monkeypatch):
    calls = []
    real = hmac.compare_digest
    monkeypatch.setattr(sec_mod.hmac, "compare_digest", lambda a, b: calls.append((a, b)) or real(a, b))
    s = Security(token=TOKEN)
    assert s.authorized({"authorization": f"Bearer {TOKEN}"})
    assert not s.authorized({"authorization": "Bearer nope"})
    assert len(calls) == 2


def test_binding_beyond_loopback_needs_a_token(capsys, monkeypatch):
    for host in ("127.0.0.1", "localhost", "::1", "127.0.0.2"):
        check_bind(host, None)
    for host in ("0.0.0.0", "::", "192.168.1.20"):
        with pytest.raises(ConfigError, match="TESTCELL_TOKEN"):
            check_bind(host, None)
        check_bind(host, TOKEN)
    monkeypatch.delenv("TESTCELL_TOKEN", raising=False)
    assert main(["up", "--host", "0.0.0.0", "--bus", "virtual", "--port", "18999"]) == 2
    assert "refusing to serve the cell beyond this machine without a token" in capsys.readouterr().err
    assert Settings.build({}, environ={}).host == "127.0.0.1"
    with pytest.raises(ConfigError, match="TESTCELL_TOKEN is empty"):
        Settings.build({}, environ={"TESTCELL_TOKEN": " "})
    s = Settings.build({}, environ={"TESTCELL_TOKEN": TOKEN, "TESTCELL_PROTECT_READS": "1"})
    assert s.token == TOKEN and s.protect_reads and TOKEN not in repr(s)
    assert TOKEN not in repr(Security.from_settings(s))


def test_bodies_over_the_limit_get_413_and_change_nothing(db, tmp_path):
    rt, store, mgr, c = make(db, tmp_path, max_body_bytes=4096, max_script_bytes=2048)
    before = state_of(rt, store, mgr)
    big = {"Q": 4e-6, "pad": "x" * 5000}
    assert c.patch("/filters/EXH_BP_R_Kalman", json=big).status_code == 413

    def chunks():  # no Content-Length: the limit holds on the bytes actually received
        for _ in range(10):
            yield b"[formulas]\n" + b" " * 1000 + b"\n"

    r = c.put("/scripts/big.fdv", content=chunks())
    assert r.status_code == 413, r.text
    script = "[formulas]\npublic Y\n" + "// padding\n" * 300 + "Y = EXH_BP_R\n"
    assert 2048 < len(script) < 4096
    r = c.put("/scripts/big.fdv", content=script)
    assert r.status_code == 413 and "limit for a script is 2048" in r.json()["detail"]
    assert state_of(rt, store, mgr) == before
    assert c.put("/scripts/small.fdv", content="[formulas]\npublic Y\nY = EXH_BP_R\n").status_code == 201


def test_a_megabyte_script_is_refused_with_413_by_default(db, tmp_path):
    rt, store, mgr, c = make(db, tmp_path)
    text = "[formulas]\npublic Y\n" + "Y = EXH_BP_R\n" * 80_000  # ~1 MB
    r = c.put("/scripts/huge.fdv", content=text)
    assert r.status_code == 413
    assert "huge.fdv" not in mgr.names()


def test_websocket_commands_need_the_token():
    """The helper a WebSocket route calls before acting on a command."""
    security = Security(token=TOKEN)
    app = FastAPI()

    @app.websocket("/ws")
    async def ws(websocket: WebSocket):
        await websocket.accept()
        command = await websocket.receive_json()
        await websocket.send_json({"allowed": websocket_may_command(websocket, security, command)})
        await websocket.close()

    c = local_client(app)
    for headers, command, allowed in (({}, {"cmd": "x"}, False),
                                      ({}, {"cmd": "x", "token": "wrong"}, False),
                                      ({}, {"cmd": "x", "token": TOKEN}, True),
                                      (GOOD, {"cmd": "x"}, True),
                                      (BAD, {"cmd": "x"}, False)):
        with c.websocket_connect("/ws", headers=headers) as w:
            w.send_json(command)
            assert w.receive_json() == {"allowed": allowed}, (headers, command)


def test_websocket_handshake_needs_the_token_when_reads_are_protected(db, tmp_path):
    from starlette.websockets import WebSocketDisconnect

    rt = Runtime(db, native_filters())
    app = create_app(Cell(runtime=rt), Security(token=TOKEN, protect_reads=True))

    async def hello(websocket: WebSocket):
        await websocket.accept()
        await websocket.send_json({"hello": True})
        await websocket.close()

    app.add_api_websocket_route("/hello", hello)
    c = local_client(app)
    with pytest.raises(WebSocketDisconnect):
        with c.websocket_connect("/hello") as w:
            w.receive_json()
    for kw in ({"headers": GOOD}, {"subprotocols": [f"token.{TOKEN}"]}):
        with c.websocket_connect("/hello", **kw) as w:
            assert w.receive_json() == {"hello": True}
    for kw in ({"subprotocols": ["token.wrong"]}, {"headers": BAD}):
        with pytest.raises(WebSocketDisconnect) as refused:
            with c.websocket_connect("/hello", **kw) as w:
                w.receive_json()
        assert refused.value.code == 1008 and "token.<TOKEN>" in refused.value.reason
