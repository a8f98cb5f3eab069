"""Identification of the AR(1) spindle model: C1 search, bounded C2/bed/ambient least squares, Ljung–Box (paper 001)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy import optimize, signal, stats

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.identify import ar1_design as design
from compd.identify import holdout
from compd.identify import lag as lag_mod
from compd.identify.data import (
    FitResult,
    ambient_columns,
    axis_names,
    columns,
    default_targets,
    measured_rows,
    progress,
    require_rows,
    target_columns,
    validate_options,
)
from compd.log import Log, read_log
from compd.models.ar1 import AR1, AR1Params, SpeedLaw, c2_of_speed
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
        description="ambient sensor column (enables C3); auto = chosen held out among every temperature column"
        " with the structure and exchange sensors (a column named for the air, amb/room/air, is no structure"
        " sensor and only wins a tie), none if no column predicts the held-out folds clearly better; none (or"
        " null) = the paper's constant shop",
    )
    structure: list[str] | Literal["auto"] = Field(
        "auto",
        description="the structure (bed) sensors when --inputs names none: auto = chosen held out among every"
        " temperature column (at most 3); a list = these (what a refit of a chosen fit holds)",
    )
    speed_column: str = "speed_rpm"
    speed_round_rpm: float = Field(50.0, gt=0, description="speeds this close form one level")
    stopped_below_rpm: float = Field(1.0, ge=0, description="slower than this counts as stopped")
    spindle_sign: Literal[1, -1] | None = Field(None, description="none: −1 with bed inputs, else +1")
    c1_by_speed: bool | Literal["auto", "law"] = Field(
        "auto",
        description="true = C1 at standstill and at each logged speed (compd's form; needs stops in the log);"
        " law = C1 and C2 smooth functions of the speed fitted in one pass (compd's form for a log at many"
        " speeds: the model's speed_law); false = one C1 (the paper's); auto = compd's form (by level up to"
        " 4 levels, the law from 3) where it predicts the held-out folds at least 5 % better, else the paper's",
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
        " sit), entering the recursion with a gain ≥ 0 each (compd's form); auto = chosen held out among every"
        " temperature column with the structure sensors and the ambient (at most 2, each kept while it cuts the"
        " held-out RMSE by 5 %); none = the paper's recursion",
    )
    lag: Any = Field(
        "auto",
        description="the inputs' sensor lag: auto (chosen held out with the sensors; off where it does not help),"
        " off, seconds for every temperature input, or {input: seconds}",
    )
    bed_gains: Literal["positive", "free"] = Field(
        "positive",
        description="positive: the structure (bed) sensors' gains ≥ 0 in the lathe form (error = bed − spindle:"
        " the bed's growth adds, paper 001 eq. 15); free: any sign",
    )


AUTO_MARGIN = 0.95  # a sensor or compd's C1 form must cut the held-out RMSE by 5 % to be kept
STRUCTURE_MAX = 3  # structure (bed) sensors the automatic choice takes at most
EXCHANGE_MAX = 2  # exchange sensors the automatic choice takes at most
LEVELS_MAX = 4  # C1 per level is tried up to this many speed levels; beyond, the speed law (one pass)
LAW_MIN_LEVELS = 3  # the speed law is tried from this many speed levels (a spectrum)
SCREEN_POINTS = 30  # the selection screens its candidates on a C1 grid this coarse (a parabola between) ...
SCREEN_KEEP = 4  # ... and scores this many of the best on its fine grid (design.SCAN_POINTS) before it takes one


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """The AR(1) model. The sensors the options leave to the fit (`ambient: auto`, `exchange: auto`, the
    structure sensors when --inputs names none) and the inputs' lead (`lag: auto`) are chosen together
    by held-out error among every temperature column at every lag of compd.identify.lag's grid
    (`choose_sensors`), then the C1 form (`c1_by_speed: auto`) the same way, both on the log's columns
    prepared once (compd.identify.ar1_design); then the fit of what was chosen on the led log."""
    opt = validate_options("ar1", Options, options)
    if isinstance(opt.structure, list):
        if inputs:
            raise BadInput(
                "give the structure sensors with --inputs or the structure option, not both", path="--option structure"
            )
        inputs = list(opt.structure)
    temps = log.temperature_columns()
    spec = lag_mod.parse(opt.lag, temps)
    lags = {} if isinstance(spec, str) else {n: spec.get(n, spec.get("*", 0.0)) for n in temps}
    need_bed = not inputs and opt.spindle_sign != 1
    chosen: dict[str, Any] | None = None
    lag_report: dict[str, Any] = {"method": "off"} if spec == "off" else {}
    if need_bed or opt.ambient == "auto" or opt.exchange == "auto" or spec == "auto":
        inputs, opt, chosen = choose_sensors(log, list(inputs or []), targets, opt, need_bed, lags, spec == "auto")
        if spec == "auto":
            lags, lag_report = chosen.pop("lags"), chosen.pop("lag")
    elif opt.ambient == "none":
        opt = opt.model_copy(update={"ambient": None})
    names = [
        *(inputs or []),
        *([opt.ambient] if opt.ambient else []),
        *([] if isinstance(opt.exchange, str) else opt.exchange),
    ]
    step = lag_mod.step_s(log)
    lead, filt = lag_mod.lead_lists(names, lags, step)
    result = _fit_form(lag_mod.led(log, names, lead, filt), inputs, targets, opt)
    lead, filt = lag_mod.lead_lists(result.model.inputs, lags, step)
    result = lag_mod.with_lead(result, lead, filt)
    if isinstance(spec, dict):
        lag_report = {
            "method": "given",
            "lead_s": {n: v for n, v in zip(result.model.inputs, lead, strict=True) if v > 0},
        }
    result.report["lag"] = lag_report
    if chosen is not None:
        result.report["sensors_chosen"] = chosen
        if need_bed:
            result.report["inputs_chosen"] = {"inputs": list(inputs or []), "method": chosen["method"]}
    result.report["at_bounds"] = result.report.get("at_bounds", []) + pinned_inputs(result, opt, chosen)
    return result


def pinned_inputs(result: FitResult, opt: Options, chosen: dict[str, Any] | None) -> list[str]:
    """A named input the fit pinned at its bound (0): a structure gain (`bed_gains: positive`) or an
    exchange gain. The sensor was named but contributes nothing: say which, and what to do."""
    p = result.model.params
    given = set((chosen or {}).get("given", result.report.get("fit_inputs", [])))
    out = []
    bed = result.report.get("fit_inputs", [])
    if opt.bed_gains == "positive" and p.spindle_sign == -1:
        for name, gain in zip(bed, p.bed_gain_um_per_k, strict=False):
            if gain <= PINNED_UM_PER_K:
                how = "named with --inputs" if name in given else "chosen held out"
                out.append(
                    f"the structure sensor {name} ({how}) has gain 0, its bound (bed_gains: positive): it"
                    " contributes nothing; drop it from --inputs, check that the error is bed − spindle"
                    " (a bed that grows away from the tool), or allow either sign with --option bed_gains=free"
                )
    exch = [] if isinstance(opt.exchange, str) else list(opt.exchange)
    for name, gain in zip(exch, p.exchange_um_per_k, strict=False):
        if gain <= PINNED_UM_PER_K:
            out.append(
                f"the exchange sensor {name} has gain 0, its bound (a warmer housing warms the spindle):"
                " it contributes nothing; drop it from --option exchange (or let exchange=auto choose)"
            )
    return out


PINNED_UM_PER_K = 1e-9  # a bounded gain this small is at its bound (the solver leaves round-off)


SELECT_LAGS_S = (0.0, 30.0, 120.0, 480.0)  # the lags (of compd.identify.lag's grid) the selection tries


def _lagged(name: str, tau_s: float) -> str:
    """A candidate column: the sensor `name` led by τ (compd.identify.lag), the name itself for none."""
    return name if tau_s <= 0 else f"{name}@{tau_s:g}s"


def choose_sensors(
    log: Log,
    bed: list[str],
    targets: list[str] | None,
    opt: Options,
    need_bed: bool,
    lags: dict[str, float],
    auto_lag: bool,
) -> tuple[list[str], Options, dict[str, Any]]:
    """The structure, ambient and exchange sensors the options leave to the fit (and with `auto_lag`
    each input's lead), by forward selection among every temperature column (none privileged by its
    name): each step tries every column not yet used, at every lag of compd.identify.lag's grid
    (`auto_lag`; else at its lag in `lags`), in every role still open (a structure sensor while fewer
    than STRUCTURE_MAX, the ambient while none, an exchange sensor while fewer than EXCHANGE_MAX) and
    takes the one whose AR(1) predicts the held-out folds (compd.identify.holdout) best, kept while it
    beats the set before clearly (AUTO_MARGIN); a first structure sensor is always taken where one is
    needed. A column named for the air (amb, room, air) is no structure sensor and wins a tie (within
    holdout.FLOOR_UM) as the ambient, nothing more. With `auto_lag` the chosen inputs' lags are then
    refined one input at a time (the others held), and kept only where they beat no lead clearly
    (compd.identify.lag.MARGIN), as compd.identify.lag does for the other kinds. Every candidate is
    scored on the log's columns prepared once (compd.identify.ar1_design: every column filtered once
    per C1 of a grid, the folds' Gram blocks shared), at the paper's single C1. Returns (structure
    sensors, the options with the ambient and exchange set, the report; with `auto_lag` its `lags`
    {input: τ} and `lag` report)."""
    target = default_targets(log, targets)
    if len(target) != 1:
        raise BadInput(f"ar1 fits one axis at a time; targets: {', '.join(target)}", path="--target")
    temps = log.temperature_columns()
    fixed_amb = opt.ambient if opt.ambient not in ("auto", "none", None) else None
    fixed_exch = tuple(opt.exchange) if isinstance(opt.exchange, list) else ()
    given = [*bed, *([fixed_amb] if fixed_amb else []), *fixed_exch]
    for name in given:
        if name not in log.columns:
            raise BadInput("no such column in the log", file=log.file, path=name)
    dt = opt.dt_s if opt.dt_s is not None else _median_step_s(log)
    rows = step_rows(log.t_s, dt)
    usable = [c for c in temps if c in given or bool(np.isfinite(log.col(c)[rows]).all())]
    usable += [c for c in given if c not in usable]
    air = set(ambient_columns(log))
    if need_bed and not [c for c in usable if c not in given and c not in air]:
        raise BadInput(
            "ar1 needs a bed (structure) sensor whose growth adds to the spindle's, and the log has no"
            " temperature column to choose: name it with --inputs (a spindle alone: --option spindle_sign=1)",
            file=log.file,
            path="--inputs",
        )
    grid = SELECT_LAGS_S if auto_lag else (0.0,)
    step = lag_mod.step_s(log)
    cols, data = [], []
    for tau in grid:
        if auto_lag:
            lead, filt = lag_mod.lead_lists(usable, dict.fromkeys(usable, tau), step)
        else:
            lead, filt = lag_mod.lead_lists(usable, lags, step)
        X = lag_mod.led(log, usable, lead, filt).matrix(usable)
        for j, c in enumerate(usable):
            cols.append(_lagged(c, tau if auto_lag else lags.get(c, 0.0)))
            data.append(X[:, j])
    keep = [k for k, c in enumerate(log.columns) if c not in cols]
    ext = Log(log.file, [log.columns[k] for k in keep] + cols, np.column_stack([log.data[:, keep], *data]))
    base = dict(zip(cols, [c for _ in grid for c in usable], strict=True))
    exponent = None if opt.c2_exponent == "linear" else float(opt.c2_exponent)
    cut = holdout.folds(log)[0]
    steps = design.prepare(
        ext, target[0], cols, opt.speed_column, dt, opt.speed_round_rpm, opt.stopped_below_rpm, exponent, cut
    )
    if not steps.levels:
        raise BadInput(f"the spindle never turns in {opt.speed_column!r}: C2 cannot be fitted", file=log.file)
    # each candidate scored at the paper's single C1 (a grid, a parabola between), as main's selection
    # scored it: scored at the speed law's C1 too (the better of the two), the held-out RMSE of the
    # family's lathes fell by half but their unseen days (other speeds, another shop) got worse
    fine = 1.0 - np.exp(design.c1_grid(dt, design.SCAN_POINTS))
    coarse = design.Scan(steps, 1.0 - np.exp(design.c1_grid(dt, SCREEN_POINTS)))
    sign = opt.spindle_sign if opt.spindle_sign is not None else (-1 if bed or need_bed else 1)
    positive = opt.bed_gains == "positive" and sign == -1
    auto_amb, auto_exch = opt.ambient == "auto", opt.exchange == "auto"

    def scored(scan: design.Scan, many: list[design.Roles]) -> np.ndarray:
        out = np.full(len(many), math.inf)
        for i, scores in enumerate(design.score_quick(scan, many)):
            if not any(isinstance(f, str) for f in scores):  # a fold that cannot be fitted: inf
                out[i] = float(holdout.pooled_rmse(scores, 1)[0])
        return out

    def held(many: list[design.Roles], also: Sequence[int] = ()) -> list[float]:
        """Each candidate's held-out RMSE on the fine grid; more than SCREEN_KEEP are screened on the
        coarse grid first, the SCREEN_KEEP best (and `also`) scored on the fine one, then any whose
        coarse figure still beats the best fine one, until the best is a fine figure (the others keep
        their coarse one)."""
        if len(many) <= SCREEN_KEEP:
            return [float(v) for v in fine_scores(many)]
        out = scored(coarse, many)
        fine_done = np.zeros(len(many), dtype=bool)
        again = sorted(set(np.argsort(out, kind="stable")[:SCREEN_KEEP].tolist()) | set(also))
        while again:
            out[again] = fine_scores([many[i] for i in again])
            fine_done[again] = True
            best = float(out[fine_done].min())
            beat = np.flatnonzero(~fine_done & (out < best))
            again = beat[np.argsort(out[beat], kind="stable")][:SCREEN_KEEP].tolist()
        return [float(v) for v in out]

    fine_scan: list[design.Scan] = []

    def fine_scores(many: list[design.Roles]) -> np.ndarray:
        if not fine_scan:
            fine_scan.append(design.Scan(steps, fine))
        return scored(fine_scan[0], many)

    def at(roles: design.Roles, tau: dict[str, float]) -> design.Roles:
        """The roles with each sensor at its lag in `tau` (0 where none)."""

        def m(c: str) -> str:
            b = base.get(c, c)
            return _lagged(b, tau.get(b, 0.0))

        return replace(
            roles,
            bed=tuple(map(m, roles.bed)),
            ambient=m(roles.ambient) if roles.ambient else None,
            exchange=tuple(map(m, roles.exchange)),
        )

    start = design.Roles(tuple(bed), fixed_amb, fixed_exch, sign, positive)
    history: list[dict[str, float]] = []
    if given and auto_lag:  # the named sensors' one lag, the others' chosen with them
        tried = {
            f"{tau:g}": s
            for tau, s in zip(grid, held([at(start, dict.fromkeys(given, tau)) for tau in grid]), strict=True)
        }
        history.append({f"lag {k} s": v for k, v in tried.items()})
        tau0 = float(min(tried, key=tried.__getitem__))
        current, best = at(start, dict.fromkeys(given, tau0)), min(tried.values())
    else:
        current = at(start, lags)
        best = math.inf if need_bed else held([current])[0]
        if not need_bed:
            history.append({"": best})
    if need_bed:
        best = math.inf  # the first structure sensor is taken whatever it scores
    while True:
        used = {base[c] for c in current.sensors}
        free = [c for c in cols if base[c] not in used]
        moves: list[tuple[str, design.Roles]] = []
        for c in free:
            if need_bed and len(current.bed) < STRUCTURE_MAX and base[c] not in air:  # the air is no structure
                moves.append((f"structure {c}", replace(current, bed=(*current.bed, c))))
            if current.bed or not need_bed:
                if auto_amb and current.ambient is None:
                    moves.append((f"ambient {c}", replace(current, ambient=c)))
                if auto_exch and len(current.exchange) < EXCHANGE_MAX:
                    moves.append((f"exchange {c}", replace(current, exchange=(*current.exchange, c))))
        if not moves:
            break
        scores = held(
            [r for _, r in moves],
            [
                j
                for j, (name, r) in enumerate(moves)  # the air, for its tie
                if name.startswith("ambient ") and base[r.ambient or ""] in air
            ],
        )
        history.append({name: s for (name, _), s in zip(moves, scores, strict=True)})
        i = int(np.argmin(scores))
        for j, (name, roles) in enumerate(moves):  # the air's name breaks a tie for the ambient
            if (
                name.startswith("ambient ")
                and base[roles.ambient or ""] in air
                and scores[j] - scores[i] <= holdout.FLOOR_UM
                and not moves[i][0].startswith("ambient ")
            ):
                i = j
                break
        if math.isinf(scores[i]) or not math.isinf(best) and not holdout.clearly_better(scores[i], best, AUTO_MARGIN):
            break
        current, best = moves[i][1], scores[i]
    if need_bed and not current.bed:
        raise BadInput(
            "no structure sensor can be fitted held out: name them with --inputs", file=log.file, path="--inputs"
        )
    chosen_lags = {base[c]: _lag_of(c, base[c]) for c in current.sensors}
    report_lag: dict[str, Any] = {}
    if auto_lag:
        per_input: dict[str, dict[str, float]] = {}
        for name in list(chosen_lags):  # each input's own lag, the others held
            others = [tau for tau in grid if tau != chosen_lags[name]]
            trial = held([at(current, {**chosen_lags, name: tau}) for tau in others])
            per_input[name] = {f"{tau:g}": s for tau, s in zip(others, trial, strict=True)}
            k = int(np.argmin(trial))
            if trial[k] < best:
                best, chosen_lags = trial[k], {**chosen_lags, name: others[k]}
                current = at(current, chosen_lags)
        none = held([at(current, {})])[0]
        kept = any(v > 0 for v in chosen_lags.values()) and holdout.clearly_better(best, none, lag_mod.MARGIN)
        report_lag = {
            "method": holdout.METHOD + f"; chosen with the sensors (each candidate column at every lag of"
            f" {list(grid)} s), then each input's own with the others held, τ_f = {lag_mod.FILTER_RATIO:g} τ (≥ 2 log"
            f" steps); kept below {lag_mod.MARGIN:g} × the held-out RMSE without",
            "held_out_rmse_um": {"none": none, "chosen": best},
            "per_input_rmse_um": per_input,
            "kept": kept,
        }
        if not kept:
            report_lag["reason"] = "no lead predicts the held-out folds clearly better than the readings as they are"
            chosen_lags = {}
        else:
            lead, filt = lag_mod.lead_lists(list(chosen_lags), chosen_lags, step)
            report_lag["lead_s"] = {n: v for n, v in chosen_lags.items() if v > 0}
            report_lag["lead_filter_s"] = {n: f for n, f in zip(chosen_lags, filt, strict=True) if f > 0}
            top = [n for n, v in chosen_lags.items() if v >= grid[-1]]
            if top:
                report_lag["at_bounds"] = [f"the lag of {', '.join(top)} is the longest tried ({grid[-1]:g} s)"]
    bed_out = [base[c] for c in current.bed]
    amb_out = base[current.ambient] if current.ambient else None
    exch_out = [base[c] for c in current.exchange]
    update: dict[str, Any] = {"ambient": amb_out}
    if auto_exch:
        update["exchange"] = exch_out
    report: dict[str, Any] = {
        "inputs": bed_out,
        "ambient": amb_out,
        "exchange": exch_out,
        "given": given,
        "method": holdout.METHOD
        + "; forward selection among every temperature column"
        + (" at every lag" if auto_lag else "")
        + ", each step the column and role (structure ≤"
        f" {STRUCTURE_MAX}, ambient ≤ 1, exchange ≤ {EXCHANGE_MAX}: those the options leave to the fit) that"
        f" predicts best, kept while it cuts the held-out RMSE below {AUTO_MARGIN:g} ×; a column named for the"
        f" air is no structure sensor and wins a tie as the ambient; scored at the paper's single C1 on a grid of"
        f" {design.SCAN_POINTS} (a parabola between); where a step has more than {SCREEN_KEEP} candidates, each is"
        f" screened on a grid of {SCREEN_POINTS} first and the best on the fine one until the best is a fine figure"
        " (the history's figure for the others is the screen's)",
        "held_out_rmse_um": history,
    }
    if auto_lag:
        report["lags"] = {n: v for n, v in chosen_lags.items() if v > 0}
        report["lag"] = report_lag
    return bed_out, opt.model_copy(update=update), report


def _lag_of(column: str, name: str) -> float:
    """The lag (s) of a candidate column (`_lagged`)."""
    return 0.0 if column == name else float(column[len(name) + 1 : -1])


def _fit_form(log: Log, inputs: list[str] | None, targets: list[str] | None, opt: Options) -> FitResult:
    """The AR(1) fit of `opt`'s C1 form; `auto`: the paper's single C1 unless compd's form (C1 per
    speed level with few levels, the speed law on a spectrum) predicts the held-out folds clearly
    better, every form scored on the log's columns prepared once (compd.identify.ar1_design)."""
    if opt.c1_by_speed != "auto":
        return _fit(log, inputs, targets, opt)
    bed = list(inputs or [])
    exchange = [] if isinstance(opt.exchange, str) else list(opt.exchange)
    target = default_targets(log, targets)
    if len(target) != 1:
        raise BadInput(f"ar1 fits one axis at a time; targets: {', '.join(target)}", path="--target")
    dt = opt.dt_s if opt.dt_s is not None else _median_step_s(log)
    exponent = None if opt.c2_exponent == "linear" else float(opt.c2_exponent)
    paper = opt.model_copy(update={"c1_by_speed": False})
    result = _fit(log, inputs, targets, paper)
    sensors = [*bed, *([opt.ambient] if opt.ambient else []), *exchange]
    cut = holdout.folds(log)[0]
    sign = result.model.params.spindle_sign
    roles = design.Roles(tuple(bed), opt.ambient, tuple(exchange), sign, opt.bed_gains == "positive" and sign == -1)
    steps = design.prepare(
        log, target[0], sensors, opt.speed_column, dt, opt.speed_round_rpm, opt.stopped_below_rpm, exponent, cut
    )
    stops = bool((steps.speed < max(opt.stopped_below_rpm, 1e-12)).any())
    const, zs = design.score_exact(steps, roles)
    forms: dict[str, list[design.FoldScore]] = {"constant": const}
    if stops and 1 <= len(steps.levels) <= LEVELS_MAX:
        forms["by_speed"] = design.fold_scores(design.fit_levels(steps, roles, zs), steps)
    if stops and len(steps.levels) >= LAW_MIN_LEVELS:
        law_steps = design.prepare(
            log,
            target[0],
            sensors,
            opt.speed_column,
            dt,
            opt.speed_round_rpm,
            opt.stopped_below_rpm,
            exponent,
            cut,
            law=True,
        )
        forms["speed_law"] = design.fold_scores(design.fit_law(law_steps, roles, exact=False), law_steps)
    usable = [k for k in range(len(cut)) if all(not isinstance(f[k], str) for f in forms.values())]
    held: dict[str, float | str] = {}
    for name, f in forms.items():
        used = [f[k] for k in usable]
        count = sum(int(c[0]) for _, c in used)  # type: ignore[misc]
        held[name] = (
            math.sqrt(sum(float(s[0]) for s, _ in used) / count)
            if count  # type: ignore[misc]
            else "; ".join(x for x in f if isinstance(x, str)) or "no held-out rows"
        )
    chosen = "constant"
    for name in ("by_speed", "speed_law"):
        if (
            name in held
            and isinstance(held[name], float)
            and isinstance(held[chosen], float)
            and holdout.clearly_better(float(held[name]), float(held[chosen]), AUTO_MARGIN)
        ):
            chosen = name
    if chosen != "constant":
        result = _fit(log, inputs, targets, opt.model_copy(update={"c1_by_speed": chosen == "by_speed" or "law"}))
    result.report["c1_form"] = {
        "chosen": chosen,
        "method": holdout.METHOD + f"; compd's form (C1 by speed up to {LEVELS_MAX} levels, the speed law from"
        f" {LAW_MIN_LEVELS}) is kept only below {AUTO_MARGIN:g} × the paper's (or the other's) RMSE",
        "held_out_blocks": [k + 1 for k in usable],
        "held_out_rmse_um": held,
    }
    if chosen != "by_speed" and all(not isinstance(f, str) for f in forms[chosen]):
        # the paper's form and the speed law on every fold: what a refit per fold (compd.commissioning.fitting's
        # comparison) scores, to the solver's tolerance: kept, not redone (C1 per level searches on its own)
        result.report["c1_form"]["held_out_folds"] = [[float(s[0]), int(c[0])] for s, c in forms[chosen]]  # type: ignore[misc]
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
    if opt.c1_by_speed == "law":
        return _fit_law(log, bed, targets, opt, names, Xs, Es, dt, sign, positive, exponent)
    problem = _Problem(
        Xs, Es, speed, rpm, len(bed), bool(opt.ambient), sign, c1_grid(dt), positive, exponent, len(exchange)
    )
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
        at_bounds.append(
            f"C1 {c1:.6g} (time constant {-dt / math.log(c1):.4g} s) is at the edge of its search"
            f" range ({_grid_tau_s(dt)}): the spindle term may stand in for something else"
        )
    c1_rows: float | np.ndarray = c1
    c1_table: list[tuple[float, float]] = []
    if opt.c1_by_speed:
        if moving.all():
            raise BadInput(
                "c1_by_speed needs the spindle to stand still in the log (C1 at standstill)",
                file=log.file,
                path="--option c1_by_speed",
            )
        c1, c1_table, c1_rows, report["c1_by_speed"] = problem.c1_by_speed(z, float(res.fun), dt)
        for speed_rpm, tau_s in report["c1_by_speed"]["time_constant_s"].items():
            if report["c1_by_speed"]["at_edge"][speed_rpm]:
                at_bounds.append(
                    f"C1 at {speed_rpm} rpm (time constant {tau_s:.4g} s) is at the edge of its"
                    f" search range ({_grid_tau_s(dt)})"
                )
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
        if exponent is None
        else {"method": "power", "exponent": exponent, "reason": "C2(level)·(n/level)^e outside the fitted levels"}
    )
    report["c2_at_unseen_speeds"] = unseen
    if not any(c > 1e-6 for _, c in table):  # 1 pm a step: nothing (the bounded solver leaves round-off)
        at_bounds.append(
            "C2 is 0 at every speed: the spindle term predicts nothing (is the error bed − spindle?"
            " name the bed sensors with --inputs)"
        )
    report["at_bounds"] = at_bounds
    params = AR1Params(
        dt_s=dt,
        c1=c1,
        c2_table=table,
        c3_um_per_k=float(theta[L + nb]) if opt.ambient else None,
        exchange_um_per_k=[float(v) for v in theta[L + nb + bool(opt.ambient) :]],
        c1_table=c1_table,
        c2_exponent=exponent,
        bed_gain_um_per_k=[float(v) for v in theta[L : L + nb]],
        spindle_sign=sign,
        t0_c=None,
        recursion_start="zero",
    )
    return _finish(AR1(params, names, axis_names(targets)), Xs, Es, float(t[rows[0]]), report)


