"""Multiple linear regression on temperature rises: the papers' baseline model.

E = b0 + Σ_j b_j (T_j − T_j0): the same linear form the LVR model evaluates, fitted by
ordinary least squares (compd.identify.mlr). `RiseLinear` is the shared run-time form of both.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import Strict
from compd.models.base import (
    MAX_ERROR_UM,
    MAX_GAIN_UM_PER_K,
    MAX_RISE_K,
    TEMP_MAX_C,
    TEMP_MIN_C,
    LeadParams,
    Model,
    check_length,
    check_matrix,
)

GainUmPerK = Annotated[float, Field(ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K)]
ReadingC = Annotated[float, Field(ge=TEMP_MIN_C, le=TEMP_MAX_C)]
RiseK = Annotated[float, Field(ge=-MAX_RISE_K, le=MAX_RISE_K)]
RiseK2 = Annotated[float, Field(ge=-(MAX_RISE_K**2), le=MAX_RISE_K**2)]


class RiseLinearParams(LeadParams):
    """A linear model on temperature rises: coefficients per input (rows) and axis (columns)."""

    coef_um_per_k: list[list[GainUmPerK]] = Field(
        description=f"p × q: µm of error per K of rise (|b| ≤ {MAX_GAIN_UM_PER_K:g}: α ≤ 1e-3/K over ≤ 10 m)"
    )
    intercept_um: list[Annotated[float, Field(ge=-MAX_ERROR_UM, le=MAX_ERROR_UM)]] = Field(
        description="q: error at zero rise, µm"
    )
    t0_c: list[ReadingC] | None = Field(
        None, description="reference readings T_j0 (−40..150 °C); none = the readings at start"
    )
    rise_mean_k: list[RiseK] | None = Field(
        None, description="mean rise of each input over the fit data (degraded mode), |·| ≤ 200 K"
    )
    rise_cov_k2: list[list[RiseK2]] | None = Field(
        None, description="p × p covariance of the rises over the fit data (degraded mode), variances ≥ 0"
    )
    degraded_max_sigma_um: float = Field(
        2.0, gt=0, le=MAX_ERROR_UM, description="largest added prediction σ an axis accepts when inputs are bad"
    )

    @model_validator(mode="after")
    def _variances(self) -> RiseLinearParams:
        for i, row in enumerate(self.rise_cov_k2 or []):
            if i < len(row) and row[i] < 0:
                raise ValueError(f"rise_cov_k2[{i}][{i}] is a variance: it must be ≥ 0, got {row[i]}")
        return self


class RiseLinear(Model):
    """Run-time form shared by mlr and lvr: out = b0 + (x − x0) B, allocation-free."""

    Params: ClassVar[type[Strict]] = RiseLinearParams  # LVR's adds a field: its own Params
    params: RiseLinearParams

    def __init__(self, params: RiseLinearParams, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self.B = np.ascontiguousarray(params.coef_um_per_k, dtype=float)
        self.b0 = np.asarray(params.intercept_um, dtype=float)
        self.x0 = np.asarray(params.t0_c, dtype=float) if params.t0_c is not None else None
        self._rise = np.zeros(len(inputs))
        self._deg_key = b""
        self.degraded_sigma_um = np.zeros(len(outputs))

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        p, q = len(inputs), len(outputs)
        check_matrix(params.coef_um_per_k, p, q, "coef_um_per_k", "input", "output")
        check_length(params.intercept_um, q, "intercept_um", "output")
        if params.t0_c is not None:
            check_length(params.t0_c, p, "t0_c", "input")
        if params.rise_mean_k is not None:
            check_length(params.rise_mean_k, p, "rise_mean_k", "input")
        if params.rise_cov_k2 is not None:
            check_matrix(params.rise_cov_k2, p, p, "rise_cov_k2", "input", "input")

    @property
    def supports_degraded(self) -> bool:
        return self.params.rise_mean_k is not None and self.params.rise_cov_k2 is not None

    def _degraded_form(self, good: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coefficients for the good inputs alone, and the σ they add per axis.

        The rises r_m of the bad inputs are replaced by their conditional expectation
        given the good ones under the fit data's Gaussian statistics,
        r_m ≈ μ_m + Σ_mo Σ_oo⁻¹ (r_o − μ_o), so
        E = b0 + B_m'(μ_m − K μ_o) + (B_o' + B_m' K) r_o with K = Σ_mo Σ_oo⁻¹, and the
        prediction loses σ² = diag(B_m' (Σ_mm − K Σ_om) B_m) per axis.
        """
        mu = np.asarray(self.params.rise_mean_k, dtype=float)
        cov = np.asarray(self.params.rise_cov_k2, dtype=float)
        o, m = np.flatnonzero(good), np.flatnonzero(~good)
        B = self.B
        q = B.shape[1]
        if o.size == 0:
            return np.zeros_like(B), self.b0 + mu @ B, np.full(q, np.inf)
        S_oo = cov[np.ix_(o, o)] + 1e-9 * np.eye(o.size)
        K = np.linalg.solve(S_oo, cov[np.ix_(o, m)]).T  # |m| × |o|
        B_eff = np.zeros_like(B)
        B_eff[o] = B[o] + K.T @ B[m]
        b_eff = self.b0 + (mu[m] - K @ mu[o]) @ B[m]
        cond = cov[np.ix_(m, m)] - K @ cov[np.ix_(o, m)]
        sigma = np.sqrt(np.maximum(np.einsum("iq,ij,jq->q", B[m], cond, B[m]), 0.0))
        return B_eff, b_eff, sigma

    def evaluate_degraded(self, x: np.ndarray, good: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """Predict from the good inputs only; NaN for an axis whose added σ is too large.

        The degraded form is computed when the set of bad inputs changes (rare),
        then evaluated like the normal one.
        """
        key = good.tobytes()
        if key != self._deg_key:
            self._deg_key = key
            self._deg_B, self._deg_b0, self.degraded_sigma_um = self._degraded_form(good.copy())
            self._deg_bad = ~good.copy()
        assert self.x0 is not None  # `start` latched it
        np.subtract(x, self.x0, out=self._rise)
        np.copyto(self._rise, 0.0, where=self._deg_bad)
        np.dot(self._rise, self._deg_B, out=out)
        out += self._deg_b0
        np.copyto(out, np.nan, where=self.degraded_sigma_um > self.params.degraded_max_sigma_um)

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self.x0 is None:
            self.x0 = np.array(x, dtype=float)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        assert self.x0 is not None  # `start` latched it
        np.subtract(x, self.x0, out=self._rise)
        np.dot(self._rise, self.B, out=out)
        out += self.b0

    def predict_rows(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
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


class MLR(RiseLinear):
    """Multiple linear regression on temperature rises (the papers' comparison model)."""

    kind = "mlr"
    summary_keys = ("coef_um_per_k", "intercept_um")
    per_axis_keys = ("intercept_um",)
