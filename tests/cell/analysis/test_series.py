"""A channel of a CAN log as a series: sampled as the runtime's blocks see it (stale ticks
included), clear errors for a missing channel or a malformed line, and the shared log options."""

import argparse

import can
import numpy as np
import pytest

from cell.analysis import series as se
from cell.core.errors import ConfigError, LogFormatError
from cell.estimators.backpressure import kalman_bank, native_filters
from cell.sim import simulate
from cell.runtime.scheduler import Runtime


@pytest.fixture(scope="module")
def gap_log(db, tmp_path_factory):
    """20 s of the transient cycle from t = 30 s, with 1.5 s of EXH_BP frames missing."""
    path = tmp_path_factory.mktemp("gap") / "gap.log"
    with can.Logger(str(path)) as w:
        for msg in simulate(db, "transient", seed=3, duration=50.0):
            if msg.timestamp < 30.0:
                continue
            if 40.0 <= msg.timestamp < 41.5 and msg.arbitration_id == 257:
                continue
            w.on_message_received(msg)
    return path


def test_bank_over_a_log_equals_the_runtime_kalman_output(db, gap_log):
    series = se.channel_series(gap_log, "EXH_BP_R", progress=False)
    assert series.truth_channel == "EXH_BP_R_TRUE"
    assert np.isnan(series.y).sum() > 5  # the gap went stale
    rt = Runtime(db, native_filters())
    got = []

    def on_tick(t):
        ch = rt.channels["EXH_BP_R_Kalman"]
        got.append(ch.value if ch.status_at(t)[0] == "ok" else np.nan)

    rt.tick_listeners.append(on_tick)
    last = None
    for msg in can.LogReader(str(gap_log)):
        rt.ingest(msg)
        last = msg.timestamp
    rt.advance(last)
    x, _, _ = kalman_bank(series.y, 1e-6, 1e-4)
    np.testing.assert_allclose(x[:, 0], np.array(got), atol=1e-9, equal_nan=True)


def test_missing_channel_is_named_with_the_channels_the_log_has(gap_log):
    with pytest.raises(ConfigError) as err:
        se.channel_series(gap_log, "EXH_BP_X", progress=False)
    assert "EXH_BP_X" in str(err.value) and "EXH_BP_R_TRUE" in str(err.value)
    with pytest.raises(ConfigError, match="NOPE"):
        se.channel_series(gap_log, "EXH_BP_R", truth="NOPE", progress=False)


def test_malformed_log_line_gives_its_line_number(gap_log, tmp_path):
    lines = gap_log.read_text().splitlines(keepends=True)
    lines[99] = "(31.000000) vcan0 101#zz\n"
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines))
    with pytest.raises(LogFormatError) as err:
        se.channel_series(bad, "EXH_BP_R", progress=False)
    assert err.value.line == 100 and ":100:" in str(err.value)


def log_options_parser():
    parser = argparse.ArgumentParser()
    parser.add_argument("log")
    parser.add_argument("--channel", default="EXH_BP_R")
    se.add_log_options(parser)
    return parser


def test_log_options_take_repeatable_dbc_and_default_to_the_cells(gap_log, tmp_path):
    parser = log_options_parser()
    args = parser.parse_args([str(gap_log), "--quiet", "--dbc", "a.dbc", "--dbc", "more/"])
    assert args.dbc == ["a.dbc", "more/"]
    plain = parser.parse_args([str(gap_log), "--quiet"])
    assert plain.dbc is None
    np.testing.assert_array_equal(
        se.load_series(plain).y, se.channel_series(gap_log, "EXH_BP_R", progress=False).y)
    missing = [str(tmp_path / "missing_a.dbc"), str(tmp_path / "missing_b.dbc")]
    with pytest.raises(ConfigError, match="missing_"):
        se.load_series(parser.parse_args([str(gap_log), "--quiet", "--dbc", missing[0],
                                          "--dbc", missing[1]]))
