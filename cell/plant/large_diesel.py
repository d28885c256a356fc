"""Engine profiles: the compositions of plants the simulator runs (``--engine NAME``).

A profile names its duty cycles and the simulator options that belong to it; it is
registered in :mod:`cell.app.builtin` (a plugin registers its own), and ``testcell sim`` and
``testcell up`` find it in :data:`cell.core.registry.ENGINES`.
"""

from __future__ import annotations

import math
from dataclasses import replace

from cell.core import registry
from cell.core.errors import ConfigError
from cell.core.options import Option, parse_bool
from cell.core.registry import Run
from cell.plant.composition import Composition
from cell.plant.diesel import (
    CYCLES,
    DieselEngine,
    DutyCycle,
    EngineParams,
    exhaust_flow,
    rated_bank_flow,
)
from cell.plant.diesel_airpath import AirPathParams, Biases, DieselAirPath
from cell.plant.backpressure import ExhaustBanks, ExhaustParams, valve_for_back_pressure

#: Seed 004's back-pressure target, mmH2O: the default valve opening gives it at rated.
TARGET_BP = 680.0


def large_diesel(
    cycle: str | DutyCycle = "rated",
    seed: int = 0,
    initial_valve: float | None = None,
    bp_limit: float | None = None,
    engine: EngineParams | None = None,
    exhaust: ExhaustParams | None = None,
    pem_sensor: bool = True,
    airpath: AirPathParams | None = None,
    biases: Biases | None = None,
) -> Composition:
    """The 60 L diesel on its dynamometer with two exhaust banks (seed 004) and its air path
    (seed 002, Appendix A).

    Parameters
    ----------
    cycle:
        Duty cycle name (:data:`~cell.plant.diesel.CYCLES`) or a :class:`DutyCycle`.
    seed:
        Noise seed.
    initial_valve:
        Valve opening in % held until a demand arrives. ``None``: the opening that gives
        680 mmH2O at rated (seed 004's target), so a run without a controller shows the
        paper's operating point. The closed-loop experiment passes 100 (fully open).
    bp_limit:
        Engine-protection limit, mmH2O (default :attr:`ExhaustParams.bp_limit`, 1200).
    engine, exhaust:
        The plants' constants.
    pem_sensor:
        Whether ``P_EM`` (the exhaust manifold pressure sensor) goes on the bus; seed 002
        uses it for the design only (``--no-pem-sensor``).
    airpath, biases:
        The air path's constants and its slowly varying biases against the observers'
        default model (:mod:`cell.plant.diesel_airpath`).

    The air path steps after the exhaust banks and reads their true back-pressure at the
    turbine outlet; it feeds nothing back, so the seed-004 plants behave as without it.
    """
    engine = engine or EngineParams()
    exhaust = replace(exhaust or ExhaustParams(), rated_flow=exhaust_flow(engine, engine.rated_speed, 1.0))
    if bp_limit is not None:
        exhaust = replace(exhaust, bp_limit=float(bp_limit))
    if initial_valve is None:
        initial_valve = valve_for_back_pressure(exhaust, TARGET_BP, rated_bank_flow(engine))
    diesel = DieselEngine(cycle, engine)
    banks = ExhaustBanks(exhaust, seed=seed, initial_valve=initial_valve)
    air = DieselAirPath(airpath, biases, pem_sensor=pem_sensor, seed=seed, period=engine.period)
    about = {"duty": diesel.schedule.name, "seed": seed,
             "valve": f"{banks.valves['L'].position:.1f} %", "bp limit": f"{banks.bp_limit:g} mmH2O",
             **({} if pem_sensor else {"P_EM sensor": "off"})}
    return Composition("large-diesel", [diesel, banks, air], diesel.schedule.duration, about)


def _valve_check(v: float) -> str | None:
    if not math.isfinite(v) or not 0.0 <= v <= 100.0:
        return f"must be an opening in 0..100 %, got {v}"
    return None


def _limit_check(v: float) -> str | None:
    if not math.isfinite(v) or not 0.0 < v <= 20000.0:
        return f"must be in (0, 20000] mmH2O, got {v}"
    return None


def _build_large_diesel(s: Run) -> Composition:
    if s.duty not in CYCLES:
        raise ConfigError(f"--duty {s.duty!r} is not a duty cycle of large-diesel; choose one "
                          f"of: {', '.join(CYCLES)}")
    return large_diesel(s.duty, s.seed, s.plant.get("valve"), s.plant.get("bp_limit"),
                        pem_sensor=not s.plant.get("no_pem_sensor"))


LARGE_DIESEL = registry.EngineProfile(
    name="large-diesel",
    description="60 L diesel on a water brake, two exhaust banks with back-pressure valves "
                "(seed 004), air path with VGT and EGR (seed 002)",
    build=_build_large_diesel,
    duties=CYCLES,
    shipped_scripts=True,
    options=(
        Option("valve", "--valve", float, metavar="PERCENT", check=_valve_check,
               help="initial valve opening in %% (default: the 680 mmH2O opening at rated)"),
        Option("bp_limit", "--bp-limit", float, metavar="MMH2O", check=_limit_check,
               help="engine-protection back-pressure limit (default 1200)"),
        Option("no_pem_sensor", "--no-pem-sensor", parse_bool, switch=True,
               help="leave the exhaust manifold pressure sensor P_EM off the bus (seed 002: "
                    "it serves the bias design only)"),
    ),
)
