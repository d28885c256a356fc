"""Running-average statistics (seed 004, Figure 2) against numpy on random data."""

import math

import numpy as np
import pytest

from cell.core.errors import ParamError
from cell.scripts import SUFFIXES, RunningStats


def numpy_stats(ts, vs, rate):
    t, v = np.asarray(ts, float), np.asarray(vs, float)
    n = len(v)
    tau = t - t[0]
    if n >= 2 and np.ptp(tau) > 0:
        cl, co = np.polyfit(tau, v, 1)
    else:
        cl, co = 0.0, float(np.mean(v))
    if n >= 3:
        resid = v - (co + cl * tau)
        es = float(np.sum(resid**2) / (n - 2))
        eo = math.sqrt(es)
        el = eo / math.sqrt(float(np.sum((tau - tau.mean()) ** 2)))
    else:
        es = eo = el = 0.0
    sd = float(np.std(v, ddof=1)) if n > 1 else 0.0
    return {
        "AV": np.mean(v), "MN": v.min(), "MX": v.max(), "RN": np.ptp(v), "SD": sd,
        "CV": sd / np.mean(v), "ST": t[0], "EN": t[-1], "TN": t[np.argmin(v)],
        "TX": t[np.argmax(v)], "IV": v[0], "FV": v[-1], "DL": v[-1] - v[0],
        "IN": np.sum(v) / rate, "IT": np.trapezoid(v, t) if n > 1 else 0.0,
        "ES": es, "EO": eo, "EL": el, "CL": cl, "CO": co, "RA": rate, "NM": n,
    }


@pytest.mark.parametrize("window", [1, 2, 3, 30])
def test_every_statistic_matches_numpy_including_before_full(window):
    rng = np.random.default_rng(window)
    rate = 10.0
    rs = RunningStats(window, rate)
    # bus times on the 10 Hz grid with jitter (ticks may be late), values with a trend
    times = np.cumsum(0.1 + rng.uniform(-0.02, 0.03, 80)) + 1000.0
    values = 680.0 + 0.5 * np.arange(80) + rng.normal(0, 3.0, 80)
    values[10] = values[11]  # a tie: TN/TX take the first occurrence
    assert rs.values()[SUFFIXES.index("NM")] == 0.0
    for k in range(80):
        rs.add(times[k], values[k])
        lo = max(0, k + 1 - window)
        want = numpy_stats(times[lo:k + 1], values[lo:k + 1], rate)
        got = rs.as_dict()
        assert list(got) == list(SUFFIXES)
        for suffix in SUFFIXES:
            assert got[suffix] == pytest.approx(float(want[suffix]), rel=1e-9, abs=1e-9), (
                f"{suffix} at sample {k} (window {window})")


def test_ties_take_first_occurrence_and_edge_cases():
    rs = RunningStats(5, 2.0)
    for t, v in [(0.0, 1.0), (0.5, 3.0), (1.0, 1.0), (1.5, 3.0)]:
        rs.add(t, v)
    d = rs.as_dict()
    assert (d["TN"], d["TX"]) == (0.0, 0.5)
    assert d["IN"] == pytest.approx(8.0 / 2.0)
    zero = RunningStats(3, 10.0)
    zero.add(0.0, 0.0)
    zero.add(0.1, 0.0)
    assert math.isnan(zero.as_dict()["CV"])  # SD/AV with AV = 0 is undefined
    one = RunningStats(1, 10.0)
    one.add(3.0, 7.0)
    d = one.as_dict()
    assert (d["CL"], d["CO"], d["SD"], d["ES"], d["NM"]) == (0.0, 7.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("samples,rate", [(0, 10.0), (1.5, 10.0), (True, 1.0), (3, 0.0),
                                          (3, float("nan")), (10**6, 10.0)])
def test_bad_construction_is_refused(samples, rate):
    with pytest.raises(ParamError):
        RunningStats(samples, rate)
