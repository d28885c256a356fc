"""What a reader needs from the figures: a legend, units on the axes, a colour bar that holds
every value shown, and labels that do not overlap (checked on the rendered figure)."""

import itertools

import matplotlib
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cell.analysis.report import plot_png
from cell.analysis.series import Series
from cell.experiments.backpressure import (
    GRID_KI,
    GRID_KP,
    CaseResult,
    Summary,
    plot_figure10,
    plot_gain_map,
)

matplotlib.use("Agg")


@pytest.fixture
def figures(monkeypatch):
    """Every figure saved during the test, kept open for inspection."""
    saved = []
    real = Figure.savefig

    def keep(self, *a, **kw):
        saved.append(self)
        return real(self, *a, **kw)

    monkeypatch.setattr(Figure, "savefig", keep)
    return saved


def _summary(fb, settle, kp=0.005, ki=0.013):
    return Summary(feedback=fb, settling_time_s=settle, settling_spread_s=0.0, overshoot_pct=0.0,
                   iae=0.0, valve_travel_pct=0.0, tripped=False, fuel_l=None, seeds=1,
                   settled=1, trips=0, kp=kp, ki=ki)


def _overlaps(fig, texts):
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    r = canvas.get_renderer()
    boxes = [(t.get_text(), t.get_window_extent(r)) for t in texts if t.get_text() and t.get_visible()]
    return [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]


def test_closed_loop_figure_has_a_legend_naming_each_trace(tmp_path, figures):
    t = np.linspace(0, 100, 200)
    trace = {"t": t.tolist(), "bp_R": (680 + 100 * np.exp(-t / 10)).tolist(),
             "demand_R": np.full_like(t, 40.0).tolist()}
    case = CaseResult(feedback="kalman", seed=0, kp=0.005, ki=0.013, settling_time_s=30.0,
                      overshoot_pct=0, iae=0, valve_travel_pct=0, tripped=False, trip_time_s=None,
                      fuel_l=None, trace=trace)
    plot_figure10(tmp_path / "f.png", [case], [_summary("kalman", 30.0)])
    fig = figures[-1]
    labels = {t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()}
    assert {"EXH_BP_R_TRUE", "VALVE_DEMAND_R", "setpoint 680 mmH2O"} <= labels, labels


def test_gain_map_colour_bar_holds_every_value_and_labels_do_not_overlap(tmp_path, figures):
    kps, kis = GRID_KP, GRID_KI
    grids = {fb: {(kp, ki): _summary(fb, 20.0 + 207.0 * (i + j) / 6 if (i, j) != (3, 4) else None,
                                     kp, ki)
                  for i, kp in enumerate(kps) for j, ki in enumerate(kis)}
             for fb in ("maf", "kalman", "adaptive")}  # what --gain-map draws
    plot_gain_map(tmp_path / "g.png", grids)
    fig = figures[-1]
    images = [im for ax in fig.axes for im in ax.get_images()]
    top = max(s.settling_time_s for g in grids.values() for s in g.values() if s.settling_time_s)
    assert top > 200  # a cell reads 227
    assert all(im.norm.vmax >= top for im in images), [im.norm.vmax for im in images]
    texts = []
    for ax in fig.axes:
        texts += [ax.title, ax.xaxis.label, ax.yaxis.label, *ax.get_xticklabels(),
                  *ax.get_yticklabels()]
    assert _overlaps(fig, texts) == []


def test_sweep_plot_y_axis_has_the_unit(tmp_path, figures):
    rng = np.random.default_rng(0)
    y = 680 + rng.normal(0, 20, 600)
    s = Series(t=np.arange(600) / 10, y=y, truth=np.full(600, 680.0), channel="EXH_BP_R",
               truth_channel="EXH_BP_R_TRUE", unit="mmH2O")
    plot_png(tmp_path / "s.png", s, [{"Q": 1e-6, "R": 1e-4, "gain": 0.1, "rmse": 1.0}], top=1)
    labels = [ax.get_ylabel() for ax in figures[-1].axes]
    assert labels and all("[mmH2O]" in lb for lb in labels), labels
