"""The Python API in the style of scikit-learn and PySINDy: data in, fit, predict, score, simulate, save.

    from identification.quad_model import QuadrotorModel, load_flight, flight_from_arrays
    data = load_flight("flight.ulg")                  # airborne rows of one or more logs (a Dataset)
    model = QuadrotorModel(budget=20, seed=0).fit(data)
    model.predict(data)                               # (N,6): ax ay az (NED m/s^2), dwx dwy dwz (FRD rad/s^2)
    model.score(data)                                 # mean R^2 over the targets; scores(data) per target
    model.simulate(x0, inputs, dt=0.004)              # (N+1,12) states from x0 under rotor speeds (N,4)
    model.save("model.yaml"); QuadrotorModel.load("model.yaml")

States xi (12): x y z (NED m), vx vy vz (NED m/s), phi theta psi (ZYX rad), wx wy wz (FRD rad/s); inputs u
(4): rotor speeds rad/s (or, for logs without rotor speeds, the motor model's equivalent speeds:
identification.motor_model; the fitted curve is saved with the model and applied to new data).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from bridge.errors import UserError
from bridge.integration import rk4_step
from identification.dataset import load_datasets
from identification.kinematics import euler_rates
from identification.metrics import r2
from identification.model_file import Model, load_model, save_model
from identification.motor_model import ThrustCurve, apply_thrust_curve, choose_motor_model, curve_from_dict
from identification.table import INPUT_NAMES, STATE_NAMES, TARGET_NAMES, Dataset
from identification.targets import stream_derivative


def load_flight(paths: str | Path | Sequence[str | Path], windows=None, **options: Any) -> Dataset:
    """The airborne rows (or the windows, log seconds) of one or more logs as one Dataset."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    return load_datasets(list(paths), windows=windows, **options)


def flight_from_arrays(
    t: np.ndarray, xi: np.ndarray, u: np.ndarray, targets: np.ndarray | None = None, source: str = "arrays"
) -> Dataset:
    """A Dataset from arrays: t (N,) s, xi (N,12), u (N,4) rad/s, targets (N,6) or None (differentiated)."""
    t = np.asarray(t, dtype=float)
    xi = np.asarray(xi, dtype=float)
    u = np.asarray(u, dtype=float)
    n = len(t)
    if xi.shape != (n, 12) or u.shape != (n, 4):
        raise UserError(f"flight_from_arrays: xi must be ({n}, 12) and u ({n}, 4); got {xi.shape}, {u.shape}")
    if targets is None:
        targets = np.column_stack((stream_derivative(t, xi[:, 3:6]), stream_derivative(t, xi[:, 9:12])))
    targets = np.asarray(targets, dtype=float)
    if targets.shape != (n, 6):
        raise UserError(f"flight_from_arrays: targets must be ({n}, 6); got {targets.shape}")
    ok = np.isfinite(targets).all(axis=1)
    ds = Dataset(t=t, xi=xi, u=u, targets=targets, source=source, format="arrays", target_source="truth")
    return ds.select(ok)


