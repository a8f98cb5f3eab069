"""Identification of the AR(1) spindle model: C1 search, bounded C2/bed/ambient least squares, Ljung–Box (paper 001)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy import optimize, signal, stats

from compd.config import Strict
from compd.errors import BadInput
from compd.identify import holdout
from compd.identify.data import (
    HELD_OUT_METHOD,
    FitResult,
    ambient_columns,
    axis_names,
    columns,
    compare_forms,
    default_targets,
    measured_rows,
    progress,
    require_rows,
    target_columns,
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
    ambient: str | None = Field(
        "auto",
        description="ambient sensor column (enables C3); auto = the column whose name says air (amb, room, air),"
        " else the temperature column the spindle's duty warms least, kept unless it predicts the held-out folds"
        " clearly worse; none (or null) = the paper's constant shop",
    )
    speed_column: str = "speed_rpm"
    speed_round_rpm: float = Field(50.0, gt=0, description="speeds this close form one level")
    stopped_below_rpm: float = Field(1.0, ge=0, description="slower than this counts as stopped")
    spindle_sign: Literal[1, -1] | None = Field(None, description="none: −1 with bed inputs, else +1")
    c1_by_speed: bool | Literal["auto"] = Field(
        "auto",
        description="fit C1 at standstill and at each logged speed (compd's form; needs stops in the log);"
        " false = one C1 (the paper's); auto = compd's form where it predicts the later blocks of the log"
        " at least 5 % better held out, else the paper's",
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
    c2_exponent: float | Literal["linear"] = Field(
        1.0,
        description="C2 at speeds outside the fitted levels: C2(nearest level)·(n/level)^e (0.5 … 3); default 1:"
        " proportional, below the levels as the older rule, above them carried on instead of held (the bearings'"
        " friction heat grows as n^(5/3), Palmgren, but the rotor's convection grows with n too, so C2 at one"
        " C1 grows less); linear = the older rule (linear from 0 below the first level, held past the last)",
    )
    exchange: list[str] | Literal["auto", "none"] = Field(
        "none",
        description="the sensors the spindle exchanges heat with besides the air (its housing, where its bearings"
        " sit), entering the recursion with a gain ≥ 0 each (compd's form); auto = chosen held out among the"
        " temperature columns that are neither --inputs nor the ambient (at most 2, each kept while it cuts the"
        " held-out RMSE by 5 %); none = the paper's recursion",
    )
    bed_gains: Literal["positive", "free"] = Field(
        "positive",
        description="positive: the structure (bed) sensors' gains ≥ 0 in the lathe form (error = bed − spindle:"
        " the bed's growth adds, paper 001 eq. 15); free: any sign",
    )


AUTO_MARGIN = 0.95  # compd's form must cut the held-out RMSE by 5 % to replace the paper's


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """The AR(1) model; with `c1_by_speed: auto` the paper's single C1 unless C1 by speed predicts
    the later blocks of the log clearly better (compd.identify.data.compare_forms)."""
    opt = validate_options("ar1", Options, options)
    chosen_ambient: dict[str, Any] | None = None
    if opt.ambient in ("auto", "none", None):
        name, chosen_ambient = (None, None) if opt.ambient != "auto" else ambient_sensor(log, inputs, targets, opt)
        opt = opt.model_copy(update={"ambient": name})
    chosen_inputs: dict[str, Any] | None = None
    if not inputs and opt.spindle_sign != 1:
        inputs, chosen_inputs = structure_sensors(log, targets, opt)
    chosen_exchange: dict[str, Any] | None = None
    if opt.exchange == "auto":
        names, chosen_exchange = exchange_sensors(log, inputs, targets, opt)
        opt = opt.model_copy(update={"exchange": names})
    result = _fit_form(log, inputs, targets, opt)
    if chosen_inputs is not None:
        result.report["inputs_chosen"] = chosen_inputs
    if chosen_exchange is not None:
        result.report["exchange_chosen"] = chosen_exchange
    if chosen_ambient is not None:
        result.report["ambient_chosen"] = chosen_ambient
    return result


def ambient_sensor(
    log: Log, inputs: list[str] | None, targets: list[str] | None, opt: Options
) -> tuple[str | None, dict[str, Any]]:
    """The ambient (C3) for `ambient: auto`: the one temperature column named for the air (amb, room,
    air) that is not a structure input, kept unless the AR(1) with it predicts the held-out folds
    clearly worse (by 5 %) than without: the paper's limit is a constant shop, and the air is what
    breaks it. A machine's data alone does not tell the air from a sensor far from the heat (the
    shop's swings follow the shift as the duty does), so an unnamed ambient is `--ambient COL`."""
    bed = set(inputs or [])
    named = [c for c in ambient_columns(log) if c not in bed]
    if len(named) != 1:
        return None, {"ambient": None, "reason": f"{len(named)} columns named for the air (amb, room, air):"
                      " name it with --ambient"}
    name = named[0]
    info: dict[str, Any] = {"found": "by name"}
    target = default_targets(log, targets)
    quick = opt.model_copy(update={"c1_by_speed": False, "exchange": []})
    held = {}
    for key, amb in (("with", name), ("without", None)):
        o = quick.model_copy(update={"ambient": amb})
        try:
            held[key] = float(holdout.held_out_rmse(log, target, lambda lg, o=o: _fit(lg, inputs, targets, o))[0])
        except ValueError:
            held[key] = math.inf
    info["held_out_rmse_um"] = held
    if held["with"] * AUTO_MARGIN > held["without"]:
        return None, {**info, "ambient": None, "candidate": name,
                      "reason": "the AR(1) with it predicts the held-out folds clearly worse"}
    return name, {**info, "ambient": name}


