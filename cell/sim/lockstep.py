"""The one loop: frames, then ticks, on bus time, with a simulator and (optionally) a runtime.

Everything that runs the cell faster than real time goes through here: writing a log
(simulator alone), replaying one (runtime alone), extracting a channel's series, running an
experiment (simulator and runtime in closed loop), and the tests.

- :class:`Lockstep` steps a :class:`~cell.sim.simulator.Simulator` and, if given, a
  :class:`~cell.runtime.scheduler.Runtime`: at every plant step the frames due go to the runtime
  (stamped with simulation time, which is the bus time), the runtime runs the ticks due up
  to that time, and the frames in its outbox (demands) go back to the simulator, before the
  plants step. Only CAN frames pass between the two, as on the live bus.
- :func:`feed` runs a runtime over frames that already exist (a log), calling ``on_tick``
  at every MED tick and finishing the ticks due at the last frame's time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import nullcontext

import can

from cell.runtime.feed import Fed, TickListener, Listening, feed
from cell.runtime.scheduler import Runtime
from cell.sim.simulator import Simulator

__all__ = ["Fed", "Lockstep", "TickListener", "feed"]

class Lockstep:
    """A simulator and (optionally) a runtime stepped together on one bus-time axis.

    Parameters
    ----------
    sim:
        The simulator.
    runtime:
        The runtime, or ``None`` to run the simulator alone (writing a log).
    stride:
        Plant steps between the exchanges with the runtime (default 1, every step). When
        every block ticks at a rate whose period is a multiple of ``stride`` steps, and every
        message's cycle time divides it, the frames of the steps in between are overwritten
        before any tick reads them, so a stride of one tick gives the same numbers faster.
    on_tick:
        Called with the bus time at every MED tick of the runtime.
    wire:
        What the bus does to the simulator's frames on their way to the runtime (drop,
        reorder: a lossy bus in a test); ``None`` delivers them all, in order.
    """

    def __init__(self, sim: Simulator, runtime: Runtime | None = None, *, stride: int = 1,
                 on_tick: TickListener | None = None,
                 wire: Callable[[list[can.Message]], list[can.Message]] | None = None) -> None:
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        self.sim = sim
        self.runtime = runtime
        self.stride = stride
        self.on_tick = on_tick
        self.wire = wire

    def steps(self, n: int, frames: bool = False) -> Iterator[tuple[int, list[can.Message]]]:
        """Run ``n`` plant steps; yield ``(k, frames)`` after each exchange, before the step.

        ``frames`` are those of step ``k`` (always encoded when ``frames`` is true, else only
        on exchange steps). Code in the loop body sees the runtime's channels at time
        ``t_k`` and may act on the simulator (or stop the run with ``break``) before the
        plants advance.
        """
        sim, rt = self.sim, self.runtime
        with Listening(rt, self.on_tick) if rt is not None else nullcontext():
            for _ in range(n):
                k = sim.k
                exchange = rt is not None and k % self.stride == 0
                out = sim.frames() if (frames or exchange) else []
                if exchange:
                    rt.ingest_many(out if self.wire is None else self.wire(out))
                    rt.advance(sim.t0 + sim.t)
                    for msg in rt.take_outbox():
                        sim.receive(msg)
                yield k, out
                sim.step()

    def frames(self, n: int) -> Iterator[can.Message]:
        """The frames of ``n`` plant steps, in time order."""
        for _, out in self.steps(n, frames=True):
            yield from out

    def run(self, duration: float) -> None:
        """Run for ``duration`` seconds of simulation time."""
        for _ in self.steps(round(duration / self.sim.dt)):
            pass
