"""The plant's inlined integrator (``plant_rk4``) gives the floats of the reference
:func:`~cell.plant.si_airpath.rk4` over :func:`~cell.plant.si_airpath.airpath_rhs`, bit for
bit, over states and inputs spread across the air path's range (throttle closed to wide open,
wastegate clipped on both sides, reverse flows, fuel cut)."""

from __future__ import annotations

import random

import pytest

from cell.plant.si_airpath import MODEL_PARAMS, PLANT_PARAMS, plant_rk4, rk4


@pytest.mark.parametrize("params", [PLANT_PARAMS, MODEL_PARAMS], ids=["plant", "model"])
def test_inlined_rk4_is_bit_identical_to_the_reference(params):
    rng = random.Random(7)
    fast = plant_rk4(params)
    for _ in range(400):
        x = [rng.uniform(0.5e5, 2.5e5), rng.uniform(0.1e5, 2e5), rng.uniform(280, 400),
             rng.uniform(1e5, 3e5), rng.uniform(0, 2e4)]
        if rng.random() < 0.3:  # near-equal pressures: the linearised flow functions, reversals
            x[1] = x[0] * rng.uniform(0.9, 1.1)
        u = (rng.uniform(-5, 95), rng.uniform(-0.2, 1.2), rng.uniform(500, 7000),
             rng.choice([rng.uniform(0.7, 1.3), 10.0]))
        assert fast(list(x), u, 1e-3, 3) == rk4(list(x), u, params, 1e-3, 3), (x, u)