def forward_select(
    candidates: list[str], score: Callable[[list[str]], float], most: int, start_um: float = math.inf
) -> tuple[list[str], list[dict[str, float]]]:
    """Forward selection: each step adds the candidate whose set scores best (held-out RMSE, µm), kept
    while it beats the set before clearly (holdout.clearly_better, AUTO_MARGIN), at most `most`; the
    first is always taken when `start_um` is inf. Returns (the chosen, every step's scores)."""
    chosen: list[str] = []
    steps: list[dict[str, float]] = [] if math.isinf(start_um) else [{"": start_um}]
    best = start_um
    while len(chosen) < min(most, len(candidates)):
        tried = {c: score([*chosen, c]) for c in candidates if c not in chosen}
        steps.append(tried)
        name = min(tried, key=tried.__getitem__)
        if not math.isinf(best) and not holdout.clearly_better(tried[name], best, AUTO_MARGIN):
            break
        chosen.append(name)
        best = tried[name]
    return chosen, steps


EXCHANGE_MAX = 2  # exchange sensors the auto choice takes at most


def exchange_sensors(
    log: Log, inputs: list[str] | None, targets: list[str] | None, opt: Options
) -> tuple[list[str], dict[str, Any]]:
    """The exchange sensors for `exchange: auto`: forward selection among the temperature columns that
    are neither structure sensors nor the ambient, each step the one whose recursion input predicts the
    held-out folds best, kept while it cuts the held-out RMSE clearly (5 %), at most EXCHANGE_MAX."""
    bed = list(inputs or [])
    candidates = [c for c in log.temperature_columns() if c not in bed and c != opt.ambient]
    target = default_targets(log, targets)
    quick = opt.model_copy(update={"c1_by_speed": False})

    def score(names: list[str]) -> float:
        o = quick.model_copy(update={"exchange": names})
        try:
            return float(holdout.held_out_rmse(log, target, lambda lg: _fit(lg, bed, targets, o))[0])
        except ValueError:
            return math.inf

    chosen, steps = forward_select(candidates, score, EXCHANGE_MAX, score([]))
    return chosen, {
        "exchange": chosen,
        "method": HELD_OUT_METHOD + f"; forward selection from none among the temperature columns that are neither"
        f" structure sensors nor the ambient, each kept while it cuts the held-out RMSE below {AUTO_MARGIN:g} ×,"
        f" at most {EXCHANGE_MAX}",
        "held_out_rmse_um": steps,
    }