class QuadrotorModel:
    """Learned equations of motion of a quadrotor (symbolic regression), fit/predict/score/simulate/save."""

    def __init__(
        self,
        engine: str = "default",
        budget: int = 60,
        seed: int = 0,
        holdout: float = 0.2,
        validate_fraction: float = 0.2,
        loss: str = "absolute",
        targets: Sequence[str] = TARGET_NAMES,
    ):
        self.engine = engine
        self.budget = budget  # genetic-programming generations per target (an iteration budget)
        self.seed = seed
        self.holdout = holdout  # fraction of each flight's time that picks among the candidates
        self.validate_fraction = validate_fraction  # fraction kept for validation only
        self.loss = loss
        self.targets = tuple(targets)
        self.model_: Model | None = None
        self.motor_: ThrustCurve | None = None
        self.motor_note_ = ""
        self.roles_ = None
        self._fns: dict[str, Any] = {}

    # -- learning ------------------------------------------------------------------------------------
    def fit(self, data: Dataset) -> QuadrotorModel:
        """Learn each target's expression from a Dataset (fit | pick | validate time blocks per flight)."""
        from identification.data_roles import assign_roles
        from identification.identify import identify

        roles = assign_roles(data, pick_fraction=self.holdout, validate_fraction=self.validate_fraction)
        self.roles_ = roles  # the fit / pick / validate rows the model file records (data_roles)
        fit_rows = roles.fit
        self.motor_, self.motor_note_ = choose_motor_model(fit_rows)
        if self.motor_ is not None:
            data = apply_thrust_curve(data, self.motor_)
        self.model_ = identify(
            data,
            engine=self.engine,
            targets=self.targets,
            budget=self.budget,
            seed=self.seed,
            pick_fraction=self.holdout,
            validate_fraction=self.validate_fraction,
            loss=self.loss,
            progress=False,
        )
        if self.motor_ is not None:
            self.model_.engine["motor_model"] = self.motor_.as_dict()
        self._fns = {}
        return self

    def _require(self) -> Model:
        if self.model_ is None:
            raise UserError(
                "this QuadrotorModel is not fitted", hint="call fit(data) or QuadrotorModel.load(path)"
            )
        return self.model_

    @property
    def target_names(self) -> tuple[str, ...]:
        """The targets the fitted model has expressions for, in the canonical order."""
        return self._require().target_names

    @property
    def equations(self) -> dict[str, sympy.Expr]:
        """Target name -> sympy expression of the states and rotor speeds."""
        return self._require().expressions

    def _inputs(self, data: Dataset) -> np.ndarray:
        """The dataset's u, through the model's motor curve when the log has only motor commands."""
        if data.u_from_throttle or (self.motor_ is not None and "throttle" in data.aux):
            curve = self.motor_ or curve_from_dict(self._require().engine.get("motor_model"), "model")
            return apply_thrust_curve(data, curve).u
        return data.u

    # -- evaluation ----------------------------------------------------------------------------------
    def predict(self, data: Dataset | np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """Accelerations (N, n_targets) of a Dataset, or of states xi (N,12) and rotor speeds u (N,4)."""
        model = self._require()
        if isinstance(data, Dataset):
            xi, u = data.xi, self._inputs(data)
        else:
            if u is None:
                raise UserError("predict(xi, u): give the rotor speeds u (N,4) rad/s with the states")
            xi = np.atleast_2d(np.asarray(data, dtype=float))
            u = np.atleast_2d(np.asarray(u, dtype=float))
        args = [*xi.T, *u.T]
        out = []
        for name in model.target_names:
            if name not in self._fns:
                symbols = [model.symbols[n] for n in (*STATE_NAMES, *INPUT_NAMES)]
                self._fns[name] = sympy.lambdify(symbols, model.expressions[name], "numpy")
            out.append(np.broadcast_to(np.asarray(self._fns[name](*args), dtype=float), (len(xi),)))
        return np.column_stack(out)

    def scores(self, data: Dataset) -> dict[str, float]:
        """R^2 per target on a Dataset."""
        model = self._require()
        pred = self.predict(data)
        return {
            name: r2(data.targets[:, TARGET_NAMES.index(name)], pred[:, i])
            for i, name in enumerate(model.target_names)
        }

    def score(self, data: Dataset) -> float:
        """Mean R^2 over the model's targets on a Dataset (scikit-learn's convention: higher is better)."""
        return float(np.mean(list(self.scores(data).values())))

    def simulate(self, x0: np.ndarray, inputs: np.ndarray, dt: float) -> np.ndarray:
        """States (N+1,12) from x0 (12,) under rotor speeds inputs (N,4) rad/s held for dt s each (RK4)."""
        model = self._require()
        if set(model.target_names) != set(TARGET_NAMES):
            raise UserError("simulate needs all six targets; fit without restricting targets")
        x = np.asarray(x0, dtype=float).reshape(12)
        inputs = np.atleast_2d(np.asarray(inputs, dtype=float))
        if inputs.shape[1] != 4 or not dt > 0:
            raise UserError(f"simulate: inputs must be (N,4) rad/s and dt > 0 s; got {inputs.shape}, dt {dt}")

        def deriv(s, w) -> list[float]:
            s = np.asarray(s, dtype=float)
            acc = self.predict(s[None, :], np.asarray(w, dtype=float)[None, :])[0]
            d = np.empty(12)
            d[0:3] = s[3:6]
            d[3:6] = acc[0:3]
            d[6:9] = euler_rates(s[6], s[7], s[9:12])
            d[9:12] = acc[3:6]
            return d.tolist()

        out = np.empty((len(inputs) + 1, 12))
        out[0] = x
        state = x.tolist()
        for k, w in enumerate(inputs):
            state = rk4_step(deriv, state, w.tolist(), dt)  # the project's one integrator
            out[k + 1] = state
        return out

    @classmethod
    def from_model(cls, model: Model, motor: ThrustCurve | None = None) -> QuadrotorModel:
        """A fitted QuadrotorModel around an identified Model (and the motor curve of its inputs)."""
        obj = cls()
        obj.model_, obj.motor_, obj.targets = model, motor, model.target_names
        return obj

    # -- files ---------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the model file (quadsr-model/1, with the motor model when one was fitted)."""
        return save_model(self._require(), path)

    @classmethod
    def load(cls, path: str | Path) -> QuadrotorModel:
        """A fitted QuadrotorModel from a model file."""
        model = load_model(path)
        motor = model.engine.get("motor_model")
        return cls.from_model(model, curve_from_dict(motor, str(path)) if motor else None)
