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
==================  ==========================================  ==============================

Its frames are in ``dbc/si_turbo.dbc`` (and ``ENGINE_1`` of ``dbc/testcell.dbc``).
"""

from __future__ import annotations

from .. import registry
from ..errors import ConfigError
from ..settings import Settings
from .base import Plant
from .composition import Composition
from .si_engine import SI_CYCLES, BreathingParams, SIBreathing, SICycle, SIEngine, SIEngineParams

ENGINE_NAME = "si-turbo"


def si_turbo(
    cycle: str | SICycle = "ftp",
    seed: int = 0,
    engine: SIEngineParams | None = None,
    breathing: BreathingParams | None = None,
) -> Composition:
    """The turbocharged SI engine on its duty cycle.

    Parameters
    ----------
    cycle:
        Duty cycle name (:data:`~cell.plant.si_engine.SI_CYCLES`) or an :class:`SICycle`.
    seed:
        Noise seed of the plants with sensors.
    engine, breathing:
        The plants' constants.
    """
    eng = SIEngine(cycle, engine)
    plants: list[Plant] = [eng, SIBreathing(breathing)]
    about = {"duty": eng.cycle.name, "seed": seed}
    return Composition(ENGINE_NAME, plants, eng.cycle.duration, about)


def _build(s: Settings) -> Composition:
    duty = s.duty or "ftp"
    if duty not in SI_CYCLES:
        raise ConfigError(f"--duty {duty!r} is not a duty cycle of {ENGINE_NAME}; choose one of: "
                          f"{', '.join(SI_CYCLES)}")
    return si_turbo(duty, s.seed)


SI_TURBO = registry.EngineProfile(
    name=ENGINE_NAME,
    description="2 L class 4-cylinder turbocharged gasoline engine: λ control and breathing "
                "(seeds 000, 001, 003)",
    build=_build,
    duties=tuple(SI_CYCLES),
    options=(),
)
