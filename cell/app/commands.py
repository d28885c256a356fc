"""``testcell experiment`` and ``testcell design``: one sub-command per registered item."""

from __future__ import annotations

import argparse

from cell.core import registry
from cell.core.errors import ConfigError


class Commands:
    """A command with one sub-command per registered item: ``testcell experiment`` over
    :data:`~cell.core.registry.EXPERIMENTS`, ``testcell design`` over
    :data:`~cell.core.registry.DESIGNS`."""

    def __init__(self, command: str, noun: str, table: dict[str, registry.Experiment]) -> None:
        self.command = command
        self.noun = noun
        self.table = table

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """``--list``, and one sub-command per registered item."""
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


#: ``testcell experiment NAME`` over :data:`~cell.core.registry.EXPERIMENTS`
EXPERIMENTS = Commands("experiment", "experiment", registry.EXPERIMENTS)
#: ``testcell design NAME`` over :data:`~cell.core.registry.DESIGNS`
DESIGNS = Commands("design", "design tool", registry.DESIGNS)
