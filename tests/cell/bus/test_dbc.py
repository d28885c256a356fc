"""Several DBC files in one catalogue: the cell's own, plugins' and a user's (``--dbc``)."""

import csv
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import can
import pytest

import cell.bus.dbc as dbc_mod
from cell.core import registry
from cell.app.cli import main
from cell.bus.dbc import CellDatabase, cell_dbc_paths, default_dbc_path, load, resolve_dbc_paths
from cell.core.errors import ConfigError
from cell.estimators.backpressure import MovingAverage
from cell.runtime.scheduler import Runtime

DATA = Path(__file__).resolve().parents[2] / "data" / "dbc"
USER = DATA / "user.dbc"
ROOT = Path(__file__).resolve().parents[3]
EEC1_ID = 0x0CF004FE  # J1939 EEC1 from source 0xFE, an extended frame


def user_frames(db, t):
    """One ECU and one DAQ frame of the user's DBC at bus time ``t``, encoded independently
    of cantools: EEC1 bytes 3-4 are speed / 0.125 rpm; DAQ_TEMPS is (T + 40) / 0.1 degC."""
    speed = int(1500.0 / 0.125).to_bytes(2, "little")
    oil, coolant = (int(round((v + 40.0) / 0.1)).to_bytes(2, "little") for v in (93.4, 81.0))
    return [
        can.Message(timestamp=t, arbitration_id=EEC1_ID, is_extended_id=True,
                    data=b"\xff\xff\xff" + speed + b"\xff\xff\xff"),
        can.Message(timestamp=t, arbitration_id=0x500, is_extended_id=False, data=oil + coolant),
    ]


def write_dbc(path, frame_id, message, signal):
    path.write_text(f'VERSION ""\n\nBS_:\n\nBU_: DAQ\n\nBO_ {frame_id} {message}: 2 DAQ\n'
                    f' SG_ {signal} : 0|16@1+ (1,0) [0|60000] "" Vector__XXX\n')
    return path


@pytest.fixture
def clean_registry(monkeypatch):
    monkeypatch.setattr(registry, "DBC_FILES", [])


# -- the cell's set ------------------------------------------------------------------------
def test_cell_set_is_testcell_dbc_first(db):
    assert db.path == default_dbc_path() == db.files[0]
    assert db.file_of("EXH_BP") == db.path and db.signals["EXH_BP_L"].file == db.path
    assert [m.name for m in db.messages] == [m.name for m in db.db.messages]
    assert load() is load(()) is load(None)  # cached


def test_a_second_file_in_the_dbc_folder_is_loaded(tmp_path, monkeypatch, clean_registry):
    folder = tmp_path / "dbc"
    folder.mkdir()
    shutil.copy(default_dbc_path(), folder / "testcell.dbc")
    shutil.copy(USER, folder / "aaa_ecu.dbc")  # sorts before testcell.dbc
    monkeypatch.setattr(dbc_mod, "dbc_dir", lambda: folder)
    db = load()
    assert [p.name for p in db.files] == ["testcell.dbc", "aaa_ecu.dbc"]
    assert db.path.name == "testcell.dbc"
    assert db.file_of("EEC1") == folder / "aaa_ecu.dbc"
    message, values = db.decode(user_frames(db, 0.0)[0])
    assert message.name == "EEC1" and values == {"ECU_ENGINE_SPEED": 1500.0}
    assert db.decode(db.encode("EXH_BP", {"EXH_BP_L": 500, "EXH_BP_R": 600}))[1] == {
        "EXH_BP_L": 500.0, "EXH_BP_R": 600.0}


def test_registered_dbc_files_are_loaded(tmp_path, clean_registry):
    own = cell_dbc_paths()
    assert own[0] == default_dbc_path() and USER not in own
    registry.dbc_file(USER)
    assert load().files == own  # the catalogue is handed the registered files, it does not look
    db = load(registry.DBC_FILES)
    assert db.files == [*own, USER]
    assert db.signals["DAQ_OIL_TEMP"].file == USER and db.signals["DAQ_OIL_TEMP"].unit == "degC"
    registry.DBC_FILES.clear()
    assert load().files == own


# -- a user's files ------------------------------------------------------------------------
@pytest.fixture(params=["file", "folder"])
def user_extra(request, tmp_path):
    if request.param == "file":
        return (USER,)
    folder = tmp_path / "mine"
    folder.mkdir()
    shutil.copy(USER, folder / "user.dbc")
    return (str(folder),)


