"""A user's signals drive the cell's blocks (issue 24, point 2: ``--map CELL_CHANNEL=SIGNAL``).

The oracle of the conversions is scipy.constants (published CODATA/NIST values), of the
filter filterpy's Kalman filter, of the payloads cantools."""

import math

import numpy as np
import pytest
import scipy.constants as sc
from filterpy.kalman import KalmanFilter

from cell.app import cli
from cell.bus.dbc import load
from cell.core.errors import ConfigError
from cell.estimators.backpressure import native_filters
from cell.runtime import mapping
from cell.runtime.scheduler import Runtime
from pathlib import Path

DAQ = Path(__file__).resolve().parents[2] / "data" / "dbc" / "daq_kpa.dbc"
MMH2O_PA = sc.g * 1000.0 * 1e-3  # 1 mmH2O (conventional): 1000 kg/m^3, standard gravity, 1 mm


@pytest.fixture(scope="module")
def daq_db():
    return load([DAQ])


# -- unit conversion against published factors ---------------------------------------------
@pytest.mark.parametrize("src, dst, value, expect", [
    ("kPa", "mmH2O", 6.67, 6.67e3 / MMH2O_PA),
    ("bar", "mmH2O", 0.0667, 0.0667 * sc.bar / MMH2O_PA),
    ("psi", "kPa", 1.0, sc.psi / 1e3),
    ("mmH2O", "Pa", 680.0, 680.0 * MMH2O_PA),
    ("inH2O", "mmH2O", 1.0, 25.4),
    ("mmHg", "Pa", 1.0, sc.mmHg),
    ("atm", "kPa", 1.0, sc.atm / 1e3),
    ("degC", "K", 25.0, sc.convert_temperature(25.0, "Celsius", "Kelvin")),
    ("K", "degC", 300.0, sc.convert_temperature(300.0, "Kelvin", "Celsius")),
    ("degF", "degC", 212.0, sc.convert_temperature(212.0, "Fahrenheit", "Celsius")),
    ("°C", "degF", -40.0, sc.convert_temperature(-40.0, "Celsius", "Fahrenheit")),
    ("rpm", "rad/s", 1800.0, 1800.0 * 2 * sc.pi / sc.minute),
    ("krpm", "rpm", 1.8, 1800.0),
    ("%", "ppm", 1.0, 1e4),
    ("kg/h", "g/s", 36.0, 10.0),
    ("MM_H2O", "mmh2o", 5.0, 5.0),  # one unit, two spellings
])
def test_a_conversion_matches_the_published_factor(src, dst, value, expect):
    scale, offset = mapping.conversion(src, dst)
    assert value * scale + offset == pytest.approx(expect, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("src, dst", [("V", "mmH2O"), ("kPa", "degC"), ("", "mmH2O"),
                                      ("rpm", "%")])
def test_an_unknown_unit_pair_has_no_conversion(src, dst):
    assert mapping.conversion(src, dst) is None


# -- the acceptance case: seed 004's Kalman filter on a DAQ's kPa channel --------------------
def trace(n: int = 3000, seed: int = 4) -> np.ndarray:
    """A back-pressure trace, mmH2O, at 100 Hz: 680 with a step to 900, and sensor noise."""
    rng = np.random.default_rng(seed)
    p = np.where(np.arange(n) < n // 2, 680.0, 900.0)
    return p + rng.normal(0.0, 60.0, n)


def run(db, frames, maps=()):
    rt = Runtime(db, native_filters())
    if maps:
        mapping.install(rt, maps)
    out = []
    rt.tick_listeners.append(lambda t: out.append(
        (t, rt.channels["EXH_BP_R_Kalman"].value, rt.channels["EXH_BP_R_Kalman"].status)))
    rt.ingest_many(frames)
    return rt, out


@pytest.fixture(scope="module")
def both_ways(daq_db):
    """The same pressure trace as the cell's EXH_BP (mmH2O) and as the DAQ's DAQ_BP (kPa)."""
    p = trace()
    t = np.arange(p.size) * 0.01 + 0.003
    own = [daq_db.encode("EXH_BP", {"EXH_BP_L": 0.0, "EXH_BP_R": v}, ts) for v, ts in zip(p, t)]
    kpa = [daq_db.encode("DAQ_BP", {"DAQ_BP_L": 0.0, "DAQ_BP_R": v * MMH2O_PA / 1e3}, ts)
           for v, ts in zip(p, t)]
    rt_own, a = run(daq_db, own)
    rt_map, b = run(daq_db, kpa, ["EXH_BP_R=DAQ_BP_R"])
    return p, own, rt_own, a, rt_map, b


def test_the_kalman_filter_on_a_mapped_kpa_channel_matches_the_cells_own_mmh2o(both_ways, daq_db):
    p, own, rt_own, a, rt_map, b = both_ways
    assert len(a) == len(b) > 250
    ta, ya, sa = zip(*a)
    tb, yb, sb = zip(*b)
    assert ta == tb and set(sa) == {"ok"} == set(sb)
    ya, yb = np.array(ya), np.array(yb)
    # the two payloads quantise at 0.01 mmH2O and 0.0001 kPa (0.0102 mmH2O): half of each
    assert np.max(np.abs(ya - yb)) < 0.011
    assert rt_map.channels["EXH_BP_R"].unit == "mmH2O"
    # and both are seed 004's filter: filterpy on the mmH2O samples the ticks saw
    frame_t = np.array([f.timestamp for f in own])
    raw = np.array([daq_db.decode(f)[1]["EXH_BP_R"] for f in own])
    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.F = kf.H = np.eye(1)
    kf.Q, kf.R = np.eye(1) * 1e-6, np.eye(1) * 1e-4
    ref = []
    for tick in ta:
        z = raw[np.searchsorted(frame_t, tick, side="right") - 1]
        if not ref:
            kf.x, kf.P = np.array([[z]]), np.eye(1)
        else:
            kf.predict()
            kf.update(z)
        ref.append(float(kf.x[0, 0]))
    np.testing.assert_allclose(ya, ref, rtol=0, atol=1e-6)


def test_the_mapped_channel_has_the_sources_bus_time(both_ways):
    p, own, rt_own, a, rt_map, b = both_ways
    ch = rt_map.channels["EXH_BP_R"]
    assert ch.t == pytest.approx(own[-1].timestamp)
    assert ch.value == pytest.approx(rt_own.channels["EXH_BP_R"].value, abs=0.011)
    assert "DAQ_BP_R" in rt_map.channels  # the source stays a channel of its own, in kPa
    assert rt_map.channels["DAQ_BP_R"].unit == "kPa"


def test_a_stale_source_makes_the_mapped_channel_and_its_filter_stale(daq_db):
    frames = [daq_db.encode("DAQ_BP", {"DAQ_BP_L": 0.0, "DAQ_BP_R": 6.67}, k * 0.01 + 0.003)
              for k in range(200)]
    rt, out = run(daq_db, frames, ["EXH_BP_R=DAQ_BP_R"])
    assert out[-1][2] == "ok"
    rt.advance(frames[-1].timestamp + 0.5)  # the DAQ's frames stop (10 ms cycle)
    status, reason = rt.channels["EXH_BP_R"].status_at(rt.now)
    assert status == "stale" and "no frame" in reason
    assert rt.channels["EXH_BP_R_Kalman"].status == "stale"


def test_an_implausible_source_makes_the_mapped_channel_invalid(daq_db):
    m = daq_db.message("DAQ_BP")
    good = [daq_db.encode("DAQ_BP", {"DAQ_BP_L": 0.0, "DAQ_BP_R": 6.67}, k * 0.01 + 0.003)
            for k in range(50)]
    bad = good[-1].__class__(arbitration_id=m.frame_id, is_extended_id=False,
                             timestamp=0.503, data=m.encode({"DAQ_BP_L": 0.0, "DAQ_BP_R": 300.0},
                                                            strict=False))
    rt, out = run(daq_db, [*good, bad], ["EXH_BP_R=DAQ_BP_R"])
    rt.advance(0.65)
    ch = rt.channels["EXH_BP_R"]
    assert ch.status == "invalid" and "DAQ_BP_R" in ch.reason and "300" in ch.reason
    assert rt.channels["EXH_BP_R_Kalman"].status == "invalid"


def test_a_mapped_channel_ignores_frames_of_its_own_name(daq_db):
    """The mapping is a channel's one source: the simulator's EXH_BP_R is not read into it."""
    frames = []
    for k in range(100):
        ts = k * 0.01 + 0.003
        frames.append(daq_db.encode("DAQ_BP", {"DAQ_BP_L": 0.0, "DAQ_BP_R": 6.67}, ts))
        frames.append(daq_db.encode("EXH_BP", {"EXH_BP_L": 0.0, "EXH_BP_R": 1.0}, ts + 0.001))
    rt, out = run(daq_db, frames, ["EXH_BP_R=DAQ_BP_R"])
    assert rt.channels["EXH_BP_R"].value == pytest.approx(6.67e3 / MMH2O_PA, abs=0.011)


def test_an_explicit_scale_and_offset_win(daq_db):
    frames = [daq_db.encode("DAQ_RAW", {"DAQ_BP_R_V": 2.5, "DAQ_BP_R_NOUNIT": 0.0},
                            k * 0.01 + 0.003) for k in range(30)]
    rt, out = run(daq_db, frames, ["EXH_BP_R=DAQ_BP_R_V*400-300"])
    assert rt.channels["EXH_BP_R"].value == pytest.approx(2.5 * 400 - 300)
    assert out[-1][1] == pytest.approx(700.0)


# -- refusals at start -------------------------------------------------------------------
@pytest.mark.parametrize("spec, words", [
    ("EXH_BP_R=DAQ_BP_R_V", ["EXH_BP_R=DAQ_BP_R_V", "'V'", "'mmH2O'", "*SCALE+OFFSET"]),
    ("EXH_BP_R=DAQ_BP_R_NOUNIT", ["''", "'mmH2O'"]),
    ("EXH_BP_R=NOPE", ["no loaded DBC file has a signal NOPE"]),
    ("NOPE=DAQ_BP_R", ["no block of this cell reads NOPE", "EXH_BP_L, EXH_BP_R"]),
    ("EXH_BP_R_Kalman=DAQ_BP_R", ["EXH_BP_R_Kalman is an output"]),
    ("EXH_BP_R=DAQ_BP_R*0", ["scale", "other than 0"]),
    ("EXH_BP_R=DAQ BP", ["is not SIGNAL"]),
    ("EXH_BP_R=", ["is not SIGNAL"]),
    ("EXH_BP_R", ["--map EXH_BP_R: cannot read"]),  # no '=': a mapping file
])
def test_a_bad_mapping_is_refused_naming_the_entry(daq_db, spec, words):
    rt = Runtime(daq_db, native_filters())
    with pytest.raises(ConfigError) as exc:
        mapping.install(rt, [spec])
    text = str(exc.value)
    assert all(w in text for w in words), text
    assert not rt.signal_map  # nothing half installed


def test_a_channel_mapped_twice_is_refused_naming_both(daq_db):
    rt = Runtime(daq_db, native_filters())
    with pytest.raises(ConfigError, match="EXH_BP_R is already mapped by --map 'EXH_BP_R=DAQ_BP_R'"):
        mapping.install(rt, ["EXH_BP_R=DAQ_BP_R", "EXH_BP_R=DAQ_BP_L"])


def test_message_dot_signal_names_a_source(daq_db):
    rt = Runtime(daq_db, native_filters())
    (e,) = mapping.install(rt, ["EXH_BP_L=DAQ_BP.DAQ_BP_L"]).entries
    assert (e.message, e.signal) == ("DAQ_BP", "DAQ_BP_L")
    assert e.scale == pytest.approx(1e3 / MMH2O_PA)


def test_a_mapping_file_in_yaml_and_its_errors_name_the_line(daq_db, tmp_path):
    good = tmp_path / "map.yaml"
    good.write_text("# my DAQ\nEXH_BP_R: DAQ_BP_R\nEXH_BP_L: DAQ_BP_L*101.97+0\n")
    rt = Runtime(daq_db, native_filters())
    entries = mapping.install(rt, [str(good)]).entries
    assert [(e.target, e.source, e.explicit) for e in entries] == [
        ("EXH_BP_R", "DAQ_BP_R", False), ("EXH_BP_L", "DAQ_BP_L", True)]
    assert entries[1].scale == 101.97
    bad = tmp_path / "bad.yaml"
    bad.write_text("EXH_BP_R: DAQ_BP_R\n\nEXH_BP_L: DAQ_BP_R_V\n")
    with pytest.raises(ConfigError) as exc:
        mapping.install(Runtime(daq_db, native_filters()), [str(bad)])
    assert f"{bad} line 3, entry EXH_BP_L" in str(exc.value) and "'V'" in str(exc.value)
    listed = tmp_path / "list.json"
    listed.write_text('[{"channel": "EXH_BP_R", "signal": "DAQ_BP_R_V", "scale": 400, '
                      '"offset": -300}, {"channel": "EXH_BP_L", "sigal": "DAQ_BP_L"}]')
    with pytest.raises(ConfigError, match=r"entry 2: unknown key 'sigal'"):
        mapping.read_file(listed)
    with pytest.raises(ConfigError, match="cannot read"):
        mapping.read_file(tmp_path / "missing.yaml")


# -- the command line --------------------------------------------------------------------
@pytest.fixture(scope="module")
def kpa_log(tmp_path_factory, daq_db):
    import can

    path = tmp_path_factory.mktemp("map") / "daq.log"
    p = trace(600)
    with can.Logger(str(path)) as w:
        for k, v in enumerate(p):
            w.on_message_received(daq_db.encode(
                "DAQ_BP", {"DAQ_BP_L": v * MMH2O_PA / 1e3, "DAQ_BP_R": v * MMH2O_PA / 1e3},
                1000.0 + k * 0.01))
    return path


def test_replay_takes_map_and_writes_the_filtered_mapped_channel(kpa_log, tmp_path, capsys):
    import csv

    out = tmp_path / "out.csv"
    code = cli.main(["replay", str(kpa_log), "--out", str(out), "--quiet", "--engine",
                     "large-diesel", "--dbc", str(DAQ), "--map", "EXH_BP_R=DAQ_BP_R",
                     "--map", "EXH_BP_L=DAQ_BP_L"])
    assert code == 0, capsys.readouterr().err
    rows = list(csv.DictReader(out.open()))
    last = rows[-1]
    assert math.isfinite(float(last["EXH_BP_R_Kalman"]))
    assert float(last["EXH_BP_R"]) == pytest.approx(float(last["DAQ_BP_R"]) * 1e3 / MMH2O_PA,
                                                    abs=0.011)


def test_sweep_takes_map(kpa_log, capsys):
    code = cli.main(["sweep", str(kpa_log), "--quiet", "--dbc", str(DAQ), "--grid",
                     "Q=1e-6,R=1e-4", "--map", "EXH_BP_R=DAQ_BP_R"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "EXH_BP_R" in out.out


@pytest.mark.parametrize("spec, words", [
    ("NOPE=DAQ_BP_R", "no block of this cell reads NOPE"),
    ("EXH_BP_R=NOPE", "no loaded DBC file has a signal NOPE"),
])
def test_replay_refuses_a_bad_map_with_exit_2_naming_it(kpa_log, tmp_path, capsys, spec, words):
    code = cli.main(["replay", str(kpa_log), "--out", str(tmp_path / "o.csv"), "--quiet",
                     "--engine", "large-diesel", "--dbc", str(DAQ), "--map", spec])
    err = capsys.readouterr().err
    assert code == 2 and words in err and spec in err, err


def test_up_refuses_a_bad_map_with_exit_2_before_serving(monkeypatch, tmp_path, capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    code = cli.main(["up", "--no-sim", "--bus", "virtual", "--port", str(port), "--dbc",
                     str(DAQ), "--map", "EXH_BP_R=DAQ_BP_R", "--map", "VALVE_DEMAND_R=DAQ_BP_L"])
    err = capsys.readouterr().err
    assert code == 2 and "--map 'VALVE_DEMAND_R=DAQ_BP_L'" in err and "is an output" in err, err
