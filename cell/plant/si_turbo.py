"""The ``si-turbo`` engine profile: a 2 L class, 4-cylinder turbocharged gasoline engine.

The plants exchange signals by name (:class:`~cell.plant.composition.Composition`):

==================  ==========================================  ==============================
plant               consumes                                    produces
==================  ==========================================  ==============================
``SIEngine``        (the duty cycle)                            ENGINE_SPEED, SI_LOAD_DEMAND,
                                                                LAMBDA_ENGINE_TRUE,
                                                                FUEL_CUT_TRUE
``SIAirPath``       ENGINE_SPEED, SI_LOAD_DEMAND,               EXH_MASS_FLOW_TRUE, T_EXH_TRUE,
(seed 003)          LAMBDA_ENGINE_TRUE                          ENGINE_TORQUE, FUEL_RATE,
                                                                ENGINE_POWER, the air-path
                                                                sensors and truth
``Catalyst``        EXH_MASS_FLOW_TRUE, T_EXH_TRUE,             LAMBDA_PRE, LAMBDA_MID,
                    LAMBDA_ENGINE_TRUE, OSC (scenario)          EXH_MASS_FLOW, T_EXH, T_CAT,
                                                                SOX_*_TRUE, OSC_TRUE, ...
``Cylinders``       ENGINE_SPEED, LAMBDA_ENGINE_TRUE,           crank-angle streams AFR_UEGO,
(seed 001)          ENGINE_TORQUE, FUEL_OFFSET_CYL_1..4         N_CRANK (+ truth), per-cylinder
                                                                AFR/IMEP truth
==================  ==========================================  ==============================

Its frames are in ``dbc/si_turbo.dbc``, ``dbc/si_airpath.dbc``, ``dbc/crank.dbc`` (and
``ENGINE_1`` of ``dbc/testcell.dbc``). The mean-value air path
(:class:`~cell.plant.si_airpath.SIAirPath`) replaced issue 8's simple
:class:`~cell.plant.si_engine.SIBreathing`, which stays in ``si_engine`` as the reference the
air path's exhaust flow is checked against. ``--imbalance 1:+0.25`` gives cylinder 1 25 % more
fuel; ``--crank off`` leaves the crank-resolved plant out (no 6 deg sample frames; runs that
need only the mean-value signals are then about twice as fast).
"""

from __future__ import annotations

import math
from dataclasses import replace

from cell.core import registry
from cell.core.errors import ConfigError
from cell.core.options import Option
from cell.core.registry import Run
from cell.plant.base import Plant
from cell.plant.catalyst import CATALYST_OPTIONS, Catalyst, CatalystParams, catalyst_params
from cell.plant.composition import Composition
from cell.plant.cylinders import (VARIANT_OPTIONS, CylinderParams, Cylinders, parse_imbalance,
                                  variant_params)
from cell.plant.si_airpath import SIAirPath, SIAirPathParams
from cell.plant.si_engine import SI_CYCLES, SICycle, SIEngine, SIEngineParams

ENGINE_NAME = "si-turbo"


