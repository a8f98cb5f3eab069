"""AR(1) spindle elongation model with speed-dependent C2, bed term and ambient input (paper 001).

Every Δτ the spindle growth steps as S(k) = C1 S(k−1) + C2(n_k) + C3 ΔT_amb(k) (eq. 12 of
paper 001 with the ambient as exogenous input; C3 = 0 is the paper), plus Σ_x C_x ΔT_x(k)
for the temperatures the spindle exchanges heat with besides the air (compd's form: the
housing its bearings sit in, `exchange_um_per_k`; the rod model with a boundary that warms), starting as eq. 17 does
from S(0) = 0 at the first step after a cold start (`recursion_start: zero`); model files
written before that rule have no `recursion_start` and keep theirs, S(0) = C2(n_0) (`c2`,
see `AR1Params.upgrade`). The error is
E(k) = Σ_j g_j ΔT_j(k) + s·S(k): for the paper's lathe Z axis the bed sensors enter
with g = α_bed L_bed and the spindle with s = −1 (error = bed growth − spindle growth).
C2(n) is piecewise linear in the spindle speed n between the fitted levels; outside them,
compd's fits write the power law C2(level)·(n/level)^e (`c2_exponent`, 1 by default:
proportional), files before it the line through (0, 0) below and the last level held
above. The state S is the model's memory.

compd's speed-dependent form (`c1_table`): C1 = e^(−b Δτ) with b = 2h/(ρcR), and a turning
spindle's convection h grows with its speed, so b is fitted at standstill and at each
logged speed and interpolated linearly in n between them (held past the last);
an empty table is the paper's single C1. For a log that runs at many speeds (a spectrum)
compd fits both coefficients as smooth functions of the speed instead (`speed_law`):
b(n) = b(0) + k (|n|/n_ref)^p, so C1(n) = C1(0)·e^(−Δτ k (|n|/n_ref)^p), and C2(n) =
a·|n|/n_ref + q·(|n|/n_ref)² (a, q ≥ 0: the heat input grows with speed, the bearings'
faster). The fit is compd.identify.ar1.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.models.base import (
    MAX_ERROR_UM,
    MAX_GAIN_UM_PER_K,
    MAX_SPEED_RPM,
    TEMP_MAX_C,
    TEMP_MIN_C,
    LeadParams,
    Model,
    check_length,
    step_rows,
)


def coefficients_from_physics(
    h: float, lam: float, rho: float, c: float, radius_m: float, alpha: float, q: float, dt_s: float
) -> tuple[float, float]:
    """(C1, C2 in µm) of the rod model (paper 001, eqs. 6–9).

    b = 2h/(ρ c R) [1/s], a = λ/(ρ c) [m²/s], C1 = e^(−b Δτ),
    C2 = q α a / (λ b) · (1 − e^(−b Δτ)) [m] × 1e6. h in W/(m² K), λ in W/(m K),
    ρ in kg/m³, c in J/(kg K), q the heat flux into the rod end in W/m².
    """
    b = 2.0 * h / (rho * c * radius_m)
    a = lam / (rho * c)
    c1 = math.exp(-b * dt_s)
    c2_m = q * alpha * a / (lam * b) * (1.0 - c1)
    return c1, c2_m * 1e6


SpeedRpm = Annotated[float, Field(gt=0, le=MAX_SPEED_RPM)]


class SpeedLaw(Strict):
    """C1 and C2 as smooth functions of the speed n (compd's form for a log at many speeds), x = |n|/ref_rpm:
    C1(n) = c1·e^(−Δτ·rate_per_s·x^rate_exponent), C2(n) = c2_um·x + c2_quad_um·x²."""

    ref_rpm: SpeedRpm = Field(description="the speed the law is stated at (the fastest fitted)")
    c2_um: float = Field(ge=0, le=MAX_ERROR_UM, description="C2's term linear in speed, µm per step at ref_rpm")
    c2_quad_um: float = Field(
        0.0,
        ge=0,
        le=MAX_ERROR_UM,
        description="C2's term in the speed squared, µm per step at ref_rpm (the bearings' friction heat grows"
        " faster than the speed)",
    )
    rate_per_s: float = Field(
        ge=0,
        le=1.0,
        description="k: how much faster the spindle cools at ref_rpm than at standstill, 1/s"
        " (1/τ(n) = −ln(c1)/Δτ + k x^p: the convection grows with speed)",
    )
    rate_exponent: float = Field(1.0, ge=0.25, le=4.0, description="p: the cooling's growth with speed")

    def c2_um_at(self, speed_rpm: float) -> float:
        """C2(n), µm per step."""
        x = abs(speed_rpm) / self.ref_rpm
        return self.c2_um * x + self.c2_quad_um * x * x

    def c1_at(self, c1_standstill: float, dt_s: float, speed_rpm: float) -> float:
        """C1(n) from C1 at standstill."""
        return c1_standstill * math.exp(-dt_s * self.rate_per_s * (abs(speed_rpm) / self.ref_rpm) ** self.rate_exponent)


class AR1Params(LeadParams):
    """AR(1) model params. Inputs: [speed, *bed sensors, ambient (when c3_um_per_k is set), *exchange sensors]."""

    dt_s: float = Field(gt=0, le=86400, description="Δτ, the model step (paper: 30–60 s), at most a day")
    c1: float = Field(gt=0, lt=1, description="C1 = e^(−b Δτ) (at standstill when c1_table is set)")
    c2_table: list[tuple[SpeedRpm, Annotated[float, Field(ge=0, le=MAX_ERROR_UM)]]] = Field(
        default_factory=list, description="(speed rpm, C2 µm ≥ 0) nodes; C2(0) = 0 is implied"
    )
    c2_exponent: float | None = Field(
        None,
        ge=0.5,
        le=3.0,
        description="C2 at speeds outside the table: C2(nearest node)·(n/node)^e (bearing friction heat ∝ n^e);"
        " none = linear from (0, 0) below the first node and constant past the last (files before the key)",
    )
    c3_um_per_k: float | None = Field(
        None,
        ge=-MAX_GAIN_UM_PER_K,
        le=MAX_GAIN_UM_PER_K,
        description="ambient gain C3 (µm per K of ambient rise per step); none = paper form",
    )
    c1_table: list[tuple[SpeedRpm, Annotated[float, Field(gt=0, lt=1)]]] = Field(
        default_factory=list,
        description="(speed rpm, C1) nodes above standstill, b = −ln C1 linear in speed between them and "
        "`c1` (standstill); empty = one C1 (the paper)",
    )
    bed_gain_um_per_k: list[Annotated[float, Field(ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K)]] = Field(
        default_factory=list, description="one gain per bed sensor (α_bed L_bed, µm/K)"
    )
    exchange_um_per_k: list[Annotated[float, Field(ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K)]] = Field(
        default_factory=list,
        description="one gain per exchange sensor (inputs after the ambient): the temperatures the spindle"
        " exchanges heat with (its housing), entering the recursion as C3 does, µm per K of rise per step",
    )
    spindle_sign: Literal[1, -1] = Field(1, description="+1: error = spindle growth; −1: bed − spindle")
    t0_c: list[Annotated[float, Field(ge=TEMP_MIN_C, le=TEMP_MAX_C)]] | None = Field(
        None, description="reference readings of bed and ambient inputs (−40..150 °C)"
    )
    speed_law: SpeedLaw | None = Field(
        None,
        description="C1 and C2 as smooth functions of the speed (compd's form for a log at many speeds; "
        "c2_table and c1_table then empty): C1(n) = c1·e^(−Δτ·rate_per_s·(|n|/ref_rpm)^rate_exponent), "
        "C2(n) = c2_um·|n|/ref_rpm + c2_quad_um·(|n|/ref_rpm)²; none = the tables",
    )
    recursion_start: Literal["zero", "c2"] = Field(
        "zero",
        description="first step after a cold start: `zero` S(0) = 0 (paper 001, eq. 17); `c2` S(0) = C2(n_0), "
        "the rule of model files written before this key (a file or config without the key gets `c2`)",
    )

    @classmethod
    def upgrade(cls, raw: Any) -> Any:
        """Params of a model file or config section as written: without `recursion_start` they
        predate it and were fitted (and are evaluated) with S(0) = C2(n_0), so they get `c2`."""
        if isinstance(raw, dict) and "recursion_start" not in raw:
            return {**raw, "recursion_start": "c2"}
        return raw

    @model_validator(mode="after")
    def _table(self) -> AR1Params:
        # speeds > 0, C2 ≥ 0 and C1 in (0, 1) are the fields' own bounds
        for key, table in (("c2_table", self.c2_table), ("c1_table", self.c1_table)):
            rpm = [n for n, _ in table]
            if any(b <= a for a, b in zip(rpm, rpm[1:], strict=False)):
                raise ValueError(f"{key} speeds must be positive and strictly increasing")
        if self.speed_law is not None and (self.c2_table or self.c1_table):
            raise ValueError("speed_law gives C1 and C2 at every speed: c2_table and c1_table must be empty")
        return self


def c2_of_speed(
    speed_rpm: float, rpm: list[float], c2: list[float], at_zero: float = 0.0, exponent: float | None = None
) -> float:
    """C2(n): linear between the table nodes; outside them linear through (0, at_zero) below the
    first and constant past the last, or with `exponent` e the power law C2(node)·(n/node)^e from
    the nearest node (the bearings' friction heat grows as n^(5/3), Palmgren's moment ∝ n^(2/3)
    times ω, and the rotor's convection with n as well: compd's fits write e = 1)."""
    n = abs(speed_rpm)
    if exponent is not None and rpm:
        if n <= rpm[0]:
            return c2[0] * (n / rpm[0]) ** exponent
        if n >= rpm[-1]:
            return c2[-1] * (n / rpm[-1]) ** exponent
    lo_n, lo_c = 0.0, at_zero
    for hi_n, hi_c in zip(rpm, c2, strict=True):
        if n <= hi_n:
            return lo_c + (hi_c - lo_c) * (n - lo_n) / (hi_n - lo_n)
        lo_n, lo_c = hi_n, hi_c
    return lo_c


def ar_filter(c1: float | np.ndarray, u: np.ndarray, s0: float = 0.0) -> np.ndarray:
    """s(k) = C1(k) s(k−1) + u(k) from s(−1) = s0, column-wise for a 2-D u; C1 a scalar or one per row.

    Step by step in the order the loop's `evaluate` rounds (C1 s, then + u); the fits
    (compd.identify.ar1) filter their design matrices with scipy's lfilter, which rounds alike.
    """
    c = np.broadcast_to(np.asarray(c1, dtype=float), u.shape[:1])
    s = np.empty_like(u, dtype=float)
    prev = np.full(u.shape[1:], s0, dtype=float)
    for k in range(u.shape[0]):
        prev = c[k] * prev + u[k]
        s[k] = prev
    return s


class AR1(Model):
    """AR(1) spindle growth stepped every Δτ, plus linear bed terms (paper 001)."""

    kind = "ar1"
    summary_keys = (
        "c1",
        "c2_table",
        "c3_um_per_k",
        "c1_table",
        "speed_law",
        "bed_gain_um_per_k",
        "exchange_um_per_k",
        "spindle_sign",
        "dt_s",
    )
    Params = AR1Params
    params: AR1Params

    def __init__(self, params: AR1Params, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self.update_period_s = params.dt_s
        self._rpm = [float(n) for n, _ in params.c2_table]
        self._c2 = [float(c) for _, c in params.c2_table]
        self._c2_exp = params.c2_exponent
        self._nb = len(params.bed_gain_um_per_k)
        self._gain = np.asarray(params.bed_gain_um_per_k, dtype=float)
        self._c3 = params.c3_um_per_k
        self._law = params.speed_law
        self._rpm1 = [float(n) for n, _ in params.c1_table]
        self._b1 = [-math.log(c) for _, c in params.c1_table]  # b Δτ at each node
        self._b0 = -math.log(params.c1)
        self._amb = 1 + self._nb if self._c3 is not None else -1
        # the exchange sensors: inputs ix … ix + nx − 1 (their references x0[ix − 1 …])
        self._ix = 1 + self._nb + (self._c3 is not None)
        self._xgain = [float(v) for v in params.exchange_um_per_k]
        self._xgain_arr = np.asarray(self._xgain, dtype=float)
        self._sign = float(params.spindle_sign)
        self.x0 = np.asarray(params.t0_c, dtype=float) if params.t0_c is not None else None
        self.s_um = 0.0
        # True until the first step after a cold start (no step taken, no state restored)
        self._fresh = params.recursion_start == "zero"
        self._rise = np.zeros(self._nb)

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        nx = len(params.exchange_um_per_k)
        need = 1 + len(params.bed_gain_um_per_k) + (params.c3_um_per_k is not None) + nx
        if len(inputs) != need:
            raise BadInput(
                f"ar1 takes {need} inputs (speed, {len(params.bed_gain_um_per_k)} bed sensors"
                f"{', ambient' if params.c3_um_per_k is not None else ''}"
                f"{f', {nx} exchange sensors' if nx else ''}), got {len(inputs)}",
                path=("inputs",),
            )
        if len(outputs) != 1:
            raise BadInput(f"ar1 has one output axis, got {len(outputs)}", path=("outputs",))
        if params.t0_c is not None:
            check_length(params.t0_c, len(inputs) - 1, "t0_c", "temperature input")

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self.x0 is None:
            self.x0 = np.array(x[1:], dtype=float)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """One Δτ step: S = C1 S + C2(n) + C3 ΔT_amb + Σ C_x ΔT_x (S(0) = 0 at a cold start);
        E = Σ g ΔT_bed + s S (µm)."""
        x0 = self.x0
        assert x0 is not None  # `start` latched it
        if self._fresh:
            self._fresh = False  # ΔL(0) = 0 (eq. 17): the first step adds nothing
        else:
            u = self._c2_at(x[0])
            if self._amb > 0:
                u += self._c3 * (x[self._amb] - x0[self._amb - 1])
            ix = self._ix
            for j, g in enumerate(self._xgain):
                u += g * (x[ix + j] - x0[ix - 1 + j])
            self.s_um = self.c1_at(x[0]) * self.s_um + u
        e = self._sign * self.s_um
        if self._nb:
            np.subtract(x[1 : 1 + self._nb], x0[: self._nb], out=self._rise)
            e += float(self._rise @ self._gain)
        out[0] = e

    def c1_at(self, speed_rpm: float) -> float:
        """C1 at this speed: `c1`, e^(−b Δτ) with b interpolated in speed (`c1_table`), or the speed law's."""
        if self._law is not None:
            return self._law.c1_at(self.params.c1, self.params.dt_s, speed_rpm)
        if not self._rpm1:
            return self.params.c1
        return math.exp(-c2_of_speed(speed_rpm, self._rpm1, self._b1, self._b0))

    def _c2_at(self, speed_rpm: float) -> float:
        """C2 at this speed (µm per step): the table's, or the speed law's."""
        if self._law is not None:
            return self._law.c2_um_at(speed_rpm)
        return c2_of_speed(speed_rpm, self._rpm, self._c2, 0.0, self._c2_exp)

    def predict_rows(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Vectorised batch prediction, stepping every Δτ and holding between steps."""
        n = X.shape[0]
        out = np.zeros((n, 1))
        if n == 0:
            return out
        self.start(X[0], float(t_s[0]))
        rows = step_rows(np.asarray(t_s, dtype=float), self.params.dt_s)
        e = self._response(X[rows], self._c1_rows(X[rows, 0]), s0=self.s_um)
        self.s_um = float(self._last_s)
        idx = np.searchsorted(rows, np.arange(n), side="right") - 1
        out[:, 0] = e[idx]
        return out

    def _c1_rows(self, speed_rpm: np.ndarray) -> float | np.ndarray:
        if not self._rpm1 and self._law is None:
            return self.params.c1
        return np.array([self.c1_at(v) for v in speed_rpm])

    def _response(self, Xs: np.ndarray, c1: float | np.ndarray, s0: float = 0.0) -> np.ndarray:
        x0 = self.x0
        assert x0 is not None  # `start` latched it
        u = np.array([self._c2_at(v) for v in Xs[:, 0]])
        if self._amb > 0:
            u += self._c3 * (Xs[:, self._amb] - x0[self._amb - 1])
        if self._xgain:
            ix = self._ix
            u += (Xs[:, ix:] - x0[ix - 1 :]) @ self._xgain_arr
        if self._fresh and u.size:
            # ΔL(0) = 0 (eq. 17): the first row keeps S; only a cold start has _fresh, so S = s0 = 0
            u[0] = 0.0
            c1 = np.r_[1.0, np.broadcast_to(np.asarray(c1, dtype=float), u.shape)[1:]]
            self._fresh = False
        s = ar_filter(c1, u, s0)
        self._last_s = s[-1]
        e = self._sign * s
        if self._nb:
            e = e + (Xs[:, 1 : 1 + self._nb] - x0[: self._nb]) @ self._gain
        return e

    def get_state(self) -> dict[str, Any]:
        return {
            "s_um": float(self.s_um),
            "t0_c": None if self.x0 is None else [float(v) for v in self.x0],
        }

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        """Restore S saved `elapsed_s` ago, cooled by its own time constant: S·C1^(elapsed/Δτ)."""
        s = float(state.get("s_um", 0.0))
        self._fresh = False  # restored memory: the next step is an ordinary one
        # while compd was down the speed is unknown: the standstill C1 (`c1`) decays S slowest
        self.s_um = s * self.params.c1 ** (max(elapsed_s, 0.0) / self.params.dt_s)
        if self.params.t0_c is None and state.get("t0_c") is not None:
            x0 = np.asarray(state["t0_c"], dtype=float)
            if x0.shape == (len(self.inputs) - 1,):
                self.x0 = x0
