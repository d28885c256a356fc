"""The cell's own parts, registered like a plugin's: one line each (see :mod:`cell.registry`)."""

from __future__ import annotations

from . import registry
from .controller import controllers
from .estimators.adaptive import adaptive_filters
from .estimators.airpath import AirPathObserver
from .estimators.diesel_observers import airpath_observers
from .estimators.filters import native_filters
from .estimators.imbalance import imbalance_observers
from .estimators.twc import twc_observers
from .experiments.airpath import AIRPATH
from .experiments.airpath_design import AIRPATH_DESIGN
from .experiments.bias import BIAS, BIAS_DESIGN
from .experiments.closed_loop import CLOSED_LOOP
from .experiments.imbalance import IMBALANCE
from .experiments.twc import TWC
from .plant.profiles import LARGE_DIESEL
from .plant.si_turbo import SI_TURBO
from .registry import BlockFamily, BlockSet

# block families: GET/PATCH /{section}/{name} and a section of the tuning file each
registry.family(BlockFamily("filter", "filters", "moving-average, Kalman and adaptive filters",
                            ({"Q": 4e-6, "R": 1e-4}, {"samples": 30})))
registry.family(BlockFamily("controller", "controllers", "PI controllers",
                            ({"enable": True}, {"setpoint": 680.0, "feedback": "EXH_BP_R_Kalman"},
                             {"kp": 0.005, "ki": 0.013})))
registry.family(BlockFamily("observer", "observers", "model-based observers on the estimator core",
                            ({"Q": [1e-4, 1e-4], "R": [1e-2]},)))

# engine profiles
registry.engine(LARGE_DIESEL)
registry.engine(SI_TURBO)

# the runtime's native blocks
registry.block_set(BlockSet("seed004-filters", lambda s: [*native_filters(), *adaptive_filters()],
                            engines=("large-diesel",)))
# the PI controllers start disabled: they keep off the bus until enabled over HTTP
registry.block_set(BlockSet("seed004-controllers",
                            lambda s: [] if s.no_controllers else controllers("kalman"),
                            engines=("large-diesel",)))
# seed 002: the default and the bias-augmented air-path observers side by side
registry.block_set(BlockSet("seed002-airpath", lambda s: airpath_observers(s.bias_design),
                            engines=("large-diesel",)))
# seed 003's constant-gain EKF of the SI air path, on the shipped gain table
registry.block_set(BlockSet("seed003-airpath", lambda s: [AirPathObserver()], engines=("si-turbo",)))

registry.block_set(BlockSet("seed000-twc", twc_observers, engines=("si-turbo",)))
# seed 001: the UEGO-inversion and transmission-rod observers on the crank-angle streams
registry.block_set(BlockSet("seed001-observers", lambda s: imbalance_observers(),
                            engines=("si-turbo",)))

# experiments
registry.experiment(CLOSED_LOOP)
registry.experiment(TWC)
registry.experiment(AIRPATH)
registry.experiment(IMBALANCE)
registry.experiment(BIAS)

# design tools
registry.design(AIRPATH_DESIGN)
registry.design(BIAS_DESIGN)