def si_turbo(
    cycle: str | SICycle = "ftp",
    seed: int = 0,
    engine: SIEngineParams | None = None,
    airpath: SIAirPathParams | None = None,
    osc: float | None = None,
    osc_drift: float | None = None,
    catalyst: CatalystParams | None = None,
    imbalance: str | tuple[float, ...] | None = None,
    crank: bool = True,
    cylinders: CylinderParams | None = None,
) -> Composition:
    """The turbocharged SI engine on its duty cycle.

    Parameters
    ----------
    cycle:
        Duty cycle name (:data:`~cell.plant.si_engine.SI_CYCLES`) or an :class:`SICycle`.
    seed:
        Noise seed of the plants with sensors.
    osc:
        The catalyst's oxygen storage capacity at the start, normalised to the fresh
        catalyst (default 1; ``--osc 0.6`` is an aged one).
    osc_drift:
        Change of OSC per hour of running (default 0).
    engine, airpath, catalyst, cylinders:
        The plants' constants.
    imbalance:
        Per-cylinder fuel offsets, ``"1:+0.25,4:-0.25"`` or a tuple (seed 001).
    crank:
        Whether to add the crank-resolved :class:`~cell.plant.cylinders.Cylinders` plant.
    """
    cat = catalyst or CatalystParams()
    if osc is not None:
        cat = replace(cat, osc=float(osc))
    if osc_drift is not None:
        cat = replace(cat, osc_drift=float(osc_drift))
    eng = SIEngine(cycle, engine)
    plants: list[Plant] = [eng, SIAirPath(airpath, seed=seed), Catalyst(cat, seed=seed)]
    about = {"duty": eng.cycle.name, "seed": seed, "osc": f"{cat.osc:g}"}
    if cat.osc_drift:
        about["osc drift"] = f"{cat.osc_drift:g}/h"
    if crank:
        offsets = imbalance if isinstance(imbalance, tuple) else parse_imbalance(imbalance)
        plants.append(Cylinders(cylinders, offsets, seed=seed))
        if any(offsets):
            about["imbalance"] = ",".join(f"{i + 1}:{v:+g}" for i, v in enumerate(offsets) if v)
    return Composition(ENGINE_NAME, plants, eng.cycle.duration, about)


def _build(s: Run) -> Composition:
    duty = s.duty or "ftp"
    if duty not in SI_CYCLES:
        raise ConfigError(f"--duty {duty!r} is not a duty cycle of {ENGINE_NAME}; choose one of: "
                          f"{', '.join(SI_CYCLES)}")
    return si_turbo(duty, s.seed, osc=s.plant.get("osc"), osc_drift=s.plant.get("osc_drift"),
                    catalyst=catalyst_params(s.plant),
                    imbalance=s.plant.get("imbalance"), crank=s.plant.get("crank", "on") == "on",
                    cylinders=variant_params(s.plant))


def _osc_check(v: float) -> str | None:
    if not math.isfinite(v) or not 0.05 <= v <= 2.0:
        return f"must be in [0.05, 2] (normalised to the fresh catalyst), got {v}"
    return None


def _drift_check(v: float) -> str | None:
    if not math.isfinite(v) or abs(v) > 10.0:
        return f"must be within ±10 per hour, got {v}"
    return None


def _imbalance_check(v: str) -> str | None:
    try:
        parse_imbalance(v)
    except ConfigError as exc:
        return str(exc).split(": ", 1)[-1]
    return None


def _crank_check(v: str) -> str | None:
    return None if v in ("on", "off") else f"must be on or off, got {v!r}"


SI_TURBO = registry.EngineProfile(
    name=ENGINE_NAME,
    description="2 L class 4-cylinder turbocharged gasoline engine: λ control, breathing and "
                "three-way catalyst (seeds 000, 001, 003)",
    build=_build,
    duties=tuple(SI_CYCLES),
    options=(
        Option("osc", "--osc", float, metavar="X", check=_osc_check,
               help="catalyst oxygen storage capacity, normalised to fresh (default 1; 0.6: aged)"),
        Option("osc_drift", "--osc-drift", float, metavar="PER_H", check=_drift_check,
               help="slow drift of the catalyst's OSC per hour of running (default 0)"),
        Option("imbalance", "--imbalance", str, metavar="CYL:OFFSET[,...]", check=_imbalance_check,
               help="per-cylinder fuel offsets, e.g. 1:+0.25 or 1:+0.25,4:-0.25 (seed 001)"),
        Option("crank", "--crank", str, metavar="on|off", check=_crank_check,
               help="the crank-resolved cylinders, UEGO and crankshaft plant with its 6 deg "
                    "sample frames (default on)"),
        *VARIANT_OPTIONS,
        *CATALYST_OPTIONS,  # the catalyst's variants: λ sensor model, kinetics, cells
    ),
)
