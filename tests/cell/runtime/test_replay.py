"""Offline replay over candump logs: rows per tick, agreement with the runtime, bad lines."""

import csv

import can
import numpy as np
import pytest

from cell.app.cli import main
from cell.core.errors import ConfigError
from cell.estimators.backpressure import native_filters
from cell.runtime.replay import replay
from cell.runtime.scheduler import Runtime


@pytest.fixture
def log_file(db, tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "cell.log"
    with can.Logger(str(path)) as w:
        for i in range(1000):  # 10 s at 100 Hz
            t = 1000.0 + i * 0.01
            true = 400.0 if i < 500 else 650.0
            w.on_message_received(db.encode("EXH_BP", {"EXH_BP_L": true + rng.normal(0, 50),
                                                      "EXH_BP_R": true + rng.normal(0, 50)}, t))
            w.on_message_received(db.encode("TRUTH_BP", {"EXH_BP_L_TRUE": true, "EXH_BP_R_TRUE": true}, t))
    return path


def test_replay_writes_one_row_per_tick_matching_the_runtime(db, log_file, tmp_path):
    out = tmp_path / "out.csv"
    assert main(["replay", str(log_file), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.DictReader(open(out)))
    assert list(rows[0])[0] == "time"
    assert {"EXH_BP_R", "EXH_BP_R_TRUE", "EXH_BP_R_Kalman", "EXH_BP_R_MAF"} <= set(rows[0])
    times = np.array([float(r["time"]) for r in rows])
    np.testing.assert_allclose(np.diff(times), 0.1, atol=1e-6)
    assert times[0] == pytest.approx(1000.0) and times[-1] == pytest.approx(1009.9)

    # the same frames through a runtime by hand give the same Kalman values
    rt = Runtime(db, native_filters())
    seen = []
    rt.tick_listeners.append(lambda t: seen.append(rt.channels["EXH_BP_R_Kalman"].value))
    for msg in can.LogReader(str(log_file)):
        rt.ingest(msg)
    rt.advance(1009.99)
    np.testing.assert_allclose([float(r["EXH_BP_R_Kalman"]) for r in rows], seen, rtol=1e-15)


def test_replay_channel_selection(log_file, tmp_path):
    out = tmp_path / "out.csv"
    assert main(["replay", str(log_file), "--out", str(out), "--channels", "EXH_BP_R,EXH_BP_R_Kalman",
                 "--quiet"]) == 0
    assert open(out).readline().strip() == "time,EXH_BP_R,EXH_BP_R_Kalman"
    assert main(["replay", str(log_file), "--out", str(out), "--channels", "NOPE", "--quiet"]) == 2


def test_malformed_line_stops_with_its_number_and_keeps_rows(db, log_file, tmp_path, capsys):
    lines = log_file.read_text().splitlines()
    lines.insert(1200, "(1006.000000) can0 1Z1#GARBAGE")
    bad = tmp_path / "bad.log"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out.csv"
    assert main(["replay", str(bad), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:1201" in err
    rows = [r for r in csv.DictReader(open(out)) if not r["time"].startswith("#")]
    assert 55 <= len(rows) <= 61  # 600 frame pairs ~ 6 s of ticks were kept
    result = replay(Runtime(db, native_filters()), bad, None, progress=False)
    assert result.error.line == 1201
    assert result.frames == 1200  # every frame before the bad line was applied


def test_missing_or_unknown_log(tmp_path, db):
    with pytest.raises(ConfigError, match="not found"):
        replay(Runtime(db), tmp_path / "nope.log", None)
    weird = tmp_path / "x.weird"
    weird.write_text("hello")
    with pytest.raises(ConfigError, match="unknown log format"):
        replay(Runtime(db), weird, None)


@pytest.mark.parametrize("suffix", [".parquet", ".mf4"])
def test_replay_writes_parquet_and_mdf4(log_file, tmp_path, suffix):
    csv_out, out = tmp_path / "ref.csv", tmp_path / f"out{suffix}"
    assert main(["replay", str(log_file), "--out", str(csv_out), "--quiet"]) == 0
    assert main(["replay", str(log_file), "--out", str(out), "--quiet"]) == 0
    ref = list(csv.DictReader(open(csv_out)))
    kal = np.array([float(r["EXH_BP_R_Kalman"]) for r in ref])
    if suffix == ".parquet":
        import pyarrow.parquet as pq

        table = pq.read_table(out)
        np.testing.assert_allclose(table.column("EXH_BP_R_Kalman").to_numpy(), kal, rtol=1e-12)
        assert table.schema.metadata[b"unit:EXH_BP_R_Kalman"] == b"mmH2O"
    else:
        from asammdf import MDF

        sig = MDF(out).get("EXH_BP_R_Kalman")
        np.testing.assert_allclose(sig.samples, kal, rtol=1e-12)
        np.testing.assert_allclose(sig.timestamps, [float(r["time"]) for r in ref], atol=1e-6)
        assert sig.unit == "mmH2O"


def test_replay_plot_and_bad_output_format(log_file, tmp_path):
    png = tmp_path / "plot.png"
    assert main(["replay", str(log_file), "--out", str(tmp_path / "o.csv"), "--plot", str(png),
                 "--quiet"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["replay", str(log_file), "--out", str(tmp_path / "o.xlsx"), "--quiet"]) == 2


def test_stopped_replay_says_where_in_the_output(log_file, tmp_path):
    lines = log_file.read_text().splitlines()
    lines.insert(10, "this is not a frame")
    bad = tmp_path / "bad.log"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.csv"
    assert main(["replay", str(bad), "--out", str(out), "--quiet"]) == 1
    assert out.read_text().splitlines()[-1].startswith(f"# stopped at {bad}:11:")


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".trc"])
def test_replay_reads_the_other_python_can_formats(log_file, tmp_path, suffix):
    other = tmp_path / f"cell{suffix}"
    with can.Logger(str(other)) as w:
        for msg in can.LogReader(str(log_file)):
            w.on_message_received(msg)
    ref, out = tmp_path / "ref.csv", tmp_path / "out.csv"
    assert main(["replay", str(log_file), "--out", str(ref), "--quiet"]) == 0
    assert main(["replay", str(other), "--out", str(out), "--quiet"]) == 0
    a = [float(r["EXH_BP_R_Kalman"]) for r in csv.DictReader(open(ref))]
    b = [float(r["EXH_BP_R_Kalman"]) for r in csv.DictReader(open(out))]
    assert len(a) == len(b)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_replay_with_scripts_runs_exactly_those(log_file, tmp_path):
    from cell.scripts import shipped_scripts

    fdv = tmp_path / "kalman.fdv"
    fdv.write_text(dict((n, t) for n, t, _ in shipped_scripts())["kalman.fdv"])
    out = tmp_path / "s.csv"
    assert main(["replay", str(log_file), "--script", str(fdv), "--out", str(out), "--quiet"]) == 0
    cols = open(out).readline().strip().split(",")
    assert "EXH_BP_R_Kalman_FDV" in cols and "EXH_BP_R_Kalman" not in cols and "EXH_BP_R_MAF_CYF" not in cols
    assert main(["replay", str(log_file), "--script", str(fdv), "--native", "--out", str(out),
                 "--quiet"]) == 0
    cols = open(out).readline().strip().split(",")
    assert "EXH_BP_R_Kalman_FDV" in cols and "EXH_BP_R_Kalman" in cols
    # without --script: what testcell up runs, native and shipped side by side
    assert main(["replay", str(log_file), "--out", str(out), "--quiet"]) == 0
    cols = open(out).readline().strip().split(",")
    assert {"EXH_BP_R_Kalman", "EXH_BP_R_Kalman_FDV", "EXH_BP_R_Kalman_CYF", "EXH_BP_R_MAF_CYF"} <= set(cols)


def test_replay_with_a_broken_script_names_its_position(log_file, tmp_path, capsys):
    bad = tmp_path / "bad.fdv"
    bad.write_text("[formulas]\npublic Y\nY = pow(EXH_BP_R, 2\n")
    assert main(["replay", str(log_file), "--script", str(bad), "--out", str(tmp_path / "o.csv")]) == 1
    assert "bad.fdv:3:" in capsys.readouterr().err
    assert main(["replay", str(log_file), "--script", str(tmp_path / "gone.fdv"),
                 "--out", str(tmp_path / "o.csv")]) == 2
