"""What one running cell is made of: its runtime, bus, tuning store and live loop."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cell.core import registry
from cell.app.live import LiveCell
from cell.runtime.scheduler import Runtime
from cell.app.tuning import TuningStore


@dataclass
class Cell:
    """Everything the HTTP service needs to show and tune a cell."""

    runtime: Runtime
    bus: str = "none"
    tuning: TuningStore | None = None
    live: LiveCell | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def tune(self, family: str, name: str, changes: dict[str, Any]) -> dict[str, Any]:
        """Apply a parameter change to a block of ``family`` and save it; all or nothing."""
        rt = self.runtime
        with rt.lock:
            block = rt.block(name, family)
            before = block.params()
            params = block.set_params(changes)
            if self.tuning is not None:
                try:
                    self.tuning.record(registry.FAMILIES[family].section, name, params)
                except Exception:
                    block.set_params(before)
                    raise
            return params

    def find(self, family: str, name: str):
        return self.runtime.block(name, family)

    def names(self, family: str) -> list[str]:
        return [b.name for b in self.runtime.blocks.values() if b.family == family]


__all__ = ["Cell"]
