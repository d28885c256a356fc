"""The ``si-turbo`` engine profile: a 2 L class, 4-cylinder turbocharged gasoline engine.

The plants exchange signals by name (:class:`~cell.plant.composition.Composition`):

==================  ==========================================  ==============================
plant               consumes                                    produces
==================  ==========================================  ==============================
``SIEngine``        (the duty cycle)                            ENGINE_SPEED, SI_LOAD_DEMAND,
                                                                LAMBDA_ENGINE_TRUE,
                                                                FUEL_CUT_TRUE
``SIBreathing``     ENGINE_SPEED, SI_LOAD_DEMAND,               EXH_MASS_FLOW_TRUE, T_EXH_TRUE,
                    LAMBDA_ENGINE_TRUE                          ENGINE_TORQUE, FUEL_RATE,
                                                                ENGINE_POWER
``Cylinders``       ENGINE_SPEED, LAMBDA_ENGINE_TRUE,           crank-angle streams AFR_UEGO,
(seed 001)          ENGINE_TORQUE, FUEL_OFFSET_CYL_1..4         N_CRANK (+ truth), per-cylinder
                                                                AFR/IMEP truth
==================  ==========================================  ==============================

Its frames are in ``dbc/si_turbo.dbc``, ``dbc/crank.dbc`` (and ``ENGINE_1`` of
``dbc/testcell.dbc``). ``--imbalance 1:+0.25`` gives cylinder 1 25 % more fuel;
``--crank off`` leaves the crank-resolved plant out (no 6 deg sample frames).
"""

from __future__ import annotations

from .. import registry
from ..errors import ConfigError
from ..settings import Option, Settings
from .base import Plant
from .composition import Composition
from .cylinders import CylinderParams, Cylinders, parse_imbalance
from .si_engine import SI_CYCLES, BreathingParams, SIBreathing, SICycle, SIEngine, SIEngineParams

ENGINE_NAME = "si-turbo"


def si_turbo(
    cycle: str | SICycle = "ftp",
    seed: int = 0,
    engine: SIEngineParams | None = None,
    breathing: BreathingParams | None = None,
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
    engine, breathing, cylinders:
        The plants' constants.
    imbalance:
        Per-cylinder fuel offsets, ``"1:+0.25,4:-0.25"`` or a tuple (seed 001).
    crank:
        Whether to add the crank-resolved :class:`~cell.plant.cylinders.Cylinders` plant.
    """
    eng = SIEngine(cycle, engine)
    plants: list[Plant] = [eng, SIBreathing(breathing)]
    about = {"duty": eng.cycle.name, "seed": seed}
    if crank:
        offsets = imbalance if isinstance(imbalance, tuple) else parse_imbalance(imbalance)
        plants.append(Cylinders(cylinders, offsets, seed=seed))
        if any(offsets):
            about["imbalance"] = ",".join(f"{i + 1}:{v:+g}" for i, v in enumerate(offsets) if v)
    return Composition(ENGINE_NAME, plants, eng.cycle.duration, about)


def _build(s: Settings) -> Composition:
    duty = s.duty or "ftp"
    if duty not in SI_CYCLES:
        raise ConfigError(f"--duty {duty!r} is not a duty cycle of {ENGINE_NAME}; choose one of: "
                          f"{', '.join(SI_CYCLES)}")
    return si_turbo(duty, s.seed, imbalance=s.plant.get("imbalance"),
                    crank=s.plant.get("crank", "on") == "on")


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
    description="2 L class 4-cylinder turbocharged gasoline engine: λ control and breathing "
                "(seeds 000, 001, 003)",
    build=_build,
    duties=tuple(SI_CYCLES),
    options=(
        Option("imbalance", "--imbalance", str, metavar="CYL:OFFSET[,...]", check=_imbalance_check,
               help="per-cylinder fuel offsets, e.g. 1:+0.25 or 1:+0.25,4:-0.25 (seed 001)"),
        Option("crank", "--crank", str, metavar="on|off", check=_crank_check,
               help="the crank-resolved cylinders, UEGO and crankshaft plant with its 6 deg "
                    "sample frames (default on)"),
    ),
)
