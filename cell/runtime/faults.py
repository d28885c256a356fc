"""Faults of the runtime's blocks: isolated, counted, reset and retried with backoff.

A block's step can fail in three ways, and each faults that block alone:

``refused``
    The block raised :class:`ArithmeticError`: the block's own way of saying "this tick's
    outputs cannot be computed" (a non-finite input, a diverged filter it has already
    restarted, an implausible input it refuses while keeping its estimate). The outputs
    are ``invalid`` with the reason and the block is stepped again at its next tick: it
    keeps its state, which is its own business.
``exception``
    The block raised anything else (a ``TypeError`` from a complex number, a
    ``ValueError``, numpy's ``LinAlgError``, a ``RuntimeError``...): a defect the block did
    not foresee. Its outputs are ``invalid`` with the exception's type and message, the
    block is reset (its ``reset()``, when it has one) and it is not stepped again until its
    backoff has passed, in bus time: 1 s after the first fault in a row, then 2, 4, 8, 16
    and at most :data:`MAX_BACKOFF_S` seconds. A step that succeeds ends the streak.
``nonfinite``
    The block returned NaN or an infinity for an output: that output is ``invalid`` and
    withheld from the bus; the block keeps running.

The same applies to a block's crank-angle sample hand-overs (``samples()`` and ``gap()``).
The runtime counts every fault here, by block and kind; ``/health`` shows the counts, the
last reason and the backoff state of every block that has faulted, and ``/metrics`` the
counts.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

#: Kinds of fault, in the order ``/health`` and ``/metrics`` list them.
FAULT_KINDS = ("refused", "exception", "nonfinite")

#: First backoff after an unexpected exception, and its cap (seconds of bus time).
FIRST_BACKOFF_S = 1.0
MAX_BACKOFF_S = 30.0


def describe(exc: BaseException) -> str:
    """``TypeName: message``, as an output's reason and ``/health`` show a fault."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def backoff_after(streak: int) -> float:
    """Seconds of bus time a block is left alone after ``streak`` exceptions in a row."""
    if streak < 1:
        return 0.0
    return min(MAX_BACKOFF_S, FIRST_BACKOFF_S * 2.0 ** (streak - 1))


@dataclass
class BlockFault:
    """What one block's faults have been so far, and whether it is backing off now."""

    counts: dict[str, int]
    reason: str | None = None
    kind: str | None = None
    at: float | None = None
    #: unexpected exceptions in a row (0 once a step succeeds)
    streak: int = 0
    #: bus time before which the block is not stepped (``None``: it runs)
    retry_at: float | None = None
    backoff_s: float = 0.0
    resets: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"faults": sum(self.counts.values()), **self.counts, "last_reason": self.reason,
                "last_kind": self.kind, "last_time": self.at, "streak": self.streak,
                "backing_off": self.retry_at is not None, "retry_at": self.retry_at,
                "backoff_s": self.backoff_s, "resets": self.resets}


class BlockFaults:
    """Every block's faults and backoff, kept by the runtime (see the module notes)."""

    def __init__(self) -> None:
        self.by_block: dict[str, BlockFault] = {}

    def _of(self, block: str) -> BlockFault:
        f = self.by_block.get(block)
        if f is None:
            f = self.by_block[block] = BlockFault({k: 0 for k in FAULT_KINDS})
        return f

    def count(self, block: str, kind: str, reason: str, t: float | None) -> BlockFault:
        """Count a fault of ``kind`` (a refusal or a non-finite output: no backoff)."""
        f = self._of(block)
        f.counts[kind] += 1
        f.reason, f.kind, f.at = reason, kind, t
        return f

    def exception(self, block: Any, exc: BaseException, t: float | None) -> str:
        """An unexpected exception of ``block`` at bus time ``t``: count it, reset the block
        and start (or lengthen) its backoff. Returns the reason its outputs carry."""
        name = block.name
        reason = describe(exc)
        f = self.count(name, "exception", reason, t)
        f.streak += 1
        f.backoff_s = backoff_after(f.streak)
        f.retry_at = (t if t is not None and math.isfinite(t) else 0.0) + f.backoff_s
        reset = getattr(block, "reset", None)
        if callable(reset):
            try:
                reset()
                f.resets += 1
            except Exception as again:  # a reset that fails too: the backoff still holds
                log.warning("block %s: reset after %s failed: %s", name, reason, describe(again))
        if f.streak in (1, 2, 5) or f.streak % 10 == 0:
            log.warning("block %s faulted (%d in a row) at bus time %s: %s; reset, retried in %g s",
                        name, f.streak, f"{t:.3f}" if t is not None else "?", reason, f.backoff_s)
        return f"{reason} (block faulted; retried at bus time {f.retry_at:.3f}, backoff {f.backoff_s:g} s)"

    def waiting(self, name: str, t: float) -> str | None:
        """The reason ``name`` is not stepped at bus time ``t`` (backing off), else ``None``."""
        f = self.by_block.get(name)
        if f is None or f.retry_at is None:
            return None
        if t + 1e-9 >= f.retry_at:
            return None  # due again: the next step is the retry
        return (f"block faulted: {f.reason}; backing off {f.backoff_s:g} s, "
                f"retry at bus time {f.retry_at:.3f}")

    def stepped(self, name: str) -> None:
        """A step of ``name`` that raised nothing: its streak and backoff end."""
        f = self.by_block.get(name)
        if f is not None and (f.streak or f.retry_at is not None):
            if f.streak:
                log.info("block %s recovered after %d fault(s) in a row", name, f.streak)
            f.streak, f.retry_at, f.backoff_s = 0, None, 0.0

    def backing_off(self) -> list[str]:
        """The blocks that are backing off now."""
        return sorted(n for n, f in self.by_block.items() if f.retry_at is not None)

    def forget(self, name: str) -> None:
        self.by_block.pop(name, None)

    def report(self) -> dict[str, dict[str, Any]]:
        return {n: f.as_dict() for n, f in sorted(self.by_block.items())}


__all__ = ["FAULT_KINDS", "FIRST_BACKOFF_S", "MAX_BACKOFF_S", "BlockFault", "BlockFaults",
           "backoff_after", "describe"]
