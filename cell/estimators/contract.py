r"""The one observer contract: what every observer of the cell does the same way.

An observer is a runtime block (family ``observer``) that subclasses
:class:`ObserverContract` and fills in four hooks:

``_observe(t, inputs) -> outputs``
    One tick of the observer proper, on inputs the contract has found plausible.
``estimate() -> Estimate | None``
    What it exposes: the state ``x``, its covariance ``P``, the last innovations ``y``
    and their NIS (``None`` before the first step).
``_restart(reason)``
    Forget the estimate, so that the next valid tick starts over (a reset).
``_design_payload()`` / ``_check_design(design)`` / ``_use_design(checked)``
    Optional: what a design file holds beyond the tunable parameters (the defaults put
    the parameters in a design and take them back).

The contract owns, for every observer:

- **Input plausibility.** Each input channel (and each sample stream) may declare a range
  ``(lo, hi)`` (:meth:`ObserverContract.declare`); a value outside it, or NaN/inf in any
  input, is not stepped on. The tick raises :class:`InputRefused` (an
  :class:`ArithmeticError`), so the runtime marks the outputs invalid with the reason
  (``input P_IM = -3 outside its plausible range [5, 400]``) and the previous estimate is
  kept.
- **The gap policy.** After ``gap_ticks`` ticks without a valid input (refused inputs, or
  ticks the runtime skipped because an input was stale; for a stream observer, ticks
  without samples) the outputs say ``stale: ...``. When valid input comes back after such
  a gap, the estimate restarts (``resumed after a gap of ...``), counted in ``gaps``.
- **Divergence.** An exception from the observer's numerics (:class:`ArithmeticError`,
  :class:`ValueError`, :class:`TypeError`: a complex power, a singular matrix), a
  non-finite ``x`` or ``P``, ``P`` not positive definite (a non-positive diagonal),
  ``x`` outside the declared state bounds, or a NIS above its chi-square bound for
  ``nis_window`` updates in a row: the observer restarts, the tick raises
  :class:`~cell.estimators.core.Diverged` with the reason, and :meth:`state` shows it
  (``contract.resets``, ``contract.last_reset_reason``).
- **The exposed state**: :meth:`state` merges the observer's own (``_state()``) with
  ``contract``: status, reason, counts, and ``x``, ``P``, ``y``, ``nis``.
- **Naming.** Estimates end in ``_EST`` (the observers' DBC signals); the confidence is
  ``<NAME>_CONF`` (the block name in capitals, ``-`` as ``_``); a sigma band from ``P``
  is ``<CHANNEL>_SD`` for the states declared with one.
- **The confidence output** ``<NAME>_CONF`` in 0..1: 0 on a refused or stale tick and just
  after a restart; rises linearly over ``settle_ticks`` valid ticks; times
  ``min(1, b / mean NIS)`` over the last 20 updates, with ``b`` the 99 % chi-square bound
  of that mean, for an observer that exposes a NIS.
- **Designs.** :meth:`design` gives the observer's design as a JSON object
  ``{"format": "testcell-design/1", "observer": NAME, "params": {...}, ...}``;
  :meth:`load_design` takes one back, validated as a whole (a file naming another
  observer, a bad field: :class:`DesignError` naming it, and the previous design kept).
  :func:`read_design` and :func:`write_design` are the file side.

Blocks that follow the contract say so with the class attribute ``observer_contract = True``
(:func:`follows_contract`): the contract test finds every registered observer by it.
"""

from __future__ import annotations

import collections
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import scipy.stats

from cell.core.errors import ConfigError, ParamError
from cell.estimators.core import Diverged
from cell.runtime.blocks import Block

log = logging.getLogger(__name__)

#: The format tag of a design file.
DESIGN_FORMAT = "testcell-design/1"
#: Updates over which the confidence averages the NIS.
NIS_MEAN_WINDOW = 20

Range = tuple[float, float]


class InputRefused(ArithmeticError):
    """An input was implausible, or the observer has had none for too long; the message says which."""


class DesignError(ConfigError):
    """A design was refused; the message names the field (and the file, when there is one)."""