STRUCTURE_MAX = 3  # structure (bed) sensors the default inputs take at most


def structure_sensors(log: Log, targets: list[str] | None, opt: Options) -> tuple[list[str], dict[str, Any]]:
    """The structure (bed) sensors when --inputs names none: forward selection among the log's
    temperature columns (not the ambient), each step the sensor whose AR(1) predicts the held-out
    folds best (compd.identify.holdout), kept while it cuts the held-out RMSE clearly (5 %), at
    most STRUCTURE_MAX. BadInput when the log has no temperature column to choose."""
    air = set(ambient_columns(log)) | {opt.ambient}
    candidates = [c for c in log.temperature_columns() if c not in air]
    if not candidates:
        raise BadInput(
            "ar1 needs a bed (structure) sensor whose growth adds to the spindle's, and the log has no"
            " temperature column but the ambient's: name it with --inputs (a spindle alone: --option"
            " spindle_sign=1)",
            file=log.file, path="--inputs",
        )
    target = default_targets(log, targets)
    quick = opt.model_copy(update={"c1_by_speed": False})

    def score(names: list[str]) -> float:
        try:
            return float(holdout.held_out_rmse(log, target, lambda lg: _fit(lg, names, targets, quick))[0])
        except ValueError:
            return math.inf

    chosen, steps = forward_select(candidates, score, STRUCTURE_MAX)
    return chosen, {
        "inputs": chosen,
        "method": HELD_OUT_METHOD + f"; forward selection among the temperature columns, each sensor kept while"
        f" it cuts the held-out RMSE below {AUTO_MARGIN:g} ×, at most {STRUCTURE_MAX}",
        "held_out_rmse_um": steps,
    }


def _fit_form(log: Log, inputs: list[str] | None, targets: list[str] | None, opt: Options) -> FitResult:
    """The AR(1) fit of `opt`'s C1 form; `auto`: the paper's single C1 unless C1 by speed predicts
    the held-out folds clearly better."""
    if opt.c1_by_speed != "auto":
        return _fit(log, inputs, targets, opt)
    paper = opt.model_copy(update={"c1_by_speed": False})
    by_speed = opt.model_copy(update={"c1_by_speed": True})
    result = _fit(log, inputs, targets, paper)
    target = default_targets(log, targets)[0]
    held, blocks = compare_forms(log, target, {
        "constant": lambda lg: _fit(lg, inputs, targets, paper),
        "by_speed": lambda lg: _fit(lg, inputs, targets, by_speed),
    })
    chosen = "constant"
    if all(isinstance(v, float) for v in held.values()) and holdout.clearly_better(
            float(held["by_speed"]), float(held["constant"]), AUTO_MARGIN):
        chosen = "by_speed"
        result = _fit(log, inputs, targets, by_speed)
    result.report["c1_form"] = {
        "chosen": chosen,
        "method": HELD_OUT_METHOD + f"; C1 by speed is kept only below {AUTO_MARGIN:g} × the paper's RMSE",
        "held_out_blocks": blocks,
        "held_out_rmse_um": held,
    }
    return result


