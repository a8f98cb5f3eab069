"""Multiple linear regression on temperature rises: the papers' baseline model (SPEC §3.5).

E = b0 + Σ_j b_j (T_j − T_j0): the same linear form the LVR model evaluates, fitted by
ordinary least squares. `RiseLinear` is the shared run-time form of both.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from compd.config import Strict
from compd.errors import BadInput
from compd.log import Log
from compd.models.base import FitResult, Model
from compd.models.fitdata import (
    axis_names,
    check_not_constant,
    columns,
    default_inputs,
    default_targets,
    require_rows,
)


class RiseLinearParams(Strict):
    """A linear model on temperature rises: coefficients per input (rows) and axis (columns)."""

    coef_um_per_k: list[list[float]] = Field(description="p × q: µm of error per K of rise")
    intercept_um: list[float] = Field(description="q: error at zero rise, µm")
    t0_c: list[float] | None = Field(
        None, description="reference readings T_j0; none = the readings at start"
    )


class RiseLinear(Model):
    """Run-time form shared by mlr and lvr: out = b0 + (x − x0) B, allocation-free."""

    Params = RiseLinearParams

    def __init__(self, params: RiseLinearParams, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self.B = np.ascontiguousarray(params.coef_um_per_k, dtype=float)
        self.b0 = np.asarray(params.intercept_um, dtype=float)
        self.x0 = np.asarray(params.t0_c, dtype=float) if params.t0_c is not None else None
        self._rise = np.zeros(len(inputs))

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        B = params.coef_um_per_k
        if len(B) != len(inputs) or any(len(row) != len(outputs) for row in B):
            raise BadInput(
                f"coef_um_per_k must be {len(inputs)} rows (inputs) × {len(outputs)} columns (outputs)"
            )
        if len(params.intercept_um) != len(outputs):
            raise BadInput(f"intercept_um needs one value per output ({len(outputs)})")
        if params.t0_c is not None and len(params.t0_c) != len(inputs):
            raise BadInput(f"t0_c needs one value per input ({len(inputs)})")

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self.x0 is None:
            self.x0 = np.array(x, dtype=float)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        np.subtract(x, self.x0, out=self._rise)
        np.dot(self._rise, self.B, out=out)
        out += self.b0

    def predict(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        if X.shape[0] == 0:
            return np.zeros((0, len(self.outputs)))
        if self.x0 is None:
            self.start(X[0], float(t_s[0]))
        return (X - self.x0) @ self.B + self.b0

    def get_state(self) -> dict[str, Any]:
        return {"t0_c": None if self.x0 is None else [float(v) for v in self.x0]}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        if self.params.t0_c is None and state.get("t0_c") is not None:
            x0 = np.asarray(state["t0_c"], dtype=float)
            if x0.shape == (len(self.inputs),):
                self.x0 = x0


def rises(X: np.ndarray) -> np.ndarray:
    """Temperature rises: each row minus the first row (the reading at start)."""
    return X - X[0]


def linear_data(
    log: Log, inputs: list[str] | None, targets: list[str] | None
) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """Inputs, targets, X (raw readings) and Y for a rise model; NaN and constant inputs refused."""
    inputs = default_inputs(log, inputs)
    targets = default_targets(log, targets)
    X = columns(log, inputs)
    Y = columns(log, targets)
    check_not_constant(log, X, inputs)
    return inputs, targets, X, Y


class MLRFitOptions(Strict):
    """`compd fit --kind mlr` takes no options beyond inputs and targets."""


class MLR(RiseLinear):
    """Multiple linear regression on temperature rises (SPEC §3.5)."""

    kind = "mlr"
    FitOptions = MLRFitOptions

    @classmethod
    def fit(cls, log: Log, inputs=None, targets=None, **options: Any) -> FitResult:
        """Ordinary least squares of E on [1, T − T(first row)]."""
        cls.fit_options(options)
        inputs, targets, X, Y = linear_data(log, inputs, targets)
        require_rows(log, X.shape[0], len(inputs) + 2, f"mlr with {len(inputs)} inputs")
        model = fit_mlr_model(inputs, axis_names(targets), X, Y)
        return FitResult(model, {"rank": int(np.linalg.matrix_rank(rises(X)))})


def fit_mlr_model(inputs: list[str], axes: list[str], X: np.ndarray, Y: np.ndarray) -> MLR:
    """The MLR model of Y on the rises of X (used as the baseline by every report)."""
    R = rises(X)
    A = np.hstack([np.ones((R.shape[0], 1)), R])
    sol, *_ = np.linalg.lstsq(A, Y, rcond=None)
    params = RiseLinearParams(
        coef_um_per_k=sol[1:].tolist(), intercept_um=sol[0].tolist(), t0_c=None
    )
    return MLR(params, inputs, axes)
