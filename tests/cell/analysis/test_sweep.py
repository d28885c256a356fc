"""Q/R sweeps (seed 004, Tables 1-2, Figures 7-8): the grids, the ranking and the CLI."""

import argparse
import json

import numpy as np
import pytest

from cell.analysis import sweep as sw
from cell.analysis.series import Series
from cell.core.errors import ConfigError
from cell.sim import write_log


# -- grids ------------------------------------------------------------------------------
def test_paper_tables():
    t1, t2 = sw.parse_grid("table1"), sw.parse_grid("TABLE2")
    assert len(t1) == 32 and len(sw.unique_pairs(t1)) == 28
    assert len(t2) == 72 and len(sw.unique_pairs(t2)) == 68
    assert {(1.0, 1e-3), (1e-7, 1e-4), (1e-5, 1e-7), (1e-6, 1.0)} <= set(t1)
    q_half = {(k * 10.0**e, r) for k in range(1, 10) for e in (-6, -5) for r in (1e-3, 1e-4)}
    r_half = {(q, k * 10.0**e) for k in range(1, 10) for e in (-3, -4) for q in (1e-5, 1e-6)}
    close = {(round(q, 15), round(r, 15)) for q, r in t2}
    assert close == {(round(q, 15), round(r, 15)) for q, r in q_half | r_half}
    dup = {p for p in t2 if t2.count(p) > 1}
    assert dup == {(1e-5, 1e-3), (1e-5, 1e-4), (1e-6, 1e-3), (1e-6, 1e-4)}
    assert (3e-6, 1e-4) in t2 and (1e-6, 7e-4) in t2  # exact decimal literals


def test_range_and_list_grids():
    g = sw.parse_grid("Q=1e-7:1e-5:9,R=1e-4:1e-3:2")
    assert len(g) == 18
    qs = sorted({q for q, _ in g})
    np.testing.assert_allclose(np.diff(np.log10(qs)), 0.25)  # log-spaced, ends included
    assert qs[0] == pytest.approx(1e-7) and qs[-1] == pytest.approx(1e-5)
    assert sw.parse_grid("Q=1e-6,2e-6,5e-6,R=1e-4") == [(1e-6, 1e-4), (2e-6, 1e-4), (5e-6, 1e-4)]
    assert sw.parse_grid(" q = 1:3:3:lin ; r=2") == [(1.0, 2.0), (2.0, 2.0), (3.0, 2.0)]


@pytest.mark.parametrize(
    "text, pos, words",
    [
        ("Q=1e-7:1e-5,R=1", 3, "a:b:n"),
        ("Q=abc,R=1", 3, "not a number"),
        ("Q=1,R=0", 7, "> 0"),
        ("Z=1,R=2", 1, "unknown name 'Z'"),
        ("Q=1e-6", 7, "R is missing"),
        ("Q=1,,R=2", 5, "empty value"),
        ("Q=1,R=1,Q=2", 9, "given twice"),
        ("Q=1:2:x,R=1", 7, "whole number"),
        ("tabel2", 1, "not a grid"),
    ],
)
def test_bad_grids_name_the_text_and_position(text, pos, words):
    with pytest.raises(ConfigError) as err:
        sw.parse_grid(text)
    msg = str(err.value)
    assert repr(text) in msg and f"position {pos}:" in msg and words in msg


# -- ranking ---------------------------------------------------------------------------
def test_sweep_ranks_by_rmse_with_truth_and_by_whiteness_without():
    rng = np.random.default_rng(2)
    truth = np.repeat(rng.uniform(100, 700, 12), 300)
    y = truth + rng.normal(0, 60, truth.size)
    pairs = [(q, 1e-4) for q in (1e-8, 1e-6, 1e-5, 1e-4, 1e-2)] + [(1e-6, 1e-4)]
    ranked = sw.sweep(Series.from_arrays(y, truth), pairs)
    assert len(ranked) == 5  # the duplicate is scored once
    assert [r["rank"] for r in ranked] == [1, 2, 3, 4, 5]
    rmse = [r["rmse"] for r in ranked]
    assert rmse == sorted(rmse)
    assert {"Q", "R", "gain", "rmse", "ss_std", "lag_s", "max_err", "whiteness", "nis"} <= set(ranked[0])
    blind = sw.sweep(Series.from_arrays(y), pairs)
    assert "rmse" not in blind[0]
    lb = [r["ljung_box"] for r in blind]
    assert lb == sorted(lb)


# -- command line -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "transient.log"
    write_log(path, "transient", seed=5, duration=80.0, progress=False)
    return path


def run_cli(argv):
    parser = argparse.ArgumentParser()
    sw.add_arguments(parser)
    return sw.main(parser.parse_args(argv))


def test_cli_writes_csv_png_jsonl_and_prints_json(small_log, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli([str(small_log), "--channel", "EXH_BP_R", "--grid", "table2",
                    "--out-dir", str(out), "--quiet", "--top", "5"]) == 0
    text = capsys.readouterr().out
    assert "72 pairs listed, 68 distinct" in text and "reference MAF-30" in text
    for suffix in ("csv", "png", "jsonl"):
        assert (out / f"sweep_EXH_BP_R.{suffix}").stat().st_size > 0
    header = (out / "sweep_EXH_BP_R.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["rank", "Q", "R", "gain"] and "rmse" in header

    assert run_cli([str(small_log), "--grid", "Q=1e-7:1e-4:7,R=1e-4", "--out-dir", str(out),
                    "--quiet", "--json", "--no-plot"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    rows = [json.loads(line) for line in lines]
    assert len(rows) == 7
    for row in rows:
        assert {"Q", "R", "rmse", "ss_std", "lag_s", "max_err", "whiteness", "nis"} <= set(row)
    assert [r["rmse"] for r in rows] == sorted(r["rmse"] for r in rows)


def test_cli_refuses_a_bad_grid_before_reading_the_log(tmp_path):
    with pytest.raises(ConfigError, match="position"):
        run_cli([str(tmp_path / "missing.log"), "--grid", "Q=1:2,R=1"])


def test_cli_writes_no_file_unless_asked_and_prints_the_paths(small_log, tmp_path, capsys,
                                                              monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run_cli([str(small_log), "--grid", "Q=1e-6,R=1e-4", "--quiet"]) == 0
    assert list(tmp_path.iterdir()) == []  # nothing in the working directory
    assert "wrote" not in capsys.readouterr().err
    out = tmp_path / "res"
    assert run_cli([str(small_log), "--grid", "Q=1e-6,R=1e-4", "--quiet", "--out-dir", str(out)]) == 0
    err = capsys.readouterr().err
    written = sorted(p.name for p in out.iterdir())
    assert written == ["sweep_EXH_BP_R.csv", "sweep_EXH_BP_R.jsonl", "sweep_EXH_BP_R.png"]
    for name in written:
        assert f"wrote {out / name}" in err


def test_help_says_json_is_json_lines():
    parser = argparse.ArgumentParser()
    sw.add_arguments(parser)
    assert "JSON Lines" in " ".join(parser.format_help().split())