def _finish(model: AR1, Xs: np.ndarray, Es: np.ndarray, t0_s: float, report: dict[str, Any]) -> FitResult:
    """The fitted model's residual at the steps: Ljung–Box and the step RMSE in the report."""
    model.start(Xs[0], t0_s)
    resid = Es - model._response(Xs, model._c1_rows(Xs[:, 0]))
    resid = resid[np.isfinite(resid)]
    lags = max(1, min(10, resid.size // 5))
    qstat, pval = ljung_box(resid, lags)
    report["ljung_box"] = {"lags": lags, "q": qstat, "p_value": pval, "white_at_5pct": pval > 0.05}
    report["step_rmse_um"] = float(np.sqrt(np.mean(resid**2)))
    model.x0 = None  # the run-time reference is the reading at start
    return FitResult(model, report)


def _fit_law(
    log: Log,
    bed: list[str],
    targets: list[str],
    opt: Options,
    names: list[str],
    Xs: np.ndarray,
    Es: np.ndarray,
    dt: float,
    sign: int,
    positive: bool,
    exponent: float | None,
) -> FitResult:
    """compd's form for a log at many speeds: C1 and C2 smooth functions of the speed (the model's
    `speed_law`), fitted in one pass: the cooling rate b(n) = b0 (1 + (ρ − 1) n/n_ref) (the convection
    grows with speed) and C2(n) = a n/n_ref + q (n/n_ref)² (a, q ≥ 0: the heat input), n_ref the fastest
    level; (b0, ρ) the best of a grid then Nelder–Mead, the rest a bounded least squares at each
    (compd.identify.ar1_design.fit_law)."""
    if not (Xs[:, 0] < max(opt.stopped_below_rpm, 1e-12)).any():
        raise BadInput(
            "c1_by_speed: law needs the spindle to stand still in the log (C1 at standstill)",
            file=log.file,
            path="--option c1_by_speed",
        )
    if opt.c2_rise or opt.rise_sensor:
        raise BadInput(
            "c1_by_speed: law fits C2 as a function of speed: c2_rise and rise_sensor do not apply", path="--option"
        )
    amb = opt.ambient or None
    exchange = [] if isinstance(opt.exchange, str) else list(opt.exchange)
    sensors = [*bed, *([amb] if amb else []), *exchange]
    steps = design.prepare(
        log,
        targets[0],
        sensors,
        opt.speed_column,
        dt,
        opt.speed_round_rpm,
        opt.stopped_below_rpm,
        exponent,
        None,
        law=True,
    )
    roles = design.Roles(tuple(bed), amb, tuple(exchange), sign, positive)
    fitted = design.fit_law(steps, roles, folds=False, exact=True)[0]
    if isinstance(fitted, str):
        raise BadInput(f"ar1 speed law: {fitted}", file=log.file)
    law = design.LawC1(steps)
    phi = fitted.phi
    b0 = float(design.b_of_z(min(max(float(phi[0]), law.z_lo), law.z_hi)))
    ratio = math.exp(min(max(float(phi[1]), 0.0), law.gamma_max))
    theta = fitted.fit.theta
    nb, na = len(bed), int(amb is not None)
    ref = steps.levels[-1]
    speed_law = SpeedLaw(
        ref_rpm=ref, c2_um=float(theta[0]), c2_quad_um=float(theta[1]), rate_per_s=b0 * (ratio - 1.0) / dt
    )
    params = AR1Params(
        dt_s=dt,
        c1=math.exp(-b0),
        c2_table=[],
        speed_law=speed_law,
        c3_um_per_k=float(theta[2 + nb]) if amb else None,
        exchange_um_per_k=[float(v) for v in theta[2 + nb + na :]],
        bed_gain_um_per_k=[float(v) for v in theta[2 : 2 + nb]],
        spindle_sign=sign,
        t0_c=None,
        recursion_start="zero",
    )
    at_bounds = []
    if b0 * ratio >= law.b_hi * (1 - 1e-6) or b0 <= law.b_lo * (1 + 1e-6):
        at_bounds.append(
            f"the speed law's time constant ({dt / b0:.4g} s at rest, {dt / (b0 * ratio):.4g} s at"
            f" {ref:g} rpm) is at the edge of its range ({_grid_tau_s(dt)})"
        )
    if theta[0] + theta[1] <= 1e-6:
        at_bounds.append(
            "C2 is 0 at every speed: the spindle term predicts nothing (is the error bed − spindle?"
            " name the bed sensors with --inputs)"
        )
    report: dict[str, Any] = {
        "fit_inputs": bed,
        "dt_s": dt,
        "step_rows": int(steps.rows.size),
        "speed_levels_rpm": steps.levels,
        "converged": fitted.converged,
        "speed_law": {
            "time_constant_s": {"0": dt / b0, f"{ref:g}": dt / (b0 * ratio)},
            "cooling_ratio": ratio,
            "c2_um_at_ref": float(theta[0] + theta[1]),
        },
        "at_bounds": at_bounds,
    }
    return _finish(AR1(params, names, axis_names(targets)), Xs, Es, float(log.t_s[steps.rows[0]]), report)


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
        self,
        Xs: np.ndarray,
        Es: np.ndarray,
        speed: np.ndarray,
        rpm: list[float],
        n_bed: int,
        ambient: bool,
        sign: int,
        grid: np.ndarray,
        positive_bed: bool = False,
        exponent: float | None = None,
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
        self.amb_rise = Xs[:, Xs.shape[1] - na :] - x0[x0.size - na :] if na else np.zeros((Xs.shape[0], 0))
        nb = self.bed_rise.shape[1]
        self.lb = np.r_[
            np.zeros(L),
            np.full(nb, 0.0 if positive_bed else -np.inf),
            np.full(int(ambient), -np.inf),
            np.zeros(n_exchange),
        ]
        self.ub = np.full(L + nb + na, np.inf)
        self.rpm = rpm
        self._last: np.ndarray | None = None

    def design(self, c1: float | np.ndarray) -> np.ndarray:
        L, sign = self.L, self.sign
        filt = ar_filter(c1, np.hstack([self.Wt @ self.cum, self.amb_rise]))
        return np.hstack([sign * filt[:, :L], self.bed_rise, sign * filt[:, L:]])

    def solve(self, c1: float | np.ndarray) -> tuple[float, np.ndarray]:
        """(sum of squared errors, [δ, bed gains, C3]) at this C1."""
        A = self.design(c1)[self.ok]
        # the bounded least squares on the Gram (Lawson–Hanson from the last solve's active set:
        # compd.identify.ar1_design.bounded_lstsq), a few small solves instead of BVLS on the rows
        x = design.bounded_lstsq(A.T @ A, A.T @ self.Es, self.lb == 0.0, self._last)
        self._last = x
        return float(np.sum((A @ x - self.Es) ** 2)), x

    def search_c1(self) -> tuple[float, int, Any]:
        """(z = log(1 − C1), grid index of the best start, the bounded search's result)."""
        grid = self.grid
        costs = [self.solve(1.0 - np.exp(z))[0] for z in progress(grid, desc="ar1 C1 search")]
        i = int(np.argmin(costs))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = optimize.minimize_scalar(
            lambda z: self.solve(1.0 - np.exp(z))[0],
            bounds=(min(lo, hi), max(lo, hi)),
            method="bounded",
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
            lambda zs: self.solve(rows_c1(zs))[0],
            np.full(L + 1, z),
            method="Nelder-Mead",
            options={"xatol": 1e-5, "fatol": 1e-9 * max(cost, 1e-12), "maxiter": 400 * (L + 1)},
        )
        zs = np.clip(res_n.x, z_min, z_max)
        edge = np.isclose(zs, z_min, atol=1e-3) | np.isclose(zs, z_max, atol=1e-3)
        c1 = float(1.0 - np.exp(zs[0]))
        c1_table = [(r_, float(1.0 - np.exp(v))) for r_, v in zip(self.rpm, zs[1:], strict=True)]
        report = {
            "converged": bool(res_n.success),
            "single_c1": float(1.0 - np.exp(z)),
            "time_constant_s": {"0": -dt / math.log(c1), **{f"{r_:g}": -dt / math.log(c) for r_, c in c1_table}},
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
        return table, {
            **linear,
            "reason": "no rise_sensor named: C2 is linear in speed between the fitted levels (c2_exponent outside"
            " them)",
        }
    rises: dict[float, float] = {}
    sources = [log]
    if opt.rise_log is not None:
        sources.append(read_log(opt.rise_log, allow_nan=True))
    for src in sources:
        X = columns(src, [opt.speed_column, opt.rise_sensor])
        for n, r in run_rises_c(
            src.t_s, X[:, 0], X[:, 1], opt.rise_window_s, opt.speed_round_rpm, opt.stopped_below_rpm
        ).items():
            if not any(abs(n - m) <= opt.speed_round_rpm for m in rises):
                rises[n] = r
    info: dict[str, Any] = {
        "rise_sensor": opt.rise_sensor,
        "rise_window_s": opt.rise_window_s,
        "rises_c": {f"{n:g}": r for n, r in rises.items()},
    }

    def near_level(n: float) -> bool:
        return any(abs(n - m) <= opt.speed_round_rpm for m, _ in table)

    refs = [n for n in rises if near_level(n) and rises[n] > 0]
    others = {n: r for n, r in rises.items() if not near_level(n)}
    if not refs or not others:
        why = (
            f"no run of {opt.rise_window_s:g} s from standstill at a fitted speed"
            if not refs
            else f"no run of {opt.rise_window_s:g} s from standstill at a speed without a fitted C2"
        )
        return table, {
            **linear,
            **info,
            "reason": f"{why} in the log: C2 is linear in speed between the fitted levels (c2_exponent outside them)",
        }
    ref = max(refs)  # the fastest fitted run: the largest rise, as the paper's 2000 rpm
    scaled, added = _scaled_table(table, {"ref_rpm": ref, "ref_rise_c": rises[ref], "rises_c": others})
    return scaled, {
        "method": "temperature_rise",
        **info,
        "ref_rpm": ref,
        **added,
        "reason": f"C2 at {', '.join(f'{n:g}' for n in others)} rpm = C2({ref:g} rpm) × the rise of "
        f"{opt.rise_sensor} there / at {ref:g} rpm (paper 001, eqs. 20–21)",
    }


def choices(result: FitResult) -> dict[str, Any]:
    """What this fit chose beyond its coefficients, as options that make a refit choose the same
    (compd.identify.lag holds them while it searches a lag): the C1 form and the sensors it chose."""
    out: dict[str, Any] = {}
    form = result.report.get("c1_form")
    if form:
        out["c1_by_speed"] = {"by_speed": True, "speed_law": "law"}.get(form["chosen"], False)
    chosen = result.report.get("sensors_chosen")
    if chosen:
        if "inputs_chosen" in result.report:
            out["structure"] = list(chosen["inputs"])
        out["ambient"] = chosen["ambient"] or "none"
        out["exchange"] = list(chosen["exchange"]) or "none"
    return out
