"""Experiments: each a module reproducing a paper's result on the emulated cell, registered
once in :data:`cell.registry.EXPERIMENTS`.

``testcell experiment --list`` lists them; ``testcell experiment NAME --help`` shows one's
own options. An experiment module defines ``add_arguments(parser)``, ``main(args) -> int``
and a :class:`~cell.registry.Experiment` that names them.
"""

from __future__ import annotations

import argparse

from .. import registry
from ..errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``testcell experiment``: ``--list``, and one sub-command per registered experiment."""
    registry.ensure_loaded()
    parser.add_argument("--list", action="store_true", help="list the experiments and exit")
    sub = parser.add_subparsers(dest="experiment", metavar="NAME")
    for exp in registry.EXPERIMENTS.values():
        p = sub.add_parser(exp.name, help=f"{exp.help} ({exp.seed})" if exp.seed else exp.help,
                           description=exp.description or exp.help)
        exp.add_arguments(p)


def listing() -> str:
    """One line per experiment: name, what it reproduces, what it does."""
    rows = [(e.name, e.seed, e.help) for e in registry.EXPERIMENTS.values()]
    width = max((len(r[0]) for r in rows), default=0)
    return "\n".join(f"{n:<{width}}  {s + ': ' if s else ''}{h}" for n, s, h in rows)


def main(args: argparse.Namespace) -> int:
    """Run the experiment named on the command line, or list them."""
    name = getattr(args, "experiment", None)
    if getattr(args, "list", False) or name is None:
        print(listing())
        if name is None and not getattr(args, "list", False):
            print("\nrun one with: testcell experiment NAME [options]  (NAME --help for its "
                  "options)")
        return 0
    exp = registry.EXPERIMENTS.get(name)
    if exp is None:
        raise ConfigError(f"experiment {name!r} is unknown; choose one of: "
                          f"{', '.join(registry.EXPERIMENTS)}")
    return exp.run(args)
