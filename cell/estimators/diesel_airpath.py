"""The large diesel's air-path observers: the default EKF and the bias-augmented EKF (seed 002).

Both run the default model (:func:`~cell.plant.diesel_airpath.airpath_rhs` with the nominal
:class:`~cell.plant.diesel_airpath.AirPathParams`: not the engine's true, biased ones) on
the estimator platform (:class:`~cell.estimators.observer.ObserverBlock`), discretised by
Euler forward steps of 10 ms as seed 002, §2.2 does. At run time they measure ``P_IM`` and
``N_T``; ``P_EM`` is estimated, not measured (§6.2).

- ``airpath-default`` (seed 002's *default observer*): publishes ``DSL_P_IM_EST_DEFAULT``,
  ``DSL_P_EM_EST_DEFAULT``, ``N_T_EST_DEFAULT``;
- ``airpath-augmented`` (the *augmented observer*, eq. 3/4 with the designed
  :math:`\\hat A_q`): publishes ``DSL_P_IM_EST``, ``DSL_P_EM_EST``, ``N_T_EST`` and the bias
  states ``Q_BIAS_1 ...``.

:math:`\\hat A_q` comes from a design file written by ``testcell design bias LOG``
(:mod:`cell.design.diesel_airpath`). The runtime reads the file named by the setting
``bias_design`` (``TESTCELL_BIAS_DESIGN``); without one it uses the design shipped with the
cell, :data:`SHIPPED_DESIGN`, made by that command on a 300 s ``etc`` log (seed 0).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cell.core.errors import ConfigError
from cell.core.options import Option
from cell.core.registry import BlockSet
from cell.plant.diesel_airpath import (
    INPUTS,
    SIGNAL,
    STATES,
    UNITS,
    AirPathParams,
    airpath_jacobian,
    airpath_rhs,
)
from cell.estimators.augmentation import AugmentationError, augment, pbh_check
from cell.estimators.contract import DesignError
from cell.estimators.core import Model
from cell.estimators.observer import ObserverBlock

#: The design the runtime uses when no ``bias_design`` file is set.
SHIPPED_DESIGN = Path(__file__).with_name("data") / "diesel_airpath_design.json"
#: Model outputs, one per state (N_T in rpm, the state in krpm); their bus signals are
#: :data:`~cell.plant.diesel_airpath.SIGNAL`.
OUTPUTS = ("P_IM", "P_EM", "N_T")
#: The sensors the observers use at run time (§6.2: not P_EM).
RUNTIME_SENSORS = ("P_IM", "N_T")
#: Observer step (Euler), s.
STEP = 0.01
_SCALE = np.array([1.0, 1.0, 1000.0])
#: Sensor noise variances (P_IM kPa², P_EM kPa², N_T rpm²), a little above the plant's.
R_DIAG = {"P_IM": 0.8 ** 2, "P_EM": 4.0 ** 2, "N_T": 100.0 ** 2}
#: Process noise variance per tick of the model states (kPa², kPa², krpm²) and of a bias
#: state (slowly varying, §2: a random walk).
Q_STATES = (0.05, 0.5, 1e-4)
Q_BIAS = 1e-3
X0 = (101.3, 105.0, 5.0)

#: Plausible ranges of the observers' input channels (the contract refuses a tick outside
#: them): an absolute manifold pressure below 30 kPa is a sensor unplugged, not an engine
#: (an all-zero ``AIRPATH_SENS`` frame); back-pressures as the DBC declares them.
RANGES = {
    "FUEL_RATE": (0.0, 3000.0), "ENGINE_SPEED": (0.0, 8000.0), "VGT_POS": (0.0, 100.0),
    "EGR_POS": (0.0, 100.0), "EXH_BP_L": (-500.0, 20000.0), "EXH_BP_R": (-500.0, 20000.0),
    "DSL_P_IM": (30.0, 1300.0), "DSL_P_EM": (30.0, 1300.0), "N_T": (0.0, 65000.0),
}
#: Bounds of the model states (kPa, kPa, krpm) beyond which an estimate has diverged, and of
#: a bias state (the DBC range of ``Q_BIAS_n``).
STATE_BOUNDS = {"P_IM": (5.0, 1500.0), "P_EM": (5.0, 1500.0), "N_T": (-5.0, 100.0)}
BIAS_BOUND = (-1e4, 1e4)
#: The model's domain guard: pressures (kPa) below this floor and back-pressures
#: (mmH2O) outside the DBC range are clamped before the model sees them, so that no
#: negative base reaches a power or a root (``(p_es/p_em) ** k`` of a negative ratio is
#: complex) whatever the estimate does; the contract's state bounds then reset it.
P_FLOOR = 1.0
BP_RANGE = (-500.0, 20000.0)


def _h(t, x, u, p):
    return np.asarray(x[:3], dtype=float) * _SCALE


def _H(t, x, u, p):
    return np.diag(_SCALE)


class _CachedRhs:
    """:func:`airpath_rhs` and its Jacobian for one observer, with a one-entry cache.

    An EKF step evaluates the model at the same point three times: the prediction, the
    Jacobian pass of the same Euler step and the base point of the forward differences
    (:func:`airpath_jacobian`). The cache keeps that to one evaluation (four per step
    instead of six). One instance per model, so the observers of two threads never share it.
    """

    def __init__(self) -> None:
        self._key: tuple[bytes, bytes] | None = None
        self._value: np.ndarray | None = None

    def f(self, t, x, u, p) -> np.ndarray:
        key = (np.asarray(x, dtype=float).tobytes(), np.asarray(u, dtype=float).tobytes())
        if key != self._key:
            self._value = airpath_rhs(t, *guard_domain(x, u), p)
            self._key = key
        return self._value

    def jacobian(self, t, x, u, p) -> np.ndarray:
        """:func:`airpath_jacobian` (in the guarded domain) with its base point from the cache."""
        x, u = guard_domain(x, u)
        return airpath_jacobian(t, x, u, p, f0=self.f(t, x, u, p))


def guard_domain(x, u) -> tuple[np.ndarray, np.ndarray]:
    """The model's domain guard: ``x`` with its pressures at least :data:`P_FLOOR` and ``u``
    with its back-pressures within :data:`BP_RANGE` (copies only when something is clamped)."""
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    if x[0] < P_FLOOR or x[1] < P_FLOOR:
        x = x.copy()
        x[:2] = np.maximum(x[:2], P_FLOOR)
    lo, hi = BP_RANGE
    if not (lo <= u[4] <= hi and lo <= u[5] <= hi):
        u = u.copy()
        u[4:6] = np.clip(u[4:6], lo, hi)
    return x, u


#: Units of the model's outputs (the measurements it predicts): N_T in rpm, as the sensor
#: reads it, where its state is in krpm.
OUTPUT_UNITS = {"P_IM": "kPa", "P_EM": "kPa", "N_T": "rpm"}


def hat_units(prefix: str) -> dict[str, str]:
    """The units of an observer's predicted measurements ``{prefix}_{output}_HAT``."""
    return {f"{prefix}_{o}_HAT": OUTPUT_UNITS[o] for o in OUTPUTS}


