"""A test-only plugin: a toy plant, its DBC file, an observer and an experiment.

It proves the platform: it registers each part with one line, and ``testcell`` picks it up
(``TESTCELL_PLUGINS=tests.plugins.toy_cell``) with no edit to the CLI, the service or the
runtime.
"""

from pathlib import Path

from cell.core import registry
from cell.core.registry import BlockSet, EngineProfile

from .experiment import TOY_STEP
from .observer import toy_observer
from .plant import Oscillator

registry.dbc_file(Path(__file__).with_name("toy.dbc"))
registry.engine(EngineProfile("toy", "a damped oscillator (test plugin)",
                              lambda s: Oscillator.composition(s.seed), duties=("square",)))
registry.block_set(BlockSet("toy-observer", lambda s: [toy_observer()], engines=("toy",)))
registry.experiment(TOY_STEP)