def test_user_frames_decode_into_channels_and_feed_a_filter(user_extra, clean_registry, tmp_path):
    from cell.app.cell import Cell
    from cell.app.tuning import TuningStore
    from service.main import create_app
    from tests.helpers.client import local_client

    db = load(user_extra)
    assert db.files[0] == default_dbc_path() and db.files[-1].name == "user.dbc"
    rt = Runtime(db, [MovingAverage("DAQ_OIL_TEMP_MAF", "DAQ_OIL_TEMP", samples=2)])
    for msg in user_frames(db, 0.0):
        rt.ingest(msg)
    rt.ingest(db.encode("DAQ_TEMPS", {"DAQ_OIL_TEMP": 100.0, "DAQ_COOLANT_TEMP": 81.0}, 0.1))
    rt.advance(0.1)
    ch = rt.channels
    assert ch["ECU_ENGINE_SPEED"].value == 1500.0 and ch["ECU_ENGINE_SPEED"].unit == "rpm"
    assert ch["DAQ_COOLANT_TEMP"].value == pytest.approx(81.0) and ch["DAQ_COOLANT_TEMP"].unit == "degC"
    assert ch["DAQ_OIL_TEMP"].value == pytest.approx(100.0)
    assert ch["DAQ_OIL_TEMP_MAF"].value == pytest.approx((93.4 + 100.0) / 2)
    assert ch["DAQ_OIL_TEMP_MAF"].unit == "degC"
    assert rt.decode_errors["unknown_id"] == 0

    store = TuningStore(tmp_path / "tuning.json")
    store.load()
    client = local_client(create_app(Cell(runtime=rt, bus="virtual:test", tuning=store)))
    listed = {c["name"]: c for c in client.get("/channels").json()}
    assert listed["ECU_ENGINE_SPEED"]["value"] == 1500.0 and listed["ECU_ENGINE_SPEED"]["unit"] == "rpm"


def test_replay_with_user_dbc_writes_its_signals(db, tmp_path, clean_registry):
    more = tmp_path / "more"
    more.mkdir()
    write_dbc(more / "rig.dbc", 0x600, "RIG", "RIG_HUMIDITY")
    log = tmp_path / "cell.log"
    with can.Logger(str(log)) as w:
        for i in range(30):
            t = 100.0 + i * 0.01
            for msg in [*user_frames(db, t),
                        db.encode("EXH_BP", {"EXH_BP_L": 600.0, "EXH_BP_R": 610.0}, t)]:
                w.on_message_received(msg)
            w.on_message_received(can.Message(timestamp=t, arbitration_id=0x600,
                                              is_extended_id=False, data=(55).to_bytes(2, "little")))
    out = tmp_path / "out.csv"
    assert main(["replay", str(log), "--dbc", str(USER), "--dbc", str(more), "--out", str(out),
                 "--quiet"]) == 0
    rows = list(csv.DictReader(open(out)))
    assert float(rows[-1]["ECU_ENGINE_SPEED"]) == 1500.0
    assert float(rows[-1]["DAQ_OIL_TEMP"]) == pytest.approx(93.4)
    assert float(rows[-1]["RIG_HUMIDITY"]) == 55.0
    assert float(rows[-1]["EXH_BP_R"]) == pytest.approx(610.0)


# -- collisions ----------------------------------------------------------------------------
COLLISIONS = {
    "collide_id.dbc": ["frame ID 0x101", "EXH_BP", "DAQ_PRESSURES"],
    "collide_signal.dbc": ["signal EXH_BP_L", "EXH_BP (0x101)", "DAQ_BP (0x501)"],
    "collide_message.dbc": ["message EXH_BP", "0x101", "0x502"],
}


@pytest.mark.parametrize("name", COLLISIONS)
def test_a_collision_with_the_cells_frames_names_both_files(name, clean_registry):
    with pytest.raises(ConfigError) as err:
        load((DATA / name,))
    text = str(err.value)
    for needle in [*COLLISIONS[name], str(default_dbc_path()), str(DATA / name)]:
        assert needle in text
    assert "\n" not in text


