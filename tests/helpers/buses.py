"""A private udp_multicast bus for each test process.

Other cells run on these machines on the cell's default group (239.74.163.2, port 43113). A
test that opened the default group would read their frames, so every test that opens a
multicast bus takes a group *and* a port of its own here, derived from the process id and
the pytest-xdist worker. The groups lie in 239.74.163.0/24, which
``scripts/setup-multicast.sh`` routes over loopback so that nothing leaves this machine.
"""

from __future__ import annotations

import functools
import os
import subprocess

from cell.bus.interface import MULTICAST_GROUP, MULTICAST_PORT

#: Groups 239.74.163.16-205 are the tests'; .2 is the cell's default, .211-.252 fixed tests'.
_FIRST, _COUNT = 16, 190


def _worker() -> int:
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return int(name[2:]) if name[2:].isdigit() else 0


@functools.cache
def private_group() -> tuple[str, int]:
    """``(group, port)`` of this test process alone (stable for the process's life)."""
    key = os.getpid() * 8 + _worker()
    group = f"239.74.163.{_FIRST + key % _COUNT}"
    port = 44000 + key % 8000
    assert (group, port) != (MULTICAST_GROUP, MULTICAST_PORT)
    return group, port


def private_bus() -> str:
    """The ``--bus`` spec of this test process's private group and port."""
    group, port = private_group()
    return f"udp_multicast:{group}:{port}"


def routed_over_loopback(group: str | None = None) -> bool:
    """Whether ``group`` (default: this process's) goes out over ``lo`` only."""
    group = group or private_group()[0]
    try:
        out = subprocess.run(["ip", "route", "get", group], capture_output=True, text=True)
    except FileNotFoundError:
        return False
    return " dev lo " in out.stdout


NOT_ROUTED = ("the tests' multicast groups (239.74.163.0/24) are not routed over loopback; run "
              "scripts/setup-multicast.sh as root (scripts/test.sh does) so udp_multicast stays "
              "on this machine")
