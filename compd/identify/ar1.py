"""Identification of the AR(1) spindle model: C1 search, bounded C2/bed/ambient least squares, Ljung–Box (paper 001)."""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy import optimize, signal, stats

from compd.config import Strict
from compd.errors import BadInput
from compd.identify.data import (
    FitResult,
    axis_names,
    columns,
    default_targets,
    progress,
    require_rows,
    validate_options,
)
from compd.log import Log
from compd.models.ar1 import AR1, AR1Params, c2_of_speed
from compd.models.ar1 import ar_filter as stepwise_filter
from compd.models.base import step_rows


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


def ar_filter(c1: float | np.ndarray, u: np.ndarray, s0: float = 0.0) -> np.ndarray:
    """compd.models.ar1.ar_filter for the fits' design matrices: scipy's lfilter for a scalar C1
    (the same roundings, fast on many columns), the run-time loop for one C1 per row."""
    if np.isscalar(c1):
        zi = np.full((1,) + u.shape[1:], c1 * s0)
        return signal.lfilter([1.0], [1.0, -float(c1)], u, axis=0, zi=zi)[0]
    return stepwise_filter(c1, u, s0)


class Options(Strict):
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
    rise_sensor: str | None = Field(
        None,
        description="headstock sensor column whose rise over a run's first `rise_window_s` scales C2 to the "
        "speeds the error was not logged at (paper 001, eqs. 20–21); none = C2 linear in speed there",
    )
    rise_window_s: float = Field(6000.0, gt=0, description="the rise's window from a run's start (paper: 100 min)")
    rise_log: str | None = Field(
        None, description="another log (speed and `rise_sensor`) holding the runs at other speeds"
    )


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """C1 by a bounded 1-D search; for each C1 the rest (C2 levels ≥ 0 and monotone, bed
    gains, C3) is a bounded linear least-squares problem on the simulated output, so the
    fit minimises the free-run error the loop will make, not the one-step error."""
    opt = validate_options("ar1", Options, options)
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
    dt = opt.dt_s if opt.dt_s is not None else _median_step_s(log)
    rows = step_rows(t, dt)
    nparam = 1 + len(bed) + (opt.ambient is not None) + 2
    require_rows(log, rows.size, nparam + 3, f"ar1 at Δτ = {dt:g} s")
    Xs, Es = X[rows], E[rows]
    speed = np.abs(Xs[:, 0])
    moving = speed >= max(opt.stopped_below_rpm, 1e-12)
    rpm = speed_levels_rpm(speed[moving], opt.speed_round_rpm)
    if not rpm:
        raise BadInput(f"the spindle never turns in {opt.speed_column!r}: C2 cannot be fitted", file=log.file)
    sign = opt.spindle_sign if opt.spindle_sign is not None else (-1 if bed else 1)
    problem = _Problem(Xs, Es, speed, rpm, len(bed), bool(opt.ambient), sign)
    z, i, res = problem.search_c1()
    c1 = float(1.0 - np.exp(z))
    report: dict[str, Any] = {
        "dt_s": dt,
        "step_rows": int(rows.size),
        "speed_levels_rpm": rpm,
        "converged": bool(res.success),
        "c1_at_grid_edge": i in (0, C1_GRID.size - 1),
    }
    c1_rows: float | np.ndarray = c1
    c1_table: list[tuple[float, float]] = []
    if opt.c1_by_speed:
        if moving.all():
            raise BadInput(
                "c1_by_speed needs the spindle to stand still in the log (C1 at standstill)",
                file=log.file, path="--option c1_by_speed",
            )
        c1, c1_table, c1_rows, report["c1_by_speed"] = problem.c1_by_speed(z, float(res.fun), dt)
    _, theta = problem.solve(c1_rows)
    L, nb = len(rpm), len(bed)
    c2 = np.cumsum(theta[:L])
    table = [(r_, float(c)) for r_, c in zip(rpm, c2, strict=True)]
    if opt.c2_rise and opt.rise_sensor:
        raise BadInput("give c2_rise (the rises) or rise_sensor (measure them), not both", path="--option")
    if opt.c2_rise:
        table, report["c2_rise"] = _scaled_table(table, opt.c2_rise)
        unseen = {"method": "temperature_rise", "reason": "the c2_rise option gives the temperature rises"}
    else:
        table, unseen = _rise_from_runs(table, log, opt)
    report["c2_at_unseen_speeds"] = unseen
    params = AR1Params(
        dt_s=dt,
        c1=c1,
        c2_table=table,
        c3_um_per_k=float(theta[L + nb]) if opt.ambient else None,
        c1_table=c1_table,
        bed_gain_um_per_k=[float(v) for v in theta[L : L + nb]],
        spindle_sign=sign,
        t0_c=None,
        recursion_start="zero",
    )
    model = AR1(params, names, axis_names(targets))
    model.start(Xs[0], float(t[rows[0]]))
    resid = Es - model._response(Xs, model._c1_rows(Xs[:, 0]))
    lags = max(1, min(10, rows.size // 5))
    qstat, pval = ljung_box(resid, lags)
    report["ljung_box"] = {"lags": lags, "q": qstat, "p_value": pval, "white_at_5pct": pval > 0.05}
    report["step_rmse_um"] = float(np.sqrt(np.mean(resid**2)))
    model.x0 = None  # the run-time reference is the reading at start
    return FitResult(model, report)


def _median_step_s(log: Log) -> float:
    """Δτ when none is given: the log's median sample period."""
    dts = np.diff(log.t_s)
    dts = dts[dts > 0]
    if dts.size == 0:
        raise BadInput("t_s never advances: cannot tell the step Δτ", file=log.file, path="t_s")
    return float(np.median(dts))


def speed_levels_rpm(moving_rpm: np.ndarray, round_rpm: float) -> list[float]:
    """The logged speed levels: sorted speeds closer than `round_rpm` to the previous one join its level."""
    levels: list[list[float]] = []
    for v in np.sort(moving_rpm):
        if not levels or v - levels[-1][-1] > round_rpm:
            levels.append([v])
        else:
            levels[-1].append(v)
    return [float(np.mean(lv)) for lv in levels]


# log(1 − C1) spans time constants from a few Δτ to 10⁵ Δτ.
C1_GRID = np.linspace(np.log(0.5), np.log(1e-5), 40)


class _Problem:
    """For a given C1 (one, or one per step), the bounded linear least squares of the rest:
    C2 level increments δ ≥ 0 (C2 monotone in speed), bed gains, C3; on the simulated output."""

    def __init__(
        self, Xs: np.ndarray, Es: np.ndarray, speed: np.ndarray, rpm: list[float], n_bed: int, ambient: bool,
        sign: int,
    ) -> None:
        L = len(rpm)
        x0 = Xs[0, 1:]
        # Interpolation weights of each step's speed on the level nodes (C2 linear in them).
        Wt = np.zeros((Xs.shape[0], L))
        for k, v in enumerate(speed):
            for j in range(L):
                e_j = np.zeros(L)
                e_j[j] = 1.0
                Wt[k, j] = c2_of_speed(v, rpm, list(e_j))
        Wt[0] = 0.0  # ΔL(0) = 0 (paper 001, eq. 17): C2 enters from the second step on
        self.Wt, self.L, self.Es, self.sign = Wt, L, Es, sign
        self.cum = np.tril(np.ones((L, L)))  # C2 levels = cumulative sum of increments δ ≥ 0
        self.bed_rise = Xs[:, 1 : 1 + n_bed] - x0[:n_bed]
        self.amb_rise = (Xs[:, -1] - x0[-1])[:, None] if ambient else np.zeros((Xs.shape[0], 0))
        nb, na = self.bed_rise.shape[1], self.amb_rise.shape[1]
        self.lb = np.r_[np.zeros(L), np.full(nb + na, -np.inf)]
        self.ub = np.full(L + nb + na, np.inf)
        self.rpm = rpm

    def design(self, c1: float | np.ndarray) -> np.ndarray:
        L, sign = self.L, self.sign
        filt = ar_filter(c1, np.hstack([self.Wt @ self.cum, self.amb_rise]))
        return np.hstack([sign * filt[:, :L], self.bed_rise, sign * filt[:, L:]])

    def solve(self, c1: float | np.ndarray) -> tuple[float, np.ndarray]:
        """(sum of squared errors, [δ, bed gains, C3]) at this C1."""
        A = self.design(c1)
        r = optimize.lsq_linear(A, self.Es, bounds=(self.lb, self.ub), method="bvls")
        return float(np.sum((A @ r.x - self.Es) ** 2)), r.x

    def search_c1(self) -> tuple[float, int, Any]:
        """(z = log(1 − C1), grid index of the best start, the bounded search's result)."""
        grid = C1_GRID
        costs = [self.solve(1.0 - np.exp(z))[0] for z in progress(grid, desc="ar1 C1 search")]
        i = int(np.argmin(costs))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = optimize.minimize_scalar(
            lambda z: self.solve(1.0 - np.exp(z))[0], bounds=(min(lo, hi), max(lo, hi)), method="bounded",
            options={"xatol": 1e-6},
        )
        z = res.x if res.fun <= costs[i] else grid[i]
        return z, i, res

    def c1_by_speed(
        self, z: float, cost: float, dt: float
    ) -> tuple[float, list[tuple[float, float]], np.ndarray, dict[str, Any]]:
        """compd's form: b Δτ = −ln C1 at standstill and at each level, linear in speed between
        them, by Nelder–Mead from the single C1 (z). Returns (C1 at standstill, c1_table, C1 per
        step, report)."""
        L, Wt = self.L, self.Wt
        w0 = 1.0 - Wt.sum(axis=1)
        z_min, z_max = float(C1_GRID.min()), float(C1_GRID.max())

        def rows_c1(zs: np.ndarray) -> np.ndarray:
            b = -np.log1p(-np.exp(np.clip(zs, z_min, z_max)))
            return np.exp(-(w0 * b[0] + Wt @ b[1:]))

        res_n = optimize.minimize(
            lambda zs: self.solve(rows_c1(zs))[0], np.full(L + 1, z), method="Nelder-Mead",
            options={"xatol": 1e-5, "fatol": 1e-9 * max(cost, 1e-12), "maxiter": 400 * (L + 1)},
        )
        zs = np.clip(res_n.x, z_min, z_max)
        c1 = float(1.0 - np.exp(zs[0]))
        c1_table = [(r_, float(1.0 - np.exp(v))) for r_, v in zip(self.rpm, zs[1:], strict=True)]
        report = {
            "converged": bool(res_n.success), "single_c1": float(1.0 - np.exp(z)),
            "time_constant_s": {"0": -dt / math.log(c1), **{f"{r_:g}": -dt / math.log(c)
                                                           for r_, c in c1_table}},
        }
        return c1, c1_table, rows_c1(zs), report


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


def run_rises_c(
    t_s: np.ndarray, speed_rpm: np.ndarray, temp_c: np.ndarray, window_s: float, round_rpm: float, stopped_rpm: float
) -> dict[float, float]:
    """Temperature rise over the first `window_s` of a run at each speed: {mean speed of the run: rise}.

    A run starts from standstill (or at the log's first row) and holds one speed (within
    `round_rpm` of its first row) for at least `window_s`; the first such run of a speed counts.
    The reading at start + window is interpolated in time (paper 001, Table 2: the first 100 min).
    """
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    out: dict[float, float] = {}
    k, K = 0, n.size
    while k < K:
        if n[k] < max(stopped_rpm, 1e-12) or (k > 0 and n[k - 1] >= max(stopped_rpm, 1e-12)):
            k += 1
            continue
        j = k
        while j + 1 < K and abs(n[j + 1] - n[k]) <= round_rpm:
            j += 1
        end_s = t_s[k] + window_s
        level = float(np.mean(n[k : j + 1]))
        if t_s[j] >= end_s and not any(abs(level - r) <= round_rpm for r in out):
            rise = float(np.interp(end_s, t_s[k : j + 1], temp_c[k : j + 1]) - temp_c[k])
            out[level] = rise
        k = j + 1
    return dict(sorted(out.items()))


def _rise_from_runs(
    table: list[tuple[float, float]], log: Log, opt: Options
) -> tuple[list[tuple[float, float]], dict[str, Any]]:
    """C2 at speeds with a run but no fitted level, scaled by the rise ratio to a fitted level
    (paper 001, eqs. 20–21), when `rise_sensor` names the sensor and the runs are there;
    otherwise the table as it is (C2 linear in speed between its levels). Returns (table, report)."""
    linear = {"method": "linear"}
    if opt.rise_sensor is None:
        return table, {**linear, "reason": "no rise_sensor named: C2 is linear in speed between the fitted levels"}
    rises: dict[float, float] = {}
    sources = [log]
    if opt.rise_log is not None:
        from compd.log import read_log

        sources.append(read_log(opt.rise_log, allow_nan=True))
    for src in sources:
        X = columns(src, [opt.speed_column, opt.rise_sensor])
        for n, r in run_rises_c(
            src.t_s, X[:, 0], X[:, 1], opt.rise_window_s, opt.speed_round_rpm, opt.stopped_below_rpm
        ).items():
            if not any(abs(n - m) <= opt.speed_round_rpm for m in rises):
                rises[n] = r
    info: dict[str, Any] = {"rise_sensor": opt.rise_sensor, "rise_window_s": opt.rise_window_s,
                            "rises_c": {f"{n:g}": r for n, r in rises.items()}}

    def near_level(n: float) -> bool:
        return any(abs(n - m) <= opt.speed_round_rpm for m, _ in table)

    refs = [n for n in rises if near_level(n) and rises[n] > 0]
    others = {n: r for n, r in rises.items() if not near_level(n)}
    if not refs or not others:
        why = (f"no run of {opt.rise_window_s:g} s from standstill at a fitted speed" if not refs
               else f"no run of {opt.rise_window_s:g} s from standstill at a speed without a fitted C2")
        return table, {**linear, **info, "reason": f"{why} in the log: C2 is linear in speed between the fitted levels"}
    ref = max(refs)  # the fastest fitted run: the largest rise, as the paper's 2000 rpm
    scaled, added = _scaled_table(table, {"ref_rpm": ref, "ref_rise_c": rises[ref], "rises_c": others})
    return scaled, {
        "method": "temperature_rise", **info, "ref_rpm": ref, **added,
        "reason": f"C2 at {', '.join(f'{n:g}' for n in others)} rpm = C2({ref:g} rpm) × the rise of "
        f"{opt.rise_sensor} there / at {ref:g} rpm (paper 001, eqs. 20–21)",
    }
