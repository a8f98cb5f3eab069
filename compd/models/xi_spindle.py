"""ξ-point spindle model, axial (paper 003, SPEC §3.3): ΔL = α L [T(ξ) − T0]."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from compd.config import Strict
from compd.errors import BadInput
from compd.models.base import Model


def axial_growth_um(t_xi_c: float | np.ndarray, t0_c: float, alpha_per_k: float, length_mm: float):
    """Axial growth ΔL = α L (T(ξ) − T0) in µm (paper 003, eq. 2; L in mm → ×1000)."""
    return alpha_per_k * length_mm * 1000.0 * (np.asarray(t_xi_c) - t0_c)


def find_xi(x_mm: np.ndarray, t_c: np.ndarray) -> float:
    """The mean-value point ξ of a profile T(x): where T equals its length average.

    The mean uses the trapezoid rule; among crossings the one nearest the middle of
    the profile's warmest half is not guessed: the first crossing from the warm end
    (x = x[0] being the heated end in paper 003's convention, nose at 0) is returned,
    linearly interpolated. Raises BadInput if the profile is constant or unsorted.
    """
    x = np.asarray(x_mm, dtype=float)
    t = np.asarray(t_c, dtype=float)
    if x.ndim != 1 or x.shape != t.shape or x.size < 2:
        raise BadInput("a profile needs at least two (x, T) points of equal count")
    if np.any(np.diff(x) <= 0):
        raise BadInput("profile positions must be strictly increasing")
    if not np.all(np.isfinite(t)):
        raise BadInput("profile temperatures must be finite")
    mean = np.trapezoid(t, x) / (x[-1] - x[0])
    d = t - mean
    if np.allclose(d, 0.0):
        raise BadInput("the profile is constant: every point is a mean-value point")
    for i in range(x.size - 1):
        if d[i] == 0.0:
            return float(x[i])
        if d[i] * d[i + 1] < 0:
            return float(x[i] - d[i] * (x[i + 1] - x[i]) / (d[i + 1] - d[i]))
    return float(x[-1])


class XiSpindleParams(Strict):
    """Parameters of the axial ξ-point model."""

    alpha_per_k: float = Field(gt=0, lt=1e-3, description="linear expansion coefficient, 1/K")
    length_mm: float = Field(gt=0, description="spindle length L over which ξ averages")
    t0_c: float | None = Field(
        None, ge=-40, le=150, description="reference temperature; none = first reading at start"
    )
    xi_mm: float | None = Field(None, ge=0, description="where the sensor sits (documentation)")


class XiSpindle(Model):
    """Axial ξ-point model: one input (the sensor at ξ), one output axis."""

    kind = "xi_spindle"
    Params = XiSpindleParams

    def __init__(self, params: XiSpindleParams, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self._gain_um_per_k = params.alpha_per_k * params.length_mm * 1000.0
        self.t0_c: float | None = params.t0_c

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        if len(inputs) != 1:
            raise BadInput(f"xi_spindle takes one input (the ξ sensor), got {len(inputs)}")
        if len(outputs) != 1:
            raise BadInput(f"xi_spindle has one output axis, got {len(outputs)}")

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self.t0_c is None:
            self.t0_c = float(x[0])

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        out[0] = self._gain_um_per_k * (x[0] - self.t0_c)

    def get_state(self) -> dict[str, Any]:
        return {"t0_c": self.t0_c}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        if self.params.t0_c is None and state.get("t0_c") is not None:
            self.t0_c = float(state["t0_c"])
