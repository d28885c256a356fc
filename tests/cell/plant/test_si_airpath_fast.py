"""The plant's inlined integrator (``plant_rk4``) and its compiled twin (``compiled_rk4``,
numba) give the floats of the reference
:func:`~cell.plant.si_airpath.rk4` over :func:`~cell.plant.si_airpath.airpath_rhs`, bit for
bit, over states and inputs spread across the air path's range (throttle closed to wide open,
wastegate clipped on both sides, reverse flows, fuel cut)."""

from __future__ import annotations

import random

import pytest

from cell.plant import airpath_kernel
from cell.plant.si_airpath import MODEL_PARAMS, PLANT_PARAMS, compiled_rk4, plant_rk4, rk4


@pytest.mark.parametrize("make", [plant_rk4, compiled_rk4], ids=["inlined", "compiled"])
@pytest.mark.parametrize("params", [PLANT_PARAMS, MODEL_PARAMS], ids=["plant", "model"])
def test_fast_rk4_is_bit_identical_to_the_reference(params, make):
    rng = random.Random(7)
    fast = make(params)
    for _ in range(400):
        x = [rng.uniform(0.5e5, 2.5e5), rng.uniform(0.1e5, 2e5), rng.uniform(280, 400),
             rng.uniform(1e5, 3e5), rng.uniform(0, 2e4)]
        if rng.random() < 0.3:  # near-equal pressures: the linearised flow functions, reversals
            x[1] = x[0] * rng.uniform(0.9, 1.1)
        u = (rng.uniform(-5, 95), rng.uniform(-0.2, 1.2), rng.uniform(500, 7000),
             rng.choice([rng.uniform(0.7, 1.3), 10.0]))
        assert fast(list(x), u, 1e-3, 3) == rk4(list(x), u, params, 1e-3, 3), (x, u)


def test_the_kernel_is_compiled():
    """numba is a dependency: the plant's hot path is the compiled one."""
    assert airpath_kernel.COMPILED
    assert hasattr(airpath_kernel.steps, "signatures")