def _fit(log: Log, inputs: list[str] | None, targets: list[str] | None, opt: Options) -> FitResult:
    """C1 by a bounded 1-D search; for each C1 the rest (C2 levels ≥ 0 and monotone, bed
    gains, C3) is a bounded linear least-squares problem on the simulated output, so the
    fit minimises the free-run error the loop will make, not the one-step error."""
    targets = default_targets(log, targets)
    if len(targets) != 1:
        raise BadInput(f"ar1 fits one axis at a time; targets: {', '.join(targets)}", path="--target")
    bed = list(inputs or [])
    exchange = [] if isinstance(opt.exchange, str) else list(opt.exchange)
    names = [opt.speed_column, *bed] + ([opt.ambient] if opt.ambient else []) + exchange
    if len(set(names)) != len(names):
        raise BadInput("the speed, bed, ambient and exchange columns must differ", path="--inputs")
    X = columns(log, names)
    E = target_columns(log, targets)[:, 0]
    t = log.t_s
    dt = opt.dt_s if opt.dt_s is not None else _median_step_s(log)
    rows = step_rows(t, dt)
    nparam = 1 + len(bed) + (opt.ambient is not None) + len(exchange) + 2
    Xs, Es = X[rows], E[rows]
    require_rows(log, int(measured_rows(Es).sum()), nparam + 3, f"ar1 at Δτ = {dt:g} s")
    speed = np.abs(Xs[:, 0])
    moving = speed >= max(opt.stopped_below_rpm, 1e-12)
    # the levels C2 is fitted at: speeds with a measured error (a speed held out, or never logged with
    # its error, is one the model has not seen: it gets C2 by interpolation or the exponent)
    rpm = speed_levels_rpm(speed[moving & measured_rows(Es)], opt.speed_round_rpm)
    if not rpm:
        raise BadInput(f"the spindle never turns in {opt.speed_column!r}: C2 cannot be fitted", file=log.file)
    sign = opt.spindle_sign if opt.spindle_sign is not None else (-1 if bed else 1)
    exponent = None if opt.c2_exponent == "linear" else float(opt.c2_exponent)
    positive = opt.bed_gains == "positive" and sign == -1
    problem = _Problem(Xs, Es, speed, rpm, len(bed), bool(opt.ambient), sign, c1_grid(dt), positive, exponent,
                       len(exchange))
    z, i, res = problem.search_c1()
    c1 = float(1.0 - np.exp(z))
    report: dict[str, Any] = {
        "fit_inputs": bed,  # what --inputs means for ar1: the structure sensors
        "dt_s": dt,
        "step_rows": int(rows.size),
        "speed_levels_rpm": rpm,
        "converged": bool(res.success),
        "c1_at_grid_edge": i in (0, GRID_POINTS - 1),
    }
    at_bounds = []
    if report["c1_at_grid_edge"]:
        at_bounds.append(f"C1 {c1:.6g} (time constant {-dt / math.log(c1):.4g} s) is at the edge of its search"
                         f" range ({_grid_tau_s(dt)}): the spindle term may stand in for something else")
    c1_rows: float | np.ndarray = c1
    c1_table: list[tuple[float, float]] = []
    if opt.c1_by_speed:
        if moving.all():
            raise BadInput(
                "c1_by_speed needs the spindle to stand still in the log (C1 at standstill)",
                file=log.file, path="--option c1_by_speed",
            )
        c1, c1_table, c1_rows, report["c1_by_speed"] = problem.c1_by_speed(z, float(res.fun), dt)
        for speed_rpm, tau_s in report["c1_by_speed"]["time_constant_s"].items():
            if report["c1_by_speed"]["at_edge"][speed_rpm]:
                at_bounds.append(f"C1 at {speed_rpm} rpm (time constant {tau_s:.4g} s) is at the edge of its"
                                 f" search range ({_grid_tau_s(dt)})")
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
    report["c2_exponent"] = (
        {"method": "linear", "reason": "asked: linear from 0 below the first level, held past the last"}
        if exponent is None else
        {"method": "power", "exponent": exponent, "reason": "C2(level)·(n/level)^e outside the fitted levels"})
    report["c2_at_unseen_speeds"] = unseen
    if not any(c > 1e-6 for _, c in table):  # 1 pm a step: nothing (the bounded solver leaves round-off)
        at_bounds.append("C2 is 0 at every speed: the spindle term predicts nothing (is the error bed − spindle?"
                         " name the bed sensors with --inputs)")
    report["at_bounds"] = at_bounds
    params = AR1Params(
        dt_s=dt,
        c1=c1,
        c2_table=table,
        c3_um_per_k=float(theta[L + nb]) if opt.ambient else None,
        exchange_um_per_k=[float(v) for v in theta[L + nb + bool(opt.ambient):]],
        c1_table=c1_table,
        c2_exponent=exponent,
        bed_gain_um_per_k=[float(v) for v in theta[L : L + nb]],
        spindle_sign=sign,
        t0_c=None,
        recursion_start="zero",
    )
    model = AR1(params, names, axis_names(targets))
    model.start(Xs[0], float(t[rows[0]]))
    resid = Es - model._response(Xs, model._c1_rows(Xs[:, 0]))
    resid = resid[np.isfinite(resid)]
    lags = max(1, min(10, resid.size // 5))
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


# The spindle's time constant τ = −Δτ / ln C1 is searched from two steps to a day: a rod that
# takes longer than a day to follow its heat is no spindle (the fit would be an integrator, the
# bed gains taking up what it cannot), one faster than two steps has no memory at this Δτ.
TAU_MIN_STEPS = 2.0
TAU_MAX_S = 86400.0
GRID_POINTS = 40


def c1_grid(dt_s: float) -> np.ndarray:
    """z = log(1 − C1) on a grid from τ = TAU_MIN_STEPS Δτ to max(TAU_MAX_S, 50 Δτ), even in z."""
    tau_lo, tau_hi = TAU_MIN_STEPS * dt_s, max(TAU_MAX_S, 50.0 * dt_s)
    return np.linspace(np.log(-np.expm1(-dt_s / tau_lo)), np.log(-np.expm1(-dt_s / tau_hi)), GRID_POINTS)


def _grid_tau_s(dt_s: float) -> str:
    """The time constants the C1 grid spans at Δτ, for a message."""
    grid = c1_grid(dt_s)
    lo, hi = (-dt_s / math.log(1.0 - math.exp(z)) for z in (grid.max(), grid.min()))
    return f"{lo:.3g} … {hi:.3g} s"


class _Problem:
    """For a given C1 (one, or one per step), the bounded linear least squares of the rest:
    C2 level increments δ ≥ 0 (C2 monotone in speed), bed gains, C3; on the simulated output."""

    def __init__(
        self, Xs: np.ndarray, Es: np.ndarray, speed: np.ndarray, rpm: list[float], n_bed: int, ambient: bool,
        sign: int, grid: np.ndarray, positive_bed: bool = False, exponent: float | None = None,
        n_exchange: int = 0,
    ) -> None:
        self.grid = grid
        L = len(rpm)
        x0 = Xs[0, 1:]
        # Interpolation weights of each step's speed on the level nodes (C2 linear in them).
        Wt = np.zeros((Xs.shape[0], L))
        for k, v in enumerate(speed):
            for j in range(L):
                e_j = np.zeros(L)
                e_j[j] = 1.0
                Wt[k, j] = c2_of_speed(v, rpm, list(e_j), 0.0, exponent)
        Wt[0] = 0.0  # ΔL(0) = 0 (paper 001, eq. 17): C2 enters from the second step on
        self.Wt, self.L, self.sign = Wt, L, sign
        # the recursion runs through every step; the least squares counts the measured ones
        self.ok = measured_rows(Es)
        self.Es = Es[self.ok]
        self.cum = np.tril(np.ones((L, L)))  # C2 levels = cumulative sum of increments δ ≥ 0
        self.bed_rise = Xs[:, 1 : 1 + n_bed] - x0[:n_bed]
        # the recursion's temperature inputs: the ambient (C3, any sign) then the exchange sensors (≥ 0:
        # a warmer housing warms the spindle), the last columns of Xs
        na = int(ambient) + n_exchange
        self.amb_rise = Xs[:, Xs.shape[1] - na:] - x0[x0.size - na:] if na else np.zeros((Xs.shape[0], 0))
        nb = self.bed_rise.shape[1]
        self.lb = np.r_[np.zeros(L), np.full(nb, 0.0 if positive_bed else -np.inf),
                        np.full(int(ambient), -np.inf), np.zeros(n_exchange)]
        self.ub = np.full(L + nb + na, np.inf)
        self.rpm = rpm

    def design(self, c1: float | np.ndarray) -> np.ndarray:
        L, sign = self.L, self.sign
        filt = ar_filter(c1, np.hstack([self.Wt @ self.cum, self.amb_rise]))
        return np.hstack([sign * filt[:, :L], self.bed_rise, sign * filt[:, L:]])

    def solve(self, c1: float | np.ndarray) -> tuple[float, np.ndarray]:
        """(sum of squared errors, [δ, bed gains, C3]) at this C1."""
        A = self.design(c1)[self.ok]
        r = optimize.lsq_linear(A, self.Es, bounds=(self.lb, self.ub), method="bvls")
        return float(np.sum((A @ r.x - self.Es) ** 2)), r.x

    def search_c1(self) -> tuple[float, int, Any]:
        """(z = log(1 − C1), grid index of the best start, the bounded search's result)."""
        grid = self.grid
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
        z_min, z_max = float(self.grid.min()), float(self.grid.max())

        def rows_c1(zs: np.ndarray) -> np.ndarray:
            b = -np.log1p(-np.exp(np.clip(zs, z_min, z_max)))
            return np.exp(-(w0 * b[0] + Wt @ b[1:]))

        res_n = optimize.minimize(
            lambda zs: self.solve(rows_c1(zs))[0], np.full(L + 1, z), method="Nelder-Mead",
            options={"xatol": 1e-5, "fatol": 1e-9 * max(cost, 1e-12), "maxiter": 400 * (L + 1)},
        )
        zs = np.clip(res_n.x, z_min, z_max)
        edge = np.isclose(zs, z_min, atol=1e-3) | np.isclose(zs, z_max, atol=1e-3)
        c1 = float(1.0 - np.exp(zs[0]))
        c1_table = [(r_, float(1.0 - np.exp(v))) for r_, v in zip(self.rpm, zs[1:], strict=True)]
        report = {
            "converged": bool(res_n.success), "single_c1": float(1.0 - np.exp(z)),
            "time_constant_s": {"0": -dt / math.log(c1), **{f"{r_:g}": -dt / math.log(c)
                                                           for r_, c in c1_table}},
            "at_edge": {"0": bool(edge[0]), **{f"{r_:g}": bool(e) for r_, e in zip(self.rpm, edge[1:], strict=True)}},
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
        return table, {**linear, "reason": "no rise_sensor named: C2 is linear in speed between the fitted levels (c2_exponent outside them)"}
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
        return table, {**linear, **info, "reason": f"{why} in the log: C2 is linear in speed between the fitted levels (c2_exponent outside them)"}
    ref = max(refs)  # the fastest fitted run: the largest rise, as the paper's 2000 rpm
    scaled, added = _scaled_table(table, {"ref_rpm": ref, "ref_rise_c": rises[ref], "rises_c": others})
    return scaled, {
        "method": "temperature_rise", **info, "ref_rpm": ref, **added,
        "reason": f"C2 at {', '.join(f'{n:g}' for n in others)} rpm = C2({ref:g} rpm) × the rise of "
        f"{opt.rise_sensor} there / at {ref:g} rpm (paper 001, eqs. 20–21)",
    }


def choices(result: FitResult) -> dict[str, Any]:
    """What this fit chose beyond its coefficients, as options that make a refit choose the same
    (compd.identify.lag holds them while it searches a lag): the C1 form."""
    form = result.report.get("c1_form")
    return {"c1_by_speed": form["chosen"] == "by_speed"} if form else {}
