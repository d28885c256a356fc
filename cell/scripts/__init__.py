"""Formula-device runtime: CyFlex-style and PUMA-style cell scripts as runtime blocks.

Seed 004 (McGurk et al. 2023) shows how a Kalman filter was written as test-bed scripts:
a cyclic Formula Device script in AVL PUMA 2 (Figures 5-6) and a General Labels plus
Running Averages pair in CyFlex (Figures 2-3). This package runs scripts in two dialects
modelled on those listings, compiled once at load into Python code that can reach only
its own function table. Both dialects are this project's own; they claim no vendor
compatibility.

Public API
----------
load_script(name, text, ravg_text=None, rates=None) -> ScriptBlock
shipped_scripts() -> list[(name, text, ravg_text)]
ScriptBlock, FdvBlock, CyflexBlock, RunningStats, ScriptError, DIALECTS
"""

from cell.scripts.block import ScriptBlock
from cell.scripts.cyflex import CyflexBlock
from cell.scripts.errors import ScriptError
from cell.scripts.expr import SUFFIXES
from cell.scripts.fdv import FdvBlock
from cell.scripts.dialects import DIALECTS, load_script, load_shipped, shipped_scripts
from cell.scripts.stats import RunningStats

__all__ = [
    "DIALECTS",
    "SUFFIXES",
    "CyflexBlock",
    "FdvBlock",
    "RunningStats",
    "ScriptBlock",
    "ScriptError",
    "load_script",
    "load_shipped",
    "shipped_scripts",
]