def default_model(params: AirPathParams | None = None) -> Model:
    """Seed 002's default model (eq. 1) of the air path, on the estimator core."""
    rhs = _CachedRhs()
    return Model(STATES, INPUTS, OUTPUTS, rhs.f, _h, F=rhs.jacobian, H=_H,
                 params=params or AirPathParams(), dt=0.0, method="euler", max_step=STEP,
                 units={**UNITS, "N_T": "krpm"})


def runtime_C(sensors: Sequence[str] = RUNTIME_SENSORS) -> np.ndarray:
    """Rows of :math:`C = \\partial h/\\partial x` (states in model units) for ``sensors``."""
    C = np.eye(3)
    return C[[OUTPUTS.index(s) for s in sensors]]


def default_observer(name: str = "airpath-default", sensors: Sequence[str] = RUNTIME_SENSORS,
                     channels: dict[str, str] | None = None, rate: str = "FAS") -> ObserverBlock:
    """The default observer (EKF on the default model) measuring ``sensors``."""
    channels = channels if channels is not None else {s: f"{SIGNAL[s]}_EST_DEFAULT" for s in STATES}
    return ObserverBlock(name, default_model(), measurements={s: SIGNAL[s] for s in sensors},
                         Q=list(Q_STATES), R=[R_DIAG[s] for s in sensors], x0=list(X0),
                         P0=[100.0, 400.0, 100.0], rate=rate, channels=channels,
                         prefix="AIRPATH_DEF", units=hat_units("AIRPATH_DEF"),
                         **_contract(sensors, ()))


def _contract(sensors: Sequence[str], biases: Sequence[str]) -> dict:
    """The contract's settings of both observers: input ranges, state bounds, sigma bands."""
    ins = [*INPUTS, *(SIGNAL[s] for s in sensors)]
    return {"ranges": {ch: RANGES[ch] for ch in ins if ch in RANGES},
            "state_bounds": STATE_BOUNDS | {b: BIAS_BOUND for b in biases}, "sd": STATES}


#: The augmented observer's block name: the ``observer`` its design files name.
AUGMENTED_NAME = "airpath-augmented"


def _check_Aq(value: Any, source: str) -> np.ndarray:
    try:
        Aq = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: field 'Aq' (a 3 x n_q list of numbers) is missing or not "
                          "numeric") from None
    if Aq.ndim != 2 or Aq.shape[0] != 3 or Aq.shape[1] < 1 or not np.isfinite(Aq).all():
        raise ConfigError(f"{source}: 'Aq' must be 3 x n_q (n_q >= 1) finite numbers, "
                          f"got shape {Aq.shape}")
    return Aq


