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


class Commands:
    """A command with one sub-command per registered item: ``testcell experiment`` over
    :data:`~cell.registry.EXPERIMENTS`, ``testcell design`` over
    :data:`~cell.registry.DESIGNS`."""

    def __init__(self, command: str, noun: str, table: dict[str, registry.Experiment]) -> None:
        self.command = command
        self.noun = noun
        self.table = table

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """``--list``, and one sub-command per registered item."""
        registry.ensure_loaded()
        parser.add_argument("--list", action="store_true", help=f"list the {self.noun}s and exit")
        sub = parser.add_subparsers(dest=self.command, metavar="NAME")
        for item in self.table.values():
            p = sub.add_parser(item.name, help=f"{item.help} ({item.seed})" if item.seed else item.help,
                               description=item.description or item.help)
            item.add_arguments(p)

    def listing(self) -> str:
        """One line per item: name, what it reproduces, what it does."""
        rows = [(e.name, e.seed, e.help) for e in self.table.values()]
        width = max((len(r[0]) for r in rows), default=0)
        return "\n".join(f"{n:<{width}}  {s + ': ' if s else ''}{h}" for n, s, h in rows)

    def main(self, args: argparse.Namespace) -> int:
        """Run the item named on the command line, or list them."""
        name = getattr(args, self.command, None)
        if getattr(args, "list", False) or name is None:
            print(self.listing())
            if name is None and not getattr(args, "list", False):
                print(f"\nrun one with: testcell {self.command} NAME [options]  (NAME --help for "
                      "its options)")
            return 0
        item = self.table.get(name)
        if item is None:
            raise ConfigError(f"{self.noun} {name!r} is unknown; choose one of: "
                              f"{', '.join(self.table) or '(none registered)'}")
        return item.run(args)


EXPERIMENT_COMMAND = Commands("experiment", "experiment", registry.EXPERIMENTS)
DESIGN_COMMAND = Commands("design", "design tool", registry.DESIGNS)
add_arguments = EXPERIMENT_COMMAND.add_arguments
listing = EXPERIMENT_COMMAND.listing
main = EXPERIMENT_COMMAND.main
