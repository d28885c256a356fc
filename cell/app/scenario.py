"""``testcell scenario KEY=VALUE``: one scenario command frame to a running simulator.

The frames come from :mod:`cell.bus.scenario` (any message the DBC files say node
``SCENARIO`` sends); this is the command line around it.
"""

from __future__ import annotations

import time

from cell.bus import dbc as dbc_mod
from cell.bus.interface import open_bus
from cell.bus.scenario import describe_frames, parse_assignments, scenario_frames, scenario_keys
from cell.core import registry
from cell.core.errors import ConfigError, ParamError


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser) -> None:
    """``testcell scenario`` options."""
    parser.add_argument("assignments", nargs="*", metavar="KEY=VALUE",
                        help="scenario keys to set, e.g. osc=0.5 (--list shows the keys)")
    parser.add_argument("--bus", default=None,
                        help="python-can bus: auto (default), virtual, udp_multicast, socketcan "
                             "or INTERFACE:CHANNEL")
    parser.add_argument("--dbc", action="append", default=None, metavar="PATH",
                        help="add a DBC file or folder to the cell's own (repeatable)")
    parser.add_argument("--list", action="store_true", help="list the scenario keys and exit")


def main(args, settings) -> int:
    """Send one scenario command on the bus; print what was sent."""
    db = dbc_mod.load([*registry.DBC_FILES, *settings.dbc])
    keys = scenario_keys(db)
    if args.list or not args.assignments:
        for k in keys.values():
            d = k.describe()
            unit = f" {d['unit']}" if d["unit"] else ""
            print(f"{k.key:<16} [{d['minimum']:g}, {d['maximum']:g}]{unit}  start {d['initial']:g}"
                  f"  ({d['message']} 0x{d['frame_id']:X}) {d['comment']}")
        if not args.list and not args.assignments:
            print("\nsend one with: testcell scenario KEY=VALUE [KEY=VALUE ...]")
        return 0
    try:
        frames = scenario_frames(db, parse_assignments(args.assignments), time.time())
    except ParamError as exc:
        raise ConfigError(f"{exc.field}: {exc.message}") from None
    bus = open_bus(settings.bus)
    try:
        for msg in frames:
            bus.send(msg)
    finally:
        bus.shutdown()
    for d in describe_frames(db, frames):
        values = ", ".join(f"{k}={v:g}" for k, v in d["signals"].items())
        print(f"sent {d['message']} (0x{d['frame_id']:X}) on {bus.spec}: {values}")
    return 0
