"""``testcell experiment closed-loop``: seed 004's Figure 10 rerun in lockstep, over seeds.

The numbers are measured, not forced: raw feedback must be the worst case (it trips, or it
moves the valve at least 5x as much as Kalman feedback), and at the shipped default gains
the Kalman loop must settle before the moving-average loop (the ratio is printed).
"""

import argparse
import json

import pytest

from cell.app.commands import EXPERIMENTS
from cell.app.cli import main as cli_main
from cell.core.errors import ConfigError
from cell.experiments import backpressure as experiment
from cell.experiments.backpressure import closed_loop, compare

SEEDS = 5


@pytest.fixture(scope="module")
def results():
    summaries, cases = compare(("raw", "maf", "kalman"), seeds=SEEDS, progress=False)
    print()
    print(experiment.format_summaries(summaries))
    return {s.feedback: s for s in summaries}, cases


def test_raw_feedback_is_the_worst_case(results):
    by, _ = results
    raw, kal = by["raw"], by["kalman"]
    ratio = raw.valve_travel_pct / kal.valve_travel_pct
    print(f"valve travel raw/Kalman: {ratio:.1f}x; raw trips {raw.trips}/{raw.seeds}")
    assert raw.tripped or ratio >= 5.0


def test_kalman_settles_before_the_moving_average_at_default_gains(results):
    by, _ = results
    kal, maf = by["kalman"], by["maf"]
    assert kal.settling_time_s is not None, "the Kalman loop never settled"
    ratio = kal.settling_time_s / maf.settling_time_s if maf.settling_time_s else 0.0
    print(f"median settling Kalman {kal.settling_time_s:.1f} s, MA {maf.settling_time_s} s, "
          f"ratio {ratio:.2f} (seed 004: 110/150 = 0.73)")
    assert maf.settling_time_s is None or kal.settling_time_s < maf.settling_time_s
    assert not kal.tripped and not maf.tripped


def test_lockstep_stride_gives_the_same_numbers_as_every_frame(db):
    a = closed_loop("kalman", seed=3, duration=40.0, t_enable=5.0, db=db)
    b = closed_loop("kalman", seed=3, duration=40.0, t_enable=5.0, db=db, stride=1)
    assert a.row() == b.row()


def test_settling_definition():
    import numpy as np

    t = np.arange(0, 30, 0.1)
    x = np.where(t < 5, 600.0, 680.0)
    x[(t > 8) & (t < 9)] = 720.0  # leaves the band once
    assert experiment._settling(t, x, 680.0, 0.03, 10.0) == pytest.approx(9.0)
    assert experiment._settling(t, np.full_like(t, 600.0), 680.0, 0.03, 10.0) is None


def parse(*argv):
    p = argparse.ArgumentParser()
    EXPERIMENTS.add_arguments(p)
    return p.parse_args(["closed-loop", *argv])


def test_json_fields_and_files(tmp_path, capsys):
    args = parse("--feedback", "raw,kalman", "--seeds", "2", "--duration", "30", "--json",
                 "--out", str(tmp_path), "--quiet", "--jobs", "1")
    assert EXPERIMENTS.main(args) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.strip()]
    assert [d["feedback"] for d in lines] == ["raw", "kalman"]
    for d in lines:
        assert isinstance(d["settling_time_s"], (float, type(None)))
        assert isinstance(d["settling_spread_s"], (float, type(None)))
        for key in ("overshoot_pct", "iae", "valve_travel_pct"):
            assert isinstance(d[key], float)
        assert isinstance(d["tripped"], bool)
        assert isinstance(d["fuel_l"], (float, type(None)))
    for name in ("closed_loop.csv", "closed_loop_cases.csv", "closed_loop.png"):
        assert (tmp_path / name).stat().st_size > 0


@pytest.mark.parametrize("argv, option", [
    (("--feedback", "raw,median"), "--feedback"),
    (("--feedback", ""), "--feedback"),
    (("--seeds", "0"), "--seeds"),
    (("--kp", "nan"), "--kp"),
    (("--ki", "-1"), "--ki"),
    (("--gain-map", "--grid-kp", "0.01,x"), "--grid-kp"),
])
def test_bad_options_name_the_option(tmp_path, argv, option):
    args = parse(*argv, "--out", str(tmp_path / "out"))
    with pytest.raises(ConfigError, match=option):
        EXPERIMENTS.main(args)
    assert not (tmp_path / "out").exists()  # refused before any work


def test_unknown_experiment_is_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["experiment", "open-loop"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "open-loop" in err and "closed-loop" in err  # names it and the choices


def test_list_shows_every_registered_experiment_with_its_seed(capsys):
    assert cli_main(["experiment", "--list"]) == 0
    out = capsys.readouterr().out
    assert "closed-loop" in out and "seed 004, Figure 10" in out


def test_each_experiment_has_its_own_help(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["experiment", "closed-loop", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--feedback" in out and "--gain-map" in out
