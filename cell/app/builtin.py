"""The cell's own parts, registered like a plugin's: one line each (see :mod:`cell.core.registry`).

Importing this module registers them; :func:`cell.app.load` does, then loads the plugins.
"""

from __future__ import annotations

from cell.control.backpressure import BACKPRESSURE_CONTROLLERS
from cell.core import registry
from cell.core.registry import BlockFamily, BlockSet

from cell.design.cylinders import IMBALANCE_DESIGN
from cell.design.catalyst import TWC_DESIGN
from cell.design.diesel_airpath import BIAS_DESIGN
from cell.design.si_airpath import AIRPATH_DESIGN
from cell.estimators.backpressure import native_filters
from cell.estimators.backpressure_adaptive import adaptive_filters
from cell.estimators.catalyst import CATALYST_BLOCKS
from cell.estimators.cylinders import imbalance_observers
from cell.estimators.diesel_airpath import DIESEL_AIRPATH_BLOCKS
from cell.estimators.si_airpath import AirPathObserver
from cell.experiments.backpressure import CLOSED_LOOP
from cell.experiments.catalyst import TWC
from cell.experiments.cylinders import IMBALANCE
from cell.experiments.diesel_airpath import BIAS
from cell.experiments.robustness import ROBUSTNESS
from cell.experiments.si_airpath import AIRPATH
from cell.plant.large_diesel import LARGE_DIESEL
from cell.plant.si_turbo import SI_TURBO

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

# the runtime's native blocks (a block set's own options come with it)
registry.block_set(BlockSet("seed004-filters", lambda run: [*native_filters(), *adaptive_filters()],
                            engines=("large-diesel",)))
registry.block_set(BACKPRESSURE_CONTROLLERS)
# seed 002: the default and the bias-augmented air-path observers side by side
registry.block_set(DIESEL_AIRPATH_BLOCKS)
# seed 003's constant-gain EKF of the SI air path, on the shipped gain table
registry.block_set(BlockSet("seed003-airpath", lambda run: [AirPathObserver()],
                            engines=("si-turbo",)))
registry.block_set(CATALYST_BLOCKS)
# seed 001: the UEGO-inversion and transmission-rod observers on the crank-angle streams
registry.block_set(BlockSet("seed001-observers", lambda run: imbalance_observers(),
                            engines=("si-turbo",)))

# experiments
registry.experiment(CLOSED_LOOP)
registry.experiment(TWC)
registry.experiment(AIRPATH)
registry.experiment(IMBALANCE)
registry.experiment(BIAS)
registry.experiment(ROBUSTNESS)

# design tools
registry.design(AIRPATH_DESIGN)
registry.design(BIAS_DESIGN)
registry.design(IMBALANCE_DESIGN)
registry.design(TWC_DESIGN)