@dataclass
class Estimate:
    """What an observer exposes after a step."""

    x: np.ndarray
    """State estimate."""
    P: np.ndarray | None = None
    """Its covariance (``None`` for an observer without one)."""
    y: np.ndarray | None = None
    """Last innovations (measured minus predicted)."""
    nis: float | None = None
    """Normalised innovation squared of the last update."""
    dof: int = 0
    """Degrees of freedom of the NIS (measurements per update)."""


def follows_contract(block: Any) -> bool:
    """Whether ``block`` is an observer on the contract (the marker the contract test uses)."""
    return bool(getattr(block, "observer_contract", False))


def confidence_channel(name: str) -> str:
    """``<NAME>_CONF`` of a block name (``airpath-default`` -> ``AIRPATH_DEFAULT_CONF``)."""
    return name.upper().replace("-", "_") + "_CONF"


class _Record:
    """The contract's bookkeeping for one observer."""

    def __init__(self) -> None:
        self.status = "starting"
        self.reason: str | None = None
        self.resets = 0
        self.last_reset_reason: str | None = None
        self.gaps = 0
        self.refused: collections.Counter[str] = collections.Counter()
        self.bad_run = 0
        self.t_step: float | None = None
        self.t_valid: float | None = None
        self.period: float | None = None
        self.resume = False
        self.valid_ticks = 0
        self.nis_run = 0
        self.nis_hist: collections.deque[float] = collections.deque(maxlen=NIS_MEAN_WINDOW)
        self.samples = 0