def test_a_collision_between_two_user_files_names_both(tmp_path, clean_registry):
    a = write_dbc(tmp_path / "a.dbc", 0x7A0, "RIG_A", "RIG_A1")
    b = write_dbc(tmp_path / "b.dbc", 0x7A0, "RIG_B", "RIG_B1")
    with pytest.raises(ConfigError, match=r"frame ID 0x7A0 is defined twice: RIG_A in .*a\.dbc "
                                          r"and RIG_B in .*b\.dbc"):
        load((a, b))
    # the same file named twice (or the cell's own named again) is not a collision
    assert load((a, str(a), default_dbc_path())).files == [*cell_dbc_paths(), a]


def test_a_signal_twice_in_one_file_keeps_its_error(tmp_path):
    p = tmp_path / "dup.dbc"
    p.write_text('VERSION ""\n\nBS_:\n\nBU_: DAQ\n\n'
                 'BO_ 1536 A: 2 DAQ\n SG_ X : 0|16@1+ (1,0) [0|1] "" Vector__XXX\n\n'
                 'BO_ 1537 B: 2 DAQ\n SG_ X : 0|16@1+ (1,0) [0|1] "" Vector__XXX\n')
    with pytest.raises(ConfigError, match=f"{p}: signal X is defined twice"):
        CellDatabase([p])


def _run_cell(*argv, timeout=60):
    return subprocess.run([sys.executable, "-m", "cell", *argv], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def test_cli_refuses_a_colliding_dbc_in_one_line(db, tmp_path):
    log = tmp_path / "cell.log"
    with can.Logger(str(log)) as w:
        w.on_message_received(db.encode("EXH_BP", {"EXH_BP_L": 1.0, "EXH_BP_R": 1.0}, 1.0))
    bad = str(DATA / "collide_id.dbc")
    r = _run_cell("replay", str(log), "--dbc", bad, "--out", str(tmp_path / "x.csv"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("testcell replay: frame ID 0x101") and bad in line
    assert not (tmp_path / "x.csv").exists()

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = _run_cell("up", "--dbc", bad, "--no-sim", "--bus", "virtual", "--port", str(port),
                  "--state", str(tmp_path / "tuning.json"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("testcell up: frame ID 0x101") and bad in line


# -- bad paths -----------------------------------------------------------------------------
def test_missing_path_or_empty_folder_is_named(db, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match=f"--dbc {empty}: folder holds no .dbc file"):
        resolve_dbc_paths([empty])
    with pytest.raises(ConfigError, match="--dbc nope.dbc: no such file or folder"):
        load(("nope.dbc",))
    log = tmp_path / "cell.log"
    log.write_text("")
    assert main(["replay", str(log), "--dbc", str(tmp_path / "gone.dbc"),
                 "--out", str(tmp_path / "x.csv")]) == 2
    assert f"--dbc {tmp_path / 'gone.dbc'}: no such file" in capsys.readouterr().err


def test_an_unparsable_dbc_is_named_with_the_reason(tmp_path):
    p = tmp_path / "broken.dbc"
    p.write_text('VERSION ""\n\nBO_ 12 X: 8 DAQ\n SG_ A : 0|8@1+ (1,0) [0|1] "" X {{{\n')
    with pytest.raises(ConfigError, match=f"{p}: cannot load DBC: .*line 4") as err:
        load((p,))
    assert "\n" not in str(err.value)


# -- cantools itself -----------------------------------------------------------------------
@pytest.mark.parametrize("path", sorted((ROOT / "dbc").glob("*.dbc")) + [USER], ids=lambda p: p.name)
def test_cantools_dump_works_on_each_file(path):
    r = subprocess.run([sys.executable, "-m", "cantools", "dump", str(path)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "Messages" in r.stdout


def test_encode_clamps_to_the_dbc_range_and_refuses_nan(db):
    from cantools.database import EncodeError

    msg = db.encode("EXH_BP", {"EXH_BP_L": -1e9, "EXH_BP_R": 1e9})
    sig = {s.name: s for s in db.message("EXH_BP").signals}
    assert db.decode(msg)[1] == {"EXH_BP_L": sig["EXH_BP_L"].minimum, "EXH_BP_R": sig["EXH_BP_R"].maximum}
    with pytest.raises(EncodeError, match="EXH_BP_L is NaN"):
        db.encode("EXH_BP", {"EXH_BP_L": float("nan"), "EXH_BP_R": 600.0})
