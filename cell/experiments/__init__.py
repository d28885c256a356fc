"""Experiments: each a module reproducing a paper's result on the emulated cell, registered
once in :data:`cell.core.registry.EXPERIMENTS` (by :mod:`cell.app.builtin`).

``testcell experiment --list`` lists them; ``testcell experiment NAME --help`` shows one's
own options. An experiment module defines ``add_arguments(parser)``, ``main(args) -> int``
and a :class:`~cell.core.registry.Experiment` that names them. Its steps are kept apart:
record (the simulator and the runtime in lockstep), estimate, score, and figures (the shared
helpers of :mod:`cell.analysis.figures`).
"""
