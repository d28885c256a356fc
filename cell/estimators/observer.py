r"""Model-based observers as runtime blocks: a :class:`~cell.estimators.core.Model` on the
:class:`~cell.estimators.core.KalmanCore`.

At each tick of its rate (MED by default) an :class:`ObserverBlock`

1. reads the model inputs :math:`u_k` and the measurements :math:`z_k` from their channels;
2. predicts from the previous tick over :math:`\Delta t = t_k - t_{k-1}` (the tick period,
   taken from successive bus times) with the inputs of the previous tick held,
   :math:`\hat x_{k|k-1} = f_{\Delta t}(\hat x_{k-1|k-1}, u_{k-1})` (seed 000, eq. 22);
3. corrects with the measured outputs, :math:`\hat x_{k|k} = \hat x_{k|k-1} + K_k (z_k -
   h(\hat x_{k|k-1}, u_k))`;
4. publishes the states and the predicted outputs as channels.

The first tick only corrects ``x0``. Channel names follow one convention:

- ``<PREFIX>_<STATE>``: the a-posteriori estimate of each model state;
- ``<PREFIX>_<OUTPUT>_HAT``: the a-priori prediction :math:`h(\hat x_{k|k-1}, u_k)` of each
  model output (the one the innovation is taken against; outputs that are not measured are
  predicted too).

``PREFIX`` defaults to the block's name. A step that diverges resets the filter to
``x0``/``P0`` and raises :class:`~cell.estimators.core.Diverged` (an
:class:`ArithmeticError`): the runtime marks that tick's outputs invalid, nothing non-finite
is ever published, and :meth:`ObserverBlock.state` shows the reset count and reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from cell.runtime.blocks import Block, Param
from cell.core.errors import ParamError
from cell.estimators.core import GainSchedule, KalmanCore, Model


def _finite_or_none(v: float | None) -> float | None:
    return v if v is None or math.isfinite(v) else None


class ObserverBlock(Block):
    """A Kalman / extended Kalman observer of a :class:`Model`, stepped by the runtime.

    Parameters
    ----------
    name:
        Block name; also the default channel prefix.
    model:
        The observer's model (states, inputs, outputs, ``f``, ``h``, params).
    inputs:
        Model input -> channel it is read from (default: the channel of the input's name).
    measurements:
        Model output -> channel of its measurement, for the outputs the filter corrects
        with (default: every output, from the channel of its name).
    Q, R:
        Process noise (one variance per state) and measurement noise (one per
        measurement) as diagonals; a number means that times the identity.
    x0, P0:
        Initial state (default zeros) and diagonal covariance (default ones); a reset
        returns to them. In a constant-gain mode ``P0`` should be the stationary a-priori
        covariance: it gives ``S`` and the NIS.
    prefix:
        Channel prefix (default ``name``).
    gain:
        ``None`` (full EKF), a constant ``n`` x ``m`` gain, or a :class:`GainSchedule`
        over the ``schedule`` channels.
    schedule:
        Channels of the scheduling variables of a :class:`GainSchedule`, one per axis.
    constraint:
        State constraint ``x -> x`` (e.g. :func:`~cell.estimators.core.bounds`).
    nis_gate, nis_window:
        Reset after ``nis_window`` consecutive updates whose NIS exceeds the ``nis_gate``
        chi-square quantile (0, the default, disables it).
    units:
        Output channel -> unit; by default from ``model.units``.
    channels:
        Model state -> channel name of its estimate, overriding ``<PREFIX>_<STATE>`` (e.g.
        ``{"P_EM": "P_EM_EST"}`` to publish a DBC signal of that name).

    Tunable parameters (``set_params``, all or nothing): ``Q``, ``R``, ``P0`` (lists of
    diagonal elements), ``x0`` (a list), ``nis_gate`` and ``nis_window``. New ``Q``/``R``
    act from the next tick and keep the estimate; new ``x0``/``P0`` act at the next reset
    (:meth:`reset`).
    """

    kind = "observer"
    family = "observer"

    def __init__(
        self,
        name: str,
        model: Model,
        *,
        inputs: Mapping[str, str] | None = None,
        measurements: Mapping[str, str] | None = None,
        Q: Any,
        R: Any,
        x0: Any = None,
        P0: Any = 1.0,
        prefix: str | None = None,
        rate: str = "MED",
        gain: Any = None,
        schedule: Sequence[str] = (),
        constraint: Callable[[np.ndarray], np.ndarray] | None = None,
        nis_gate: float = 0.9999,
        nis_window: int = 0,
        units: Mapping[str, str] | None = None,
        channels: Mapping[str, str] | None = None,
    ) -> None:
        self.model = model
        inputs = dict(inputs) if inputs is not None else {i: i for i in model.inputs}
        measurements = (dict(measurements) if measurements is not None
                        else {o: o for o in model.outputs})
        if set(inputs) != set(model.inputs):
            raise ParamError("inputs", f"must map each model input ({', '.join(model.inputs) or 'none'}) "
                                       f"to a channel, got {', '.join(inputs) or 'none'}")
        if not measurements or not set(measurements) <= set(model.outputs):
            raise ParamError("measurements", f"must map one or more model outputs "
                                             f"({', '.join(model.outputs)}) to channels, got "
                                             f"{', '.join(measurements) or 'none'}")
        if isinstance(gain, GainSchedule) != bool(schedule) or len(schedule) != (
                len(gain.grid) if isinstance(gain, GainSchedule) else 0):
            raise ParamError("schedule", "give one scheduling channel per axis of a GainSchedule "
                                         "gain, and none otherwise")
        self._u_ch = [inputs[i] for i in model.inputs]
        self._rows = [model.outputs.index(o) for o in measurements]
        self._z_ch = list(measurements.values())
        self._s_ch = list(schedule)
        prefix = prefix or name
        if channels and not set(channels) <= set(model.states):
            raise ParamError("channels", f"must name model states ({', '.join(model.states)}), got "
                                         f"{', '.join(channels)}")
        self._x_out = [(channels or {}).get(s, f"{prefix}_{s}") for s in model.states]
        self._hat_out = [f"{prefix}_{o}_HAT" for o in model.outputs]
        unit_map = dict(zip(self._x_out, model.states)) | dict(zip(self._hat_out, model.outputs))
        model_units = {ch: model.units[q] for ch, q in unit_map.items() if q in model.units}
        super().__init__(name, list(dict.fromkeys(self._u_ch + self._z_ch + self._s_ch)),
                         self._x_out + self._hat_out, rate, units=model_units | dict(units or {}))
        n, m = len(model.states), len(measurements)
        self.PARAMS = {
            "Q": Param("Q", float, "process noise covariance, one variance per state",
                       shape="diag", size=n, pd=True),
            "R": Param("R", float, "measurement noise covariance, one variance per measurement",
                       shape="diag", size=m, pd=True),
            "x0": Param("x0", float, "initial state, taken at the next reset", shape="vector",
                        size=n, ge=-1e6, le=1e6),
            "P0": Param("P0", float, "initial covariance (diagonal), taken at the next reset",
                        shape="diag", size=n, pd=True),
            "nis_gate": Param("nis_gate", float, "chi-square probability of the NIS gate",
                              ge=0.5, le=1.0 - 1e-12),
            "nis_window": Param("nis_window", int,
                                "consecutive updates above the NIS gate that reset (0: off)",
                                ge=0, le=1_000_000),
        }
        checked = self.validate({"Q": Q, "R": R, "x0": np.zeros(n) if x0 is None else x0,
                                 "P0": P0, "nis_gate": nis_gate, "nis_window": nis_window})
        try:
            self.core = KalmanCore(checked["x0"], np.diag(checked["P0"]), np.diag(checked["Q"]),
                                   np.diag(checked["R"]), gain=gain, constraint=constraint,
                                   name=name)
        except ValueError as exc:
            raise ParamError("gain", str(exc)) from None
        self._apply(checked)
        self._t: float | None = None
        self._u: np.ndarray | None = None

    # -- parameters -----------------------------------------------------------------------
    def _apply(self, checked: dict[str, Any]) -> None:
        super()._apply(checked)
        core = self.core
        core.Q, core.R = np.diag(self.Q), np.diag(self.R)
        core.x0, core.P0 = np.array(self.x0), np.diag(self.P0)
        core.nis_gate, core.nis_window = self.nis_gate, self.nis_window
        if core.mode != "full":  # P is not propagated: it is P0
            core.P = core.P0.copy()

    def reset(self) -> None:
        """Restart from ``x0``/``P0`` at the next tick (counted as a reset)."""
        self.core.reset("reset requested")
        self._t = self._u = None

    # -- stepping -------------------------------------------------------------------------
    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        for ch in self.inputs:
            if not math.isfinite(inputs[ch]):
                raise ArithmeticError(f"input {ch} is {inputs[ch]}")
        u = np.array([inputs[c] for c in self._u_ch], dtype=float)
        z = np.array([inputs[c] for c in self._z_ch], dtype=float)
        core, model = self.core, self.model
        t_prev, u_prev = self._t, self._u
        self._t, self._u = t, u
        if t_prev is not None and t > t_prev:
            f, F = model.transition(t_prev, t - t_prev)
            core.predict(u_prev, F=F, f=f)
        x_prior = core.x
        h, H = model.measurement(t, u, self._rows)
        core.update(z, H=H, h=h, s=[inputs[c] for c in self._s_ch] or None)
        with np.errstate(all="ignore"):
            z_hat = model.output(t, x_prior, u)
        if not np.isfinite(z_hat).all():
            core.diverge("nonfinite", f"non-finite predicted output {z_hat.tolist()}")
        return dict(zip(self._x_out, core.x.tolist())) | dict(zip(self._hat_out, z_hat.tolist()))

    def state(self) -> dict[str, Any]:
        """Estimate, covariance, gain and the last update's innovation statistics (JSON)."""
        core = self.core
        return {"t": self._t, "mode": core.mode, "states": list(self.model.states),
                **core_state(core), "log_likelihood": _finite_or_none(core.log_likelihood)}


def core_state(core: KalmanCore) -> dict[str, Any]:
    """A Kalman core's estimate, covariance, gain, last innovation and reset record (JSON):
    the part of ``GET /observers/{name}`` every observer on the core shares."""
    return {
        "x": core.x.tolist(),
        "P_diag": np.diag(core.P).tolist(),
        "P": core.P.tolist(),
        "K": core.K.tolist(),
        "y": core.y.tolist(),
        "S": core.S.tolist(),
        "nis": core.nis,
        "nis_threshold": core.nis_threshold,
        "updates": core.updates,
        "resets": core.resets,
        "last_reset_reason": core.last_reset_reason,
        "guard_count": core.guard_count,
    }


__all__ = ["ObserverBlock", "core_state"]
