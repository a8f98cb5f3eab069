"""AR(1) spindle elongation model with speed-dependent C2, bed term and ambient input (paper 001).

Every Δτ the spindle growth steps as S(k) = C1 S(k−1) + C2(n_k) + C3 ΔT_amb(k) (eq. 9 of
paper 001 with the ambient as exogenous input; C3 = 0 is the paper), and the error is
E(k) = Σ_j g_j ΔT_j(k) + s·S(k): for the paper's lathe Z axis the bed sensors enter
with g = α_bed L_bed and the spindle with s = −1 (error = bed growth − spindle growth).
C2(n) is piecewise linear in the spindle speed n through (0, 0) and the fitted levels,
held at the last level above it. The state S is the model's memory.

compd's speed-dependent form (`c1_table`): C1 = e^(−b Δτ) with b = 2h/(ρcR), and a turning
spindle's convection h grows with its speed, so b is fitted at standstill and at each
logged speed and interpolated linearly in n between them (held past the last);
an empty table is the paper's single C1.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator
from scipy import optimize, signal, stats

from compd.config import Strict
from compd.errors import BadInput
from compd.log import Log
from compd.models.base import (
    MAX_ERROR_UM,
    MAX_GAIN_UM_PER_K,
    MAX_SPEED_RPM,
    TEMP_MAX_C,
    TEMP_MIN_C,
    FitResult,
    Model,
    ModelParams,
    check_length,
)
from compd.models.fitdata import (
    axis_names,
    columns,
    default_targets,
    progress,
    require_rows,
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


def scale_c2_by_rise(c2_ref_um: float, rise_ref_c: float, rises_c: dict[float, float]) -> dict[float, float]:
    """C2 at other speeds from the temperature rise of one headstock sensor (paper 001, §4).

    C2(n) = C2(n_ref) · ΔT(n) / ΔT(n_ref), the rises taken over the same time (paper:
    the first 100 min). Paper: 0.22 · 3.02/7.46 = 0.089 µm at 1000 rpm.
    """
    if rise_ref_c <= 0:
        raise BadInput("the reference temperature rise must be positive", path="c2_rise.ref_rise_c")
    return {float(n): c2_ref_um * r / rise_ref_c for n, r in rises_c.items()}


def ljung_box(resid: np.ndarray, lags: int) -> tuple[float, float]:
    """Ljung–Box Q = n(n+2) Σ_{k=1..m} ρ_k²/(n−k) and its p-value against χ²(m) (paper 001, eq. 12).

    ρ_k is the sample autocorrelation of the mean-removed residuals (denominator Σ e²).
    """
    e = np.asarray(resid, dtype=float) - np.mean(resid)
    n = e.size
    if not 1 <= lags < n:
        raise ValueError(f"lags must be 1..{n - 1}")
    den = float(e @ e)
    if den == 0.0:
        return 0.0, 1.0
    k = np.arange(1, lags + 1)
    rho = np.array([float(e[j:] @ e[:-j]) / den for j in k])
    qstat = n * (n + 2) * float(np.sum(rho**2 / (n - k)))
    return qstat, float(stats.chi2.sf(qstat, lags))


SpeedRpm = Annotated[float, Field(gt=0, le=MAX_SPEED_RPM)]


class AR1Params(ModelParams):
    """AR(1) model params. Inputs: [speed, *bed sensors, ambient (when c3_um_per_k is set)]."""

    dt_s: float = Field(gt=0, le=86400, description="Δτ, the model step (paper: 30–60 s), at most a day")
    c1: float = Field(gt=0, lt=1, description="C1 = e^(−b Δτ) (at standstill when c1_table is set)")
    c2_table: list[tuple[SpeedRpm, Annotated[float, Field(ge=0, le=MAX_ERROR_UM)]]] = Field(
        default_factory=list, description="(speed rpm, C2 µm ≥ 0) nodes; C2(0) = 0 is implied"
    )
    c3_um_per_k: float | None = Field(
        None, ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K,
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
    spindle_sign: Literal[1, -1] = Field(1, description="+1: error = spindle growth; −1: bed − spindle")
    t0_c: list[Annotated[float, Field(ge=TEMP_MIN_C, le=TEMP_MAX_C)]] | None = Field(
        None, description="reference readings of bed and ambient inputs (−40..150 °C)"
    )

    @model_validator(mode="after")
    def _table(self) -> AR1Params:
        # speeds > 0, C2 ≥ 0 and C1 in (0, 1) are the fields' own bounds
        for key, table in (("c2_table", self.c2_table), ("c1_table", self.c1_table)):
            rpm = [n for n, _ in table]
            if any(b <= a for a, b in zip(rpm, rpm[1:], strict=False)):
                raise ValueError(f"{key} speeds must be positive and strictly increasing")
        return self


def c2_of_speed(speed_rpm: float, rpm: list[float], c2: list[float], at_zero: float = 0.0) -> float:
    """C2(n): linear through (0, at_zero) and the table nodes, constant past the last node."""
    n = abs(speed_rpm)
    lo_n, lo_c = 0.0, at_zero
    for hi_n, hi_c in zip(rpm, c2, strict=True):
        if n <= hi_n:
            return lo_c + (hi_c - lo_c) * (n - lo_n) / (hi_n - lo_n)
        lo_n, lo_c = hi_n, hi_c
    return lo_c


def ar_filter(c1: float | np.ndarray, u: np.ndarray, s0: float = 0.0) -> np.ndarray:
    """s(k) = C1(k) s(k−1) + u(k) from s(−1) = s0, column-wise for a 2-D u; C1 a scalar or one per row."""
    if np.isscalar(c1):
        zi = np.full((1,) + u.shape[1:], c1 * s0)
        return signal.lfilter([1.0], [1.0, -float(c1)], u, axis=0, zi=zi)[0]
    s = np.empty_like(u, dtype=float)
    prev = np.full(u.shape[1:], s0, dtype=float)
    for k in range(u.shape[0]):
        prev = c1[k] * prev + u[k]
        s[k] = prev
    return s


class AR1FitOptions(Strict):
    """`compd fit --kind ar1 --option KEY=VALUE` (`--ambient COL` sets `ambient`)."""

    dt_s: float | None = Field(None, gt=0, description="Δτ; none = the log's median sample period")
    ambient: str | None = Field(None, description="ambient sensor column (enables C3)")
    speed_column: str = "speed_rpm"
    speed_round_rpm: float = Field(50.0, gt=0, description="speeds this close form one level")
    stopped_below_rpm: float = Field(1.0, ge=0, description="slower than this counts as stopped")
    spindle_sign: Literal[1, -1] | None = Field(None, description="none: −1 with bed inputs, else +1")
    c1_by_speed: bool = Field(
        False, description="fit C1 at standstill and at each logged speed (compd's form; needs stops in the log)"
    )
    c2_rise: dict[str, Any] | None = Field(
        None,
        description="{ref_rpm, ref_rise_c, rises_c: {rpm: rise}}: add C2 at unlogged speeds (paper §4)",
    )


class AR1(Model):
    """AR(1) spindle growth stepped every Δτ, plus linear bed terms (paper 001)."""

    kind = "ar1"
    Params = AR1Params
    FitOptions = AR1FitOptions

    def __init__(self, params: AR1Params, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self.update_period_s = params.dt_s
        self._rpm = [float(n) for n, _ in params.c2_table]
        self._c2 = [float(c) for _, c in params.c2_table]
        self._nb = len(params.bed_gain_um_per_k)
        self._gain = np.asarray(params.bed_gain_um_per_k, dtype=float)
        self._c3 = params.c3_um_per_k
        self._rpm1 = [float(n) for n, _ in params.c1_table]
        self._b1 = [-math.log(c) for _, c in params.c1_table]  # b Δτ at each node
        self._b0 = -math.log(params.c1)
        self._amb = 1 + self._nb if self._c3 is not None else -1
        self._sign = float(params.spindle_sign)
        self.x0 = np.asarray(params.t0_c, dtype=float) if params.t0_c is not None else None
        self.s_um = 0.0
        self._rise = np.zeros(self._nb)

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        need = 1 + len(params.bed_gain_um_per_k) + (params.c3_um_per_k is not None)
        if len(inputs) != need:
            raise BadInput(
                f"ar1 takes {need} inputs (speed, {len(params.bed_gain_um_per_k)} bed sensors"
                f"{', ambient' if params.c3_um_per_k is not None else ''}), got {len(inputs)}",
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
        """One Δτ step: S = C1 S + C2(n) + C3 ΔT_amb; E = Σ g ΔT_bed + s S (µm)."""
        u = c2_of_speed(x[0], self._rpm, self._c2)
        if self._amb > 0:
            u += self._c3 * (x[self._amb] - self.x0[self._amb - 1])
        self.s_um = self.c1_at(x[0]) * self.s_um + u
        e = self._sign * self.s_um
        if self._nb:
            np.subtract(x[1 : 1 + self._nb], self.x0[: self._nb], out=self._rise)
            e += float(self._rise @ self._gain)
        out[0] = e

    def c1_at(self, speed_rpm: float) -> float:
        """C1 at this speed: `c1`, or e^(−b Δτ) with b interpolated in speed (`c1_table`)."""
        if not self._rpm1:
            return self.params.c1
        return math.exp(-c2_of_speed(speed_rpm, self._rpm1, self._b1, self._b0))

    def predict(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
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
        if not self._rpm1:
            return self.params.c1
        return np.array([self.c1_at(v) for v in speed_rpm])

    def _response(self, Xs: np.ndarray, c1: float | np.ndarray, s0: float = 0.0) -> np.ndarray:
        u = np.array([c2_of_speed(v, self._rpm, self._c2) for v in Xs[:, 0]])
        if self._amb > 0:
            u += self._c3 * (Xs[:, self._amb] - self.x0[self._amb - 1])
        s = ar_filter(c1, u, s0)
        self._last_s = s[-1]
        e = self._sign * s
        if self._nb:
            e = e + (Xs[:, 1 : 1 + self._nb] - self.x0[: self._nb]) @ self._gain
        return e

    def get_state(self) -> dict[str, Any]:
        return {
            "s_um": float(self.s_um),
            "t0_c": None if self.x0 is None else [float(v) for v in self.x0],
        }

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        """Restore S saved `elapsed_s` ago, cooled by its own time constant: S·C1^(elapsed/Δτ)."""
        s = float(state.get("s_um", 0.0))
        # while compd was down the speed is unknown: the standstill C1 (`c1`) decays S slowest
        self.s_um = s * self.params.c1 ** (max(elapsed_s, 0.0) / self.params.dt_s)
        if self.params.t0_c is None and state.get("t0_c") is not None:
            x0 = np.asarray(state["t0_c"], dtype=float)
            if x0.shape == (len(self.inputs) - 1,):
                self.x0 = x0

    @classmethod
    def fit(cls, log: Log, inputs=None, targets=None, **options: Any) -> FitResult:
        """C1 by a bounded 1-D search; for each C1 the rest (C2 levels ≥ 0 and monotone, bed
        gains, C3) is a bounded linear least-squares problem on the simulated output, so the
        fit minimises the free-run error the loop will make, not the one-step error."""
        opt = cls.fit_options(options)
        targets = default_targets(log, targets)
        if len(targets) != 1:
            raise BadInput(f"ar1 fits one axis at a time; targets: {', '.join(targets)}", path="--target")
        bed = list(inputs or [])
        names = [opt.speed_column, *bed] + ([opt.ambient] if opt.ambient else [])
        if len(set(names)) != len(names):
            raise BadInput("the speed, bed and ambient columns must differ", path="--inputs")
        X = columns(log, names)
        E = columns(log, targets)[:, 0]
        t = log.t_s
        dt = opt.dt_s
        if dt is None:
            dts = np.diff(t)
            dts = dts[dts > 0]
            if dts.size == 0:
                raise BadInput("t_s never advances: cannot tell the step Δτ", file=log.file, path="t_s")
            dt = float(np.median(dts))
        rows = step_rows(t, dt)
        nparam = 1 + len(bed) + (opt.ambient is not None) + 2
        require_rows(log, rows.size, nparam + 3, f"ar1 at Δτ = {dt:g} s")
        Xs, Es = X[rows], E[rows]
        speed = np.abs(Xs[:, 0])
        moving = speed >= max(opt.stopped_below_rpm, 1e-12)
        levels: list[list[float]] = []
        for v in np.sort(speed[moving]):
            if not levels or v - levels[-1][-1] > opt.speed_round_rpm:
                levels.append([v])
            else:
                levels[-1].append(v)
        rpm = [float(np.mean(lv)) for lv in levels]
        if not rpm:
            raise BadInput(f"the spindle never turns in {opt.speed_column!r}: C2 cannot be fitted", file=log.file)
        sign = opt.spindle_sign if opt.spindle_sign is not None else (-1 if bed else 1)
        x0 = Xs[0, 1:]
        # Interpolation weights of each step's speed on the level nodes (C2 linear in them).
        L = len(rpm)
        Wt = np.zeros((rows.size, L))
        for k, v in enumerate(speed):
            for j in range(L):
                e_j = np.zeros(L)
                e_j[j] = 1.0
                Wt[k, j] = c2_of_speed(v, rpm, list(e_j))
        cum = np.tril(np.ones((L, L)))  # C2 levels = cumulative sum of increments δ ≥ 0
        bed_rise = Xs[:, 1 : 1 + len(bed)] - x0[: len(bed)]
        amb_rise = (Xs[:, -1] - x0[-1])[:, None] if opt.ambient else np.zeros((rows.size, 0))
        nb, na = bed_rise.shape[1], amb_rise.shape[1]
        lb = np.r_[np.zeros(L), np.full(nb + na, -np.inf)]
        ub = np.full(L + nb + na, np.inf)

        def design(c1: float | np.ndarray) -> np.ndarray:
            filt = ar_filter(c1, np.hstack([Wt @ cum, amb_rise]))
            return np.hstack([sign * filt[:, :L], bed_rise, sign * filt[:, L:]])

        def solve(c1: float | np.ndarray) -> tuple[float, np.ndarray]:
            A = design(c1)
            r = optimize.lsq_linear(A, Es, bounds=(lb, ub), method="bvls")
            return float(np.sum((A @ r.x - Es) ** 2)), r.x

        # log(1 − C1) spans time constants from a few Δτ to 10⁵ Δτ.
        grid = np.linspace(np.log(0.5), np.log(1e-5), 40)
        costs = [solve(1.0 - np.exp(z))[0] for z in progress(grid, desc="ar1 C1 search")]
        i = int(np.argmin(costs))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = optimize.minimize_scalar(
            lambda z: solve(1.0 - np.exp(z))[0], bounds=(min(lo, hi), max(lo, hi)), method="bounded",
            options={"xatol": 1e-6},
        )
        z = res.x if res.fun <= costs[i] else grid[i]
        c1 = float(1.0 - np.exp(z))
        report: dict[str, Any] = {
            "dt_s": dt,
            "step_rows": int(rows.size),
            "speed_levels_rpm": rpm,
            "converged": bool(res.success),
            "c1_at_grid_edge": i in (0, grid.size - 1),
        }
        c1_rows: float | np.ndarray = c1
        c1_table: list[tuple[float, float]] = []
        if opt.c1_by_speed:
            if moving.all():
                raise BadInput(
                    "c1_by_speed needs the spindle to stand still in the log (C1 at standstill)",
                    file=log.file, path="--option c1_by_speed",
                )
            # b Δτ = −ln C1 at standstill and at each level, linear in speed between them
            w0 = 1.0 - Wt.sum(axis=1)
            z_min, z_max = float(grid.min()), float(grid.max())

            def rows_c1(zs: np.ndarray) -> np.ndarray:
                b = -np.log1p(-np.exp(np.clip(zs, z_min, z_max)))
                return np.exp(-(w0 * b[0] + Wt @ b[1:]))

            res_n = optimize.minimize(
                lambda zs: solve(rows_c1(zs))[0], np.full(L + 1, z), method="Nelder-Mead",
                options={"xatol": 1e-5, "fatol": 1e-9 * max(res.fun, 1e-12), "maxiter": 400 * (L + 1)},
            )
            zs = np.clip(res_n.x, z_min, z_max)
            c1 = float(1.0 - np.exp(zs[0]))
            c1_table = [(r_, float(1.0 - np.exp(v))) for r_, v in zip(rpm, zs[1:], strict=True)]
            c1_rows = rows_c1(zs)
            report["c1_by_speed"] = {
                "converged": bool(res_n.success), "single_c1": float(1.0 - np.exp(z)),
                "time_constant_s": {"0": -dt / math.log(c1), **{f"{r_:g}": -dt / math.log(c)
                                                               for r_, c in c1_table}},
            }
        cost, theta = solve(c1_rows)
        c2 = np.cumsum(theta[:L])
        table = [(r_, float(c)) for r_, c in zip(rpm, c2, strict=True)]
        if opt.c2_rise:
            table, report["c2_rise"] = _scaled_table(table, opt.c2_rise)
        params = AR1Params(
            dt_s=dt,
            c1=c1,
            c2_table=table,
            c3_um_per_k=float(theta[L + nb]) if na else None,
            c1_table=c1_table,
            bed_gain_um_per_k=[float(v) for v in theta[L : L + nb]],
            spindle_sign=sign,
            t0_c=None,
        )
        model = cls(params, names, axis_names(targets))
        model.start(Xs[0], float(t[rows[0]]))
        resid = Es - model._response(Xs, model._c1_rows(Xs[:, 0]))
        lags = max(1, min(10, rows.size // 5))
        qstat, pval = ljung_box(resid, lags)
        report["ljung_box"] = {"lags": lags, "q": qstat, "p_value": pval, "white_at_5pct": pval > 0.05}
        report["step_rmse_um"] = float(np.sqrt(np.mean(resid**2)))
        model.x0 = None  # the run-time reference is the reading at start
        return FitResult(model, report)


def _scaled_table(
    table: list[tuple[float, float]], spec: dict[str, Any]
) -> tuple[list[tuple[float, float]], dict[str, Any]]:
    """Add C2 at speeds not in the log by the temperature-rise ratio (paper 001 §4)."""
    try:
        ref_rpm = float(spec["ref_rpm"])
        ref_rise = float(spec["ref_rise_c"])
        rises = {float(k): float(v) for k, v in dict(spec["rises_c"]).items()}
    except (KeyError, TypeError, ValueError) as e:
        raise BadInput(
            f"c2_rise needs ref_rpm, ref_rise_c and rises_c {{rpm: rise}} ({e})", path="--option c2_rise"
        ) from None
    rpm = [n for n, _ in table]
    c2_ref = c2_of_speed(ref_rpm, rpm, [c for _, c in table])
    added = scale_c2_by_rise(c2_ref, ref_rise, rises)
    merged = dict(table)
    for n, c in added.items():
        if n not in merged:
            merged[n] = c
    out = sorted(merged.items())
    monotone = all(b[1] >= a[1] for a, b in zip(out, out[1:], strict=False))
    info = {"c2_ref_um": c2_ref, "added": {str(k): v for k, v in added.items()}, "monotone": monotone}
    return out, info
