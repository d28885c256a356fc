"""The simulator's plants: small stateful parts of an engine, composed into engine profiles.

=====================  ===========================================================
module                 what
=====================  ===========================================================
:mod:`.base`           :class:`Plant`, the interface every plant shares
:mod:`.composition`    :class:`Composition`: plants wired by signal name
:mod:`.diesel`         the 60 L diesel on its dynamometer, its duty cycles (seed 004)
:mod:`.exhaust`        two exhaust banks, butterfly valves, sensors, protection (seed 004)
:mod:`.profiles`       engine profiles: ``large-diesel``
:mod:`.si_engine`      the turbocharged SI engine: duty cycles, λ control, breathing
:mod:`.twc_model`      the three-way catalyst's equations (seed 000, section III)
:mod:`.catalyst`       the catalyst plant and its sensors (seed 000)
:mod:`.si_turbo`       engine profile ``si-turbo``
=====================  ===========================================================
"""

from cell.plant.base import Plant
from cell.plant.composition import Composition
from cell.plant.diesel import (
    CYCLES,
    RUNNING,
    STOPPED,
    TRIPPED,
    DieselEngine,
    DutyCycle,
    EngineParams,
    duty_cycle,
)
from cell.plant.backpressure import BANKS, TRIP_EXH_BP_LIMIT, TRIP_NONE, ExhaustBanks, ExhaustParams
from cell.plant.large_diesel import large_diesel

__all__ = [
    "BANKS", "CYCLES", "RUNNING", "STOPPED", "TRIPPED", "TRIP_EXH_BP_LIMIT", "TRIP_NONE",
    "Composition", "DieselEngine", "DutyCycle", "EngineParams", "ExhaustBanks", "ExhaustParams",
    "Plant", "duty_cycle", "large_diesel",
]
