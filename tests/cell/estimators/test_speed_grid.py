"""The speed grid the UEGO inversion takes its designs from (issue 18 point 6): the design
of a band is the design made directly at that band's speed, the bands next to the one in
use are made by the background thread (not by the caller), a speed dithering at a band edge
keeps its band, and the grid holds a bounded number of designs."""

from __future__ import annotations

import math
import time

import numpy as np

from cell.estimators.cylinders import UegoInversion, uego_design
from cell.estimators.speed_grid import BAND, SpeedGrid

PARAMS = (0.025, 0.020, 3, 4.0, 4.0)


def _idle(grid: SpeedGrid, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while not grid.idle() and time.monotonic() < end:
        time.sleep(0.01)
    assert grid.idle()


def test_a_band_design_is_the_design_at_its_speed_and_its_neighbours_come_from_the_thread():
    grid = SpeedGrid(lambda rpm: uego_design(*PARAMS, rpm), ahead=2, keep=8)
    i = grid.select(2000.0, None)
    assert i == round(math.log(2000.0) / math.log(BAND))
    lp, (first, second) = grid.design(i)
    ref, _ = uego_design(*PARAMS, BAND ** i)
    assert np.array_equal(lp.M, ref.M) and np.array_equal(lp.N, ref.N)
    _idle(grid)
    assert grid.designed_inline == 1  # only the band asked for first
    assert grid.designed == 5  # and two on each side, by the background thread
    assert grid.design(i + 2)[0] is not lp and grid.designed_inline == 1  # made ahead


def test_hysteresis_holds_the_band_at_its_edge_and_the_grid_stays_bounded():
    grid = SpeedGrid(lambda rpm: uego_design(*PARAMS, rpm), ahead=1, keep=4, hysteresis=0.25)
    i = grid.select(3000.0, None)
    edge = BAND ** (i + 0.5)
    for f in (0.999, 1.001, 0.999, 1.001):  # dithering across the edge
        assert grid.select(edge * f, i) == i
    assert grid.select(BAND ** (i + 0.8), i) == i + 1  # beyond the band: the next one
    assert grid.select(BAND ** (i + 0.8), None) == i + 1
    for k in range(12):  # a sweep over twelve bands
        grid.design(i + k)
    _idle(grid)
    assert len(grid._nodes) <= 4


def test_the_observer_takes_its_design_from_the_shared_grid_of_its_parameters():
    a, b = UegoInversion(), UegoInversion()
    assert a._grid is b._grid
    c = UegoInversion(tau1=0.03)
    assert c._grid is not a._grid
    a.set_params({"tau1": 0.03})
    assert a._grid is c._grid  # retuned: the grid of its new parameters