class AugmentedObserver(ObserverBlock):
    r"""Seed 002's augmented observer (eq. 3/4) with :math:`\hat A_q` = ``Aq``, on the contract.

    Its design (``design()``, ``load_design``, files of ``testcell design bias``) holds
    ``Aq`` besides the tunable parameters. A design loaded live must keep dim q (the bias
    states are channels); one that fails the PBH test with the run-time sensors is refused.
    """

    def __init__(self, Aq: np.ndarray, name: str = AUGMENTED_NAME,
                 sensors: Sequence[str] = RUNTIME_SENSORS, rate: str = "FAS",
                 channels: dict[str, str] | None = None) -> None:
        Aq = np.asarray(Aq, dtype=float).reshape(3, -1)
        pbh_check(runtime_C(sensors), Aq, STATES, sensors)
        nq = Aq.shape[1]
        if channels is None:
            channels = {s: f"{SIGNAL[s]}_EST" for s in STATES} | {
                f"Q_BIAS_{i + 1}": f"Q_BIAS_{i + 1}" for i in range(nq)}
        self.Aq = Aq
        self._sensors = tuple(sensors)
        super().__init__(name, augment(default_model(), Aq),
                         measurements={s: SIGNAL[s] for s in sensors},
                         Q=[*Q_STATES, *[Q_BIAS] * nq], R=[R_DIAG[s] for s in sensors],
                         x0=[*X0, *[0.0] * nq], P0=[100.0, 400.0, 100.0, *[100.0] * nq],
                         rate=rate, channels=channels, prefix="AIRPATH_AUG",
                         units={**hat_units("AIRPATH_AUG"),
                                **{f"Q_BIAS_{i + 1}": "" for i in range(nq)}},
                         **_contract(sensors, [f"Q_BIAS_{i + 1}" for i in range(nq)]))

    def _design_payload(self) -> dict[str, Any]:
        return {"Aq": self.Aq.tolist()}

    def _check_design(self, design: Any) -> Any:
        if "Aq" not in design:
            return None
        Aq = _check_Aq(design["Aq"], "Aq")
        if Aq.shape != self.Aq.shape:
            raise DesignError(f"Aq: {Aq.shape[0]} x {Aq.shape[1]} but the running observer has "
                              f"dim q = {self.Aq.shape[1]} (its bias channels); start the cell with "
                              "--bias-design FILE for another dim q")
        try:
            pbh_check(runtime_C(self._sensors), Aq, STATES, self._sensors)
        except AugmentationError as exc:
            raise DesignError(f"Aq: {exc}") from None
        return Aq

    def _use_design(self, checked: Any) -> None:
        if checked is not None:
            self.Aq = checked
            self.model = augment(default_model(), checked)


def augmented_observer(Aq: np.ndarray, name: str = AUGMENTED_NAME,
                       sensors: Sequence[str] = RUNTIME_SENSORS, rate: str = "FAS",
                       channels: dict[str, str] | None = None) -> AugmentedObserver:
    r"""The augmented observer (seed 002, eq. 3/4) with :math:`\hat A_q` = ``Aq``.

    Refused (:class:`~cell.estimators.augmentation.AugmentationError`) when ``Aq`` fails the PBH
    test (Theorem 2) with the run-time sensors.
    """
    return AugmentedObserver(Aq, name, sensors, rate, channels)


def load_design(path: str | Path) -> np.ndarray:
    r""":math:`\hat A_q` from a design file of ``testcell design bias``; refuses a bad file,
    or one that names another observer than ``airpath-augmented``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"bias design {path}: no such file (write one with `testcell design "
                          "bias LOG --out FILE`)") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"bias design {path}: not a readable JSON file: {exc}") from None
    if not isinstance(data, dict) or "Aq" not in data:
        raise ConfigError(f"bias design {path}: field 'Aq' (a 3 x n_q list of numbers) is "
                          "missing or not numeric")
    if data.get("observer", AUGMENTED_NAME) != AUGMENTED_NAME:
        raise DesignError(f"bias design {path}: names observer {data['observer']!r}, not "
                          f"{AUGMENTED_NAME!r}")
    return _check_Aq(data["Aq"], f"bias design {path}")


def airpath_observers(design: str | Path | None = None) -> list[ObserverBlock]:
    """The block set of ``large-diesel``: the default and the augmented observer side by side."""
    path = Path(design) if design else SHIPPED_DESIGN
    Aq = load_design(path)
    try:
        aug = augmented_observer(Aq)
    except AugmentationError as exc:
        raise ConfigError(f"bias design {path}: {exc}") from None
    return [default_observer(), aug]


#: seed 002: the default and the bias-augmented air-path observers of large-diesel side by
#: side, with their own option ``--bias-design`` (``TESTCELL_BIAS_DESIGN``).
DIESEL_AIRPATH_BLOCKS = BlockSet(
    "seed002-airpath", lambda run: airpath_observers(run.blocks.get("bias_design")),
    engines=("large-diesel",),
    options=(Option("bias_design", "--bias-design", Path, metavar="FILE",
                    help="design file of the augmented diesel air-path observer (testcell design "
                         "bias; default: the design shipped with the cell)"),))