class ObserverContract(Block):
    """Base of every observer: plausibility, gaps, divergence, state, naming, designs, confidence.

    A subclass calls ``super().__init__(name, inputs, outputs, rate, units=...)`` and then
    :meth:`declare` once (it adds the confidence and sigma outputs), and implements
    :meth:`_observe`, :meth:`estimate` and :meth:`_restart` (module docstring). Its own
    ``state()`` goes in ``_state()``.
    """

    observer_contract: ClassVar[bool] = True
    kind = "observer"
    family = "observer"

    # -- declaration ---------------------------------------------------------------------
    def declare(self, *, ranges: Mapping[str, Range] | None = None,
                sample_ranges: Mapping[str, Range] | None = None,
                state_bounds: Sequence[Range] | None = None, gap_ticks: int = 10,
                settle_ticks: int = 10, nis_gate: float = 0.9999, nis_window: int = 0,
                sd: Mapping[int, str] | None = None, sd_units: Mapping[str, str] | None = None
                ) -> None:
        """Declare the contract's settings and add its outputs.

        Parameters
        ----------
        ranges:
            Input channel -> plausible ``(lo, hi)``, inclusive; other inputs need only be finite.
        sample_ranges:
            Stream -> plausible ``(lo, hi)`` of its samples (a frame with one outside is skipped).
        state_bounds:
            Per state of :meth:`estimate`'s ``x``, the ``(lo, hi)`` beyond which it has diverged.
        gap_ticks:
            Ticks without valid input after which the outputs are stale and the estimate
            restarts when input comes back.
        settle_ticks:
            Valid ticks after a (re)start over which the confidence rises from 0 to 1.
        nis_gate, nis_window:
            Restart after ``nis_window`` updates in a row whose NIS exceeds the ``nis_gate``
            chi-square quantile (0: off; an observer whose core does this itself leaves it off).
        sd:
            State index -> channel of its sigma band :math:`\\sqrt{P_{ii}}`.
        """
        for ch, (lo, hi) in (ranges or {}).items():
            if ch not in self.inputs:
                raise ParamError("ranges", f"{ch} is not an input of {self.name}")
            if not lo <= hi:
                raise ParamError("ranges", f"{ch}: lower bound {lo} above upper bound {hi}")
        if gap_ticks < 1 or settle_ticks < 1:
            raise ParamError("gap_ticks", "gap_ticks and settle_ticks must be >= 1")
        self.ranges = {ch: (float(lo), float(hi)) for ch, (lo, hi) in (ranges or {}).items()}
        self._range_list = [(ch, *self.ranges.get(ch, (-math.inf, math.inf))) for ch in self.inputs]
        self.sample_ranges = {s: (float(lo), float(hi)) for s, (lo, hi) in (sample_ranges or {}).items()}
        self.state_bounds = None if state_bounds is None else np.asarray(state_bounds, dtype=float)
        self.gap_ticks, self.settle_ticks = int(gap_ticks), int(settle_ticks)
        self.contract_nis_gate, self.contract_nis_window = float(nis_gate), int(nis_window)
        self.conf_channel = confidence_channel(self.name)
        self.sd_channels = dict(sd or {})
        new = [self.conf_channel, *self.sd_channels.values()]
        self.outputs = [o for o in self.outputs if o not in new] + new
        self.units.setdefault(self.conf_channel, "1")
        self.units.update(sd_units or {})
        self._rec = _Record()
        self._sd_idx = list(self.sd_channels)
        self._sd_out = list(self.sd_channels.values())

    # -- the hooks -------------------------------------------------------------------------
    def _observe(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        raise NotImplementedError

    def estimate(self) -> Estimate | None:
        """The observer's current state, covariance, innovations and NIS (``None``: none yet)."""
        return None

    def _restart(self, reason: str) -> None:
        """Forget the estimate: the next valid tick starts over."""
        raise NotImplementedError

    def _state(self) -> dict[str, Any]:
        return {}

    # -- stepping ----------------------------------------------------------------------------
    def _refuse(self, status: str, reason: str) -> None:
        rec = self._rec
        rec.status, rec.reason = status, reason
        raise InputRefused(reason)

    def _implausible(self, inputs: Mapping[str, float]) -> tuple[str, str] | None:
        """``(what, reason)`` of the first implausible input, or ``None``."""
        for ch, lo, hi in self._range_list:
            v = inputs[ch]
            if not lo <= v <= hi:  # NaN fails both
                if math.isfinite(v):
                    return ch, f"input {ch} = {v:g} outside its plausible range [{lo:g}, {hi:g}]"
                return ch, f"input {ch} is {v}"
        return None

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        rec = self._rec
        if rec.t_step is not None and t > rec.t_step:
            dt = t - rec.t_step
            rec.period = dt if rec.period is None or dt < rec.period else rec.period
        rec.t_step = t
        bad = self._implausible(inputs)
        quiet = None
        if bad is None and self.streams:
            bad, quiet = self._stream_gap()
        if bad is not None or quiet is not None:
            rec.bad_run += 1
            what, reason = bad if bad is not None else ("samples", quiet)
            if bad is not None:
                rec.refused[what] += 1
                rec.valid_ticks = 0
            if rec.bad_run >= self.gap_ticks:
                rec.resume = rec.resume or rec.t_valid is not None
                rec.valid_ticks = 0
                self._refuse("stale", f"stale: no valid input for {rec.bad_run} ticks ({reason})")
            if bad is not None:
                self._refuse("invalid", reason)
        if quiet is None:
            if (rec.t_valid is not None and rec.period is not None
                    and t - rec.t_valid > (self.gap_ticks + 0.5) * rec.period):
                rec.resume = True
            if rec.resume:
                gap = t - rec.t_valid if rec.t_valid is not None else 0.0
                rec.gaps += 1
                self._reset_estimate(f"resumed after a gap of {gap:.3g} s without valid input")
            rec.resume = False
            rec.bad_run = 0
            rec.t_valid = t
        self.errors = {}
        try:
            with np.errstate(all="ignore"):
                out = self._observe(t, inputs)
        except Diverged as exc:  # the core has reset itself
            self._diverged(f"diverged: {exc}")
        except (ArithmeticError, ValueError, TypeError) as exc:
            self._diverged(f"diverged: {type(exc).__name__} in the model: {exc}")
        est = self.estimate()
        if est is not None:
            why = self._check(est)
            if why is not None:
                self._diverged(f"diverged: {why}")
        rec.valid_ticks += 1
        rec.status, rec.reason = "ok", None
        out[self.conf_channel] = self._confidence(est)
        if self._sd_out and est is not None and est.P is not None:
            d = np.sqrt(np.diagonal(est.P)).tolist()
            for i, ch in zip(self._sd_idx, self._sd_out):
                out[ch] = d[i]
        return out

    def _check(self, est: Estimate) -> str | None:
        """Why the estimate has diverged, or ``None``."""
        x = est.x
        if not np.isfinite(x).all():
            return f"non-finite state {x.tolist()}"
        b = self.state_bounds
        if b is not None:
            out = (x < b[:, 0]) | (x > b[:, 1])
            if out.any():
                i = int(np.argmax(out))
                return (f"state {self._state_name(i)} = {x[i]:.6g} beyond its bounds "
                        f"[{b[i, 0]:g}, {b[i, 1]:g}]")
        P = est.P
        if P is not None:
            if not np.isfinite(P).all():
                return "non-finite covariance P"
            dg = np.diagonal(P)
            if not (dg > 0.0).all():
                return f"covariance P not positive definite (diagonal {dg.tolist()})"
        if est.nis is not None:
            rec = self._rec
            rec.nis_hist.append(est.nis)
            if self.contract_nis_window > 0:
                bound = _chi2_ppf(self.contract_nis_gate, max(est.dof, 1))
                rec.nis_run = rec.nis_run + 1 if est.nis > bound else 0
                if rec.nis_run >= self.contract_nis_window:
                    return (f"NIS above {bound:.4g} (chi-square {est.dof} dof) in "
                            f"{rec.nis_run} consecutive updates, last {est.nis:.4g}")
        return None

    def _state_name(self, i: int) -> str:
        names = getattr(self, "state_names", None)
        return names[i] if names is not None and i < len(names) else f"x[{i}]"

    def _diverged(self, reason: str) -> None:
        self._reset_estimate(reason)
        rec = self._rec
        rec.status, rec.reason = "diverged", reason
        log.debug("%s %s", self.name, reason)
        raise Diverged(reason)

    def _reset_estimate(self, reason: str) -> None:
        rec = self._rec
        rec.resets += 1
        rec.last_reset_reason = reason
        rec.valid_ticks = rec.nis_run = 0
        rec.nis_hist.clear()
        self._restart(reason)

    def _confidence(self, est: Estimate | None) -> float:
        rec = self._rec
        conf = min(1.0, rec.valid_ticks / self.settle_ticks)
        if est is not None and est.nis is not None and rec.nis_hist:
            mean = sum(rec.nis_hist) / len(rec.nis_hist)
            n = len(rec.nis_hist)
            bound = _chi2_ppf(0.99, max(est.dof, 1) * n) / n
            if mean > bound:
                conf *= bound / mean
        return conf

    # -- sample streams --------------------------------------------------------------------
    def samples(self, stream: str, index: int, values: np.ndarray, t: float) -> None:
        """Consume a frame of samples, unless one is implausible (then the frame is skipped,
        counted, and the next tick says why)."""
        lo, hi = self.sample_ranges.get(stream, (-math.inf, math.inf))
        vmin, vmax = float(values.min()), float(values.max())
        if not (lo <= vmin and vmax <= hi):  # NaN fails
            rec = self._rec
            rec.refused[stream] += 1
            bad = vmin if not lo <= vmin else vmax
            self._sample_reason = (f"samples of {stream} implausible ({bad:g} outside "
                                   f"[{lo:g}, {hi:g}])" if math.isfinite(bad)
                                   else f"samples of {stream} not finite")
            return
        self._rec.samples += 1
        self._samples(stream, index, values, t)

    def _stream_gap(self) -> tuple[tuple[str, str] | None, str | None]:
        """For a stream observer at a tick: ``(refused, quiet)``: the implausible frames since
        the last tick, or why no valid samples came (not refused until ``gap_ticks``)."""
        rec = self._rec
        got, rec.samples = rec.samples, 0
        why, self._sample_reason = getattr(self, "_sample_reason", None), None
        if why is not None:
            return (self.streams[0], why), None
        return None, None if got else f"no samples of {', '.join(self.streams)}"

    # -- state -----------------------------------------------------------------------------
    def contract_state(self) -> dict[str, Any]:
        """The contract's part of :meth:`state` (JSON)."""
        rec = self._rec
        est = self.estimate()
        out: dict[str, Any] = {
            "status": rec.status, "reason": rec.reason, "resets": rec.resets,
            "last_reset_reason": rec.last_reset_reason, "gaps": rec.gaps,
            "refused": dict(rec.refused), "gap_ticks": self.gap_ticks,
            "ranges": {ch: list(r) for ch, r in self.ranges.items()},
            "x": None, "P": None, "innovations": None, "nis": None,
        }
        if est is not None:
            out["x"] = _finite_list(est.x)
            out["P"] = None if est.P is None else [_finite_list(r) for r in est.P]
            out["innovations"] = None if est.y is None else _finite_list(est.y)
            out["nis"] = est.nis if est.nis is None or math.isfinite(est.nis) else None
        return out

    def state(self) -> dict[str, Any]:
        return {**self._state(), "contract": self.contract_state()}

    # -- designs ---------------------------------------------------------------------------
    def design(self) -> dict[str, Any]:
        """The observer's design as a JSON object naming it (:data:`DESIGN_FORMAT`)."""
        return {"format": DESIGN_FORMAT, "observer": self.name, "params": self.params(),
                **self._design_payload()}

    def _design_payload(self) -> dict[str, Any]:
        return {}

    def _check_design(self, design: Mapping[str, Any]) -> Any:
        """Validate the observer's own part of a design; return what :meth:`_use_design` takes.
        Raise :class:`DesignError` or :class:`ParamError`; change nothing."""
        return None

    def _use_design(self, checked: Any) -> None:
        pass

    def load_design(self, design: Any, source: str = "design") -> None:
        """Take a design (a :meth:`design` object), validated as a whole: on any bad field
        :class:`DesignError` names it and the previous design stays. The estimate restarts."""
        if not isinstance(design, Mapping):
            raise DesignError(f"{source}: a design is a JSON object, got {type(design).__name__}")
        fmt = design.get("format", DESIGN_FORMAT)
        if fmt != DESIGN_FORMAT:
            raise DesignError(f"{source}: format {fmt!r} is not {DESIGN_FORMAT!r}")
        who = design.get("observer")
        if who != self.name:
            raise DesignError(f"{source}: names observer {who!r}, not {self.name!r}"
                              if who is not None else f"{source}: field 'observer' is missing "
                              f"(the design must name its observer, here {self.name!r})")
        params = design.get("params", {})
        try:
            if not isinstance(params, Mapping):
                raise DesignError(f"{source}: field 'params' must be an object")
            checked_params = self.validate(dict(params)) if params else {}
            own = self._check_design(design)
        except ParamError as exc:
            raise DesignError(f"{source}: params.{exc.field}: {exc.message}") from None
        except DesignError as exc:
            raise DesignError(f"{source}: {exc}") if not str(exc).startswith(source) else exc
        self._use_design(own)
        if checked_params:
            self._apply(checked_params)
        self._reset_estimate(f"design loaded from {source}")


# -- files -------------------------------------------------------------------------------------
def read_design(path: str | Path) -> dict[str, Any]:
    """A design file's JSON object; :class:`DesignError` names a missing or unreadable file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DesignError(f"design {path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise DesignError(f"design {path}: not a readable JSON file: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("observer"), str):
        raise DesignError(f"design {path}: field 'observer' (the observer it is for) is missing")
    return data


def write_design(design: Mapping[str, Any], path: str | Path) -> Path:
    """Write a design object as JSON (refuses one that names no observer)."""
    if not isinstance(design.get("observer"), str):
        raise DesignError("a design must name its observer (field 'observer')")
    path = Path(path)
    path.write_text(json.dumps({"format": DESIGN_FORMAT, **design}, indent=1, allow_nan=False))
    return path


def _finite_list(a: Any) -> list[float | None]:
    return [v if math.isfinite(v) else None for v in np.asarray(a, dtype=float).ravel().tolist()]


_CHI2: dict[tuple[float, int], float] = {}


def _chi2_ppf(p: float, dof: int) -> float:
    key = (p, dof)
    v = _CHI2.get(key)
    if v is None:
        v = _CHI2[key] = float(scipy.stats.chi2.ppf(p, dof))
    return v


__all__ = ["DESIGN_FORMAT", "DesignError", "Estimate", "InputRefused", "ObserverContract",
           "confidence_channel", "follows_contract", "read_design", "write_design"]
