"""The one interface every runtime block shares.

Native filters, observers, controllers and compiled scripts all look alike to the
runtime: named input channels, named output channels, their own state, a rate
(``FAS``/``MED``/``SLO``) and ``step(t, inputs) -> outputs`` once per tick of that rate.
The base class validates tunable parameters; subclasses fill ``_step`` and ``_apply``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from cell.core.errors import ParamError

RATE_NAMES = ("FAS", "MED", "SLO")


#: shapes a :class:`Param` can take (see its docstring)
SHAPES = ("scalar", "vector", "diag", "matrix")

Bound = float | tuple[float, ...] | None

#: Bounds of every element of a covariance (a positive-definite ``diag`` or ``matrix``
#: :class:`Param`) that declares none of its own: the range over which the estimators'
#: numerics are tested. 1e300 or 5e-324 is no noise variance.
COVARIANCE_BOUNDS = (1e-12, 1e6)


@dataclass(frozen=True)
class Param:
    """A tunable parameter: its type, shape and the open or closed bounds it must respect.

    Shapes and their JSON form
    --------------------------
    ``scalar`` (default)
        A number; ``type`` is ``float`` or ``int``.
    ``vector``
        A list of ``size`` numbers, e.g. an initial state ``x0``. Checked into a 1-D float
        array.
    ``diag``
        A diagonal matrix, e.g. a covariance ``Q``, given as the list of its ``size``
        diagonal elements. Also accepted: the full nested list if it is diagonal, and a
        single number ``q`` meaning ``q`` times the identity. Checked into a 1-D float
        array of the diagonal, and given back (:meth:`dump`) as that list.
    ``matrix``
        A full symmetric ``size`` x ``size`` matrix as a nested list (rows). A list of
        ``size`` numbers or a single number is taken as a diagonal. Checked into a 2-D
        float array and given back as a nested list.

    Every element must be finite. The bounds ``gt``/``ge``/``le`` apply to each element
    of a vector or ``diag`` and to the diagonal of a ``matrix``; for these shapes a bound
    may also be a tuple with one bound per element. ``pd`` requires a ``diag`` or
    ``matrix`` to be positive definite (a ``diag``: every element > 0; a ``matrix``: a
    Cholesky factor exists). ``size`` of ``None`` accepts any length >= 1.
    """

    name: str
    type: type  # float or int
    doc: str
    gt: Bound = None
    ge: Bound = None
    le: Bound = None
    shape: str = "scalar"
    size: int | None = None
    pd: bool = False

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"Param {self.name}: shape must be one of {SHAPES}, got {self.shape!r}")
        if self.pd and self.gt is None and self.ge is None and self.le is None:
            object.__setattr__(self, "ge", COVARIANCE_BOUNDS[0])
            object.__setattr__(self, "le", COVARIANCE_BOUNDS[1])

    def check(self, value: Any) -> Any:
        """Return ``value`` converted to the parameter's type and shape, or raise :class:`ParamError`."""
        if self.shape != "scalar":
            return self._check_array(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(self.name, f"must be a number, got {type(value).__name__} {value!r}")
        given = value  # as sent: 1e300 is named so, not as the int it converts to
        if self.type is int:
            if isinstance(value, float):
                if not math.isfinite(value) or value != int(value):
                    raise ParamError(self.name, f"must be a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
            if not math.isfinite(value):
                raise ParamError(self.name, f"must be finite, got {value!r}")
        if self.gt is not None and not value > self.gt:
            raise ParamError(self.name, f"must be > {self.gt:g}, got {given!r}")
        if self.ge is not None and not value >= self.ge:
            raise ParamError(self.name, f"must be >= {self.ge:g}, got {given!r}")
        if self.le is not None and not value <= self.le:
            raise ParamError(self.name, f"must be <= {self.le:g}, got {given!r}")
        return value

    def dump(self, value: Any) -> Any:
        """The JSON form of a checked value: the number itself, or (nested) lists."""
        return value.tolist() if isinstance(value, np.ndarray) else value

    # -- vectors and matrices -----------------------------------------------------------
    def _check_array(self, value: Any) -> np.ndarray:
        arr = self._shaped(self._numbers(value))
        if self.shape == "matrix":
            if not np.all(np.isfinite(arr)):
                i, j = np.argwhere(~np.isfinite(arr))[0]
                raise ParamError(self.name, f"element [{i}][{j}] must be finite, "
                                            f"got {float(arr[i, j])!r}")
            if not np.allclose(arr, arr.T, rtol=1e-12, atol=0.0):
                i, j = np.argwhere(~np.isclose(arr, arr.T, rtol=1e-12, atol=0.0))[0]
                raise ParamError(self.name, f"must be symmetric: [{i}][{j}] = {float(arr[i, j])!r} but "
                                            f"[{j}][{i}] = {float(arr[j, i])!r}")
            arr = 0.5 * (arr + arr.T)
            self._check_elements(np.diagonal(arr), "diagonal element")
            if self.pd:
                try:
                    np.linalg.cholesky(arr)
                except np.linalg.LinAlgError:
                    low = np.linalg.eigvalsh(arr)[0]
                    raise ParamError(self.name, f"must be positive definite, its smallest "
                                                f"eigenvalue is {low:g}") from None
        else:
            label = "diagonal element" if self.shape == "diag" else "element"
            if self.pd and np.any(arr <= 0.0):  # first: the covariance bounds would word it
                i = int(np.argmax(arr <= 0.0))
                raise ParamError(self.name, f"must be positive definite: {label} [{i}] is "
                                            f"{float(arr[i])!r}")
            self._check_elements(arr, label)
        arr.flags.writeable = False
        return arr

    def _numbers(self, value: Any) -> np.ndarray:
        """``value`` as a float array, refusing anything but (nested lists of) numbers."""
        if isinstance(value, np.ndarray):
            value = value.tolist()

        def numeric(v: Any) -> bool:
            if isinstance(v, (list, tuple)):
                return all(numeric(e) for e in v)
            return isinstance(v, (int, float)) and not isinstance(v, bool)

        what = {"vector": "a list of numbers", "diag": "a list of diagonal elements",
                "matrix": "a nested list (rows) of numbers"}[self.shape]
        if not numeric(value):
            raise ParamError(self.name, f"must be {what}, got {type(value).__name__} {value!r}")
        try:
            return np.array(value, dtype=float)
        except ValueError:  # ragged nesting
            raise ParamError(self.name, f"must be {what} of equal lengths, got {value!r}") from None

    def _shaped(self, arr: np.ndarray) -> np.ndarray:
        """Bring a parsed array to the parameter's shape (1-D, or 2-D for ``matrix``)."""
        n, given = self.size, _shape_text(arr)
        expected = f"{n}" if n is not None else "one or more"
        if self.shape == "vector":
            if arr.ndim != 1 or arr.size == 0 or (n is not None and arr.size != n):
                raise ParamError(self.name, f"must be a list of {expected} numbers, got shape "
                                            f"{_shape_text(arr)}")
            return arr
        if arr.ndim == 0 and n is not None:  # a number: that times the identity
            arr = np.full(n, float(arr))
        if self.shape == "diag" and arr.ndim == 2 and arr.shape[0] == arr.shape[1]:
            off = np.where(np.eye(arr.shape[0], dtype=bool), 0.0, arr)
            if np.any(off != 0.0):
                i, j = np.argwhere(off != 0.0)[0]
                raise ParamError(self.name, f"must be diagonal, but element [{i}][{j}] is "
                                            f"{float(arr[i, j])!r}")
            arr = np.diagonal(arr).copy()
        if self.shape == "matrix" and arr.ndim == 1:
            arr = np.diag(arr)
        dims = 1 if self.shape == "diag" else 2
        m = arr.shape[0] if arr.ndim else 0
        if (arr.ndim != dims or m == 0 or (n is not None and m != n)
                or (dims == 2 and arr.shape[1] != m)):
            form = (f"a list of {expected} diagonal elements" if dims == 1
                    else f"a {n}x{n} matrix" if n is not None else "a square matrix")
            raise ParamError(self.name, f"must be {form}, got shape {given}")
        return arr

    def _check_elements(self, arr: np.ndarray, label: str) -> None:
        """Finite values and the bounds, element by element; the error names the first bad one."""
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            raise ParamError(self.name, f"{label} [{i}] must be finite, got {float(arr[i])!r}")
        for bound, op, ok in ((self.gt, ">", np.greater), (self.ge, ">=", np.greater_equal),
                              (self.le, "<=", np.less_equal)):
            if bound is None:
                continue
            limit = np.broadcast_to(np.asarray(bound, dtype=float), arr.shape)
            bad = ~ok(arr, limit)
            if bad.any():
                i = int(np.argmax(bad))
                raise ParamError(self.name, f"{label} [{i}] must be {op} {limit[i]:g}, "
                                            f"got {float(arr[i])!r}")


def _shape_text(arr: np.ndarray) -> str:
    return "scalar" if arr.ndim == 0 else "x".join(str(d) for d in arr.shape)


class Block:
    """Base class of everything the runtime steps.

    Parameters
    ----------
    name:
        Unique block name (for native filters, the name of its output channel).
    inputs, outputs:
        Channel names read and written.
    rate:
        ``"FAS"``, ``"MED"`` or ``"SLO"``.
    units:
        Optional unit per output channel, for outputs that are not DBC signals (a DBC
        signal's own unit wins).
    """

    kind: ClassVar[str] = "block"
    family: ClassVar[str] = "block"
    PARAMS: ClassVar[dict[str, Param]] = {}
    #: whether the block's DBC outputs go onto the bus (a disabled controller keeps off it)
    on_bus: bool = True
    #: an output without a DBC unit takes the unit of the block's single input (filters)
    keeps_input_unit: ClassVar[bool] = False
    #: parameters that are saved but not restored at start-up (a controller starts disabled)
    VOLATILE: ClassVar[tuple[str, ...]] = ()
    #: parameters that name an input channel -> the unit that channel must have (``""``: any);
    #: the runtime refuses a change naming a channel there is not (:mod:`cell.runtime.checks`)
    CHANNEL_PARAMS: ClassVar[dict[str, str]] = {}
    #: crank-angle sample streams (:mod:`cell.runtime.samples`) the block consumes sample by sample,
    #: besides its inputs read at ticks; empty for an ordinary block
    streams: tuple[str, ...] = ()

    def __init__(
        self,
        name: str,
        inputs: list[str],
        outputs: list[str],
        rate: str | tuple[str, ...] = "MED",
        *,
        units: Mapping[str, str] | None = None,
    ) -> None:
        rates = (rate,) if isinstance(rate, str) else tuple(rate)
        for r in rates:
            if r not in RATE_NAMES:
                raise ParamError("rate", f"must be one of {', '.join(RATE_NAMES)}, got {r!r}")
        if not rates:
            raise ParamError("rate", "a block needs at least one rate")
        self.name = name
        self.inputs = list(inputs)
        self.outputs = list(outputs)
        #: the tasks whose ticks step this block; a multi-rate block (a script whose
        #: statements run at different intervals) is stepped once per tick of any of them
        self.rates = rates
        #: output -> reason, for outputs the last step could not compute (returned as NaN)
        self.errors: dict[str, str] = {}
        #: output -> unit, for outputs without a DBC unit
        self.units: dict[str, str] = dict(units or {})

    @property
    def rate(self) -> str:
        return self.rates[0]

    # -- units ----------------------------------------------------------------------
    def sources_of(self, out: str) -> set[str] | None:
        """The input channels output ``out`` depends on, or ``None`` when the block cannot
        tell (a script follows its statements; :mod:`cell.runtime.units`)."""
        return None

    def statistic_unit(self, out: str, unit_of: Callable[[str], str]) -> str | None:
        """The unit of ``out`` when it is a statistic of one input (a running average's
        integral of ``mmH2O`` is ``mmH2O*s``), given ``unit_of(channel)``; else ``None``."""
        return None

    # -- parameters -----------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        """The tunable parameters in their JSON form (numbers and lists)."""
        return {p: spec.dump(getattr(self, p)) for p, spec in self.PARAMS.items()}

    def validate(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Check a parameter change as a whole; raise :class:`ParamError` on the first bad field."""
        if not isinstance(changes, dict):
            raise ParamError("body", f"must be an object of parameters, got {type(changes).__name__}")
        if not changes:
            raise ParamError("body", f"names no parameter; {self.kind} {self.name} takes: {self._known()}")
        checked = {}
        for key, value in changes.items():
            spec = self.PARAMS.get(key)
            if spec is None:
                raise ParamError(
                    key, f"is not a parameter of {self.kind} {self.name}; it takes: {self._known()}"
                )
            checked[key] = spec.check(value)
        return checked

    def set_params(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Validate then apply all changes at once; nothing changes if any field is bad."""
        checked = self.validate(changes)
        self._apply(checked)
        return self.params()

    def _apply(self, checked: dict[str, Any]) -> None:
        for key, value in checked.items():
            setattr(self, key, value)

    def safe_unsaved(self, changes: dict[str, Any]) -> bool:
        """Whether ``changes`` is a safety action that stays applied when it cannot be saved
        (a controller switched off); the default: no change is."""
        return False

    def _known(self) -> str:
        return ", ".join(self.PARAMS) or "nothing"

    # -- stepping --------------------------------------------------------------------
    def step(
        self, t: float, inputs: dict[str, float], ticking: frozenset[str] | None = None
    ) -> dict[str, float]:
        """Advance one tick at bus time ``t`` with the inputs' latest values.

        ``ticking`` names the tasks (``FAS``/``MED``/``SLO``) that tick at ``t``; a
        single-rate block can ignore it. Raise :class:`ArithmeticError` (or return a
        non-finite value) to mark the outputs invalid for this tick.
        """
        self.ticking = ticking if ticking is not None else frozenset(self.rates)
        return self._step(t, inputs)

    def _step(self, t: float, inputs: dict[str, float]) -> dict[str, float]:
        raise NotImplementedError

    def fallback(self, t: float, reason: str) -> dict[str, float] | None:
        """The outputs at a tick where an input is not ``ok`` (``reason`` says which and
        why), instead of a step: a controller holds its last output or goes to its safe
        output. ``None`` (the default) marks the outputs with the input's status."""
        return None

    # -- sample streams (blocks that declare :attr:`streams`) ---------------------------
    def samples(self, stream: str, index: int, values: np.ndarray, t: float) -> None:
        """Consume consecutive samples of ``stream``, in angle order, as their frame arrives.

        ``index`` is the first sample's angle index within the stream's period (0..119 for
        6 deg over 720 deg); ``values`` are that sample and the ones after it; ``t`` is the
        frame's bus time. The runtime calls this for every sample of every frame, between
        ticks, so the block sees the whole stream; it publishes at its ticks (:meth:`step`).
        Raise :class:`ArithmeticError` to have the frame counted as a block error.
        """
        self._samples(stream, index, values, t)

    def _samples(self, stream: str, index: int, values: np.ndarray, t: float) -> None:
        raise NotImplementedError(f"{self.kind} {self.name} declares streams but takes no samples")

    def gap(self, stream: str, lost: int, index: int, t: float) -> None:
        """Told that ``lost`` samples of ``stream`` never arrived; the next start at ``index``.

        A block skips ahead over a short gap or resets over a long one, and says which in
        its :meth:`state`. The default does nothing.
        """

    def state(self) -> dict[str, Any]:
        return {}

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "family": self.family,
            "rate": self.rate,
            "rates": list(self.rates),
            "inputs": self.inputs,
            "outputs": self.outputs,
            "params": self.params(),
            "state": self.state(),
        }
