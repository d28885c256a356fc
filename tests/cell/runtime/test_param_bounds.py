"""Every tunable parameter of every registered block set has physical bounds (issue 20, point
2): absurd values are refused naming the parameter, and the previous value stays."""

import math

import numpy as np
import pytest

from cell.core import registry
from cell.core.errors import ParamError
from cell.core.settings import Settings
from cell.runtime.blocks import COVARIANCE_BOUNDS, Param


def all_blocks():
    settings = Settings.build({}, environ={})
    return [(name, b) for name, bs in registry.BLOCK_SETS.items() for b in bs.build(settings)]


BLOCKS = all_blocks()
PARAMS = [(f"{set_name}/{b.name}/{p}", b, p) for set_name, b in BLOCKS for p in b.PARAMS]


def test_every_block_set_is_covered():
    assert {n for n, _ in BLOCKS} == set(registry.BLOCK_SETS)
    assert len(PARAMS) > 50


def lower(spec: Param):
    return spec.gt if spec.gt is not None else spec.ge


@pytest.mark.parametrize("label, block, key", PARAMS, ids=[p[0] for p in PARAMS])
def test_the_parameter_has_bounds_and_refuses_absurd_values(label, block, key):
    spec = block.PARAMS[key]
    if spec.type is str:  # a list of names: bounded by its choices
        assert getattr(spec, "choices", ()), label
        return
    lo, hi = lower(spec), spec.le
    assert lo is not None and hi is not None, f"{label} has no {'lower' if lo is None else 'upper'} bound"
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(np.asarray(lo) <= hi)
    if key in ("Q", "R", "P0"):  # covariances: the range the numerics are tested over
        assert (lo, hi) == COVARIANCE_BOUNDS, label
    before = block.params()
    size = None if spec.shape == "scalar" else len(np.atleast_1d(before[key]))
    for absurd in (1e300, -1e300, 5e-324 if key in ("Q", "R", "P0") else None):
        if absurd is None:
            continue
        value = absurd if size is None else [absurd] * size
        if spec.type is int and math.isfinite(absurd) and abs(absurd) < 1:
            continue
        with pytest.raises(ParamError) as err:
            block.set_params({key: value})
        assert err.value.field == key
        assert f"{absurd!r}" in str(err.value) or f"{float(absurd)!r}" in str(err.value), str(err.value)
        assert block.params() == before
