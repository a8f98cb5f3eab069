"""Identifying the inputs' sensor lag: the lead of compd.models.lead, chosen by held-out error.

The lead is off where it does not help.

A sensor that lags its structure by τ makes every model late by about τ after a change
of duty. The lag is not in the papers' models, and the log does not say it directly, so
it is chosen the way an unseen day would judge it (compd.identify.holdout):

1. the kind is fitted on the log as it is; what that fit chose beyond its coefficients
   (the feed axis's form, AR(1)'s C1 form, LVR's components: each kind's `choices`) is
   held fixed while the lag is searched, so a lag is compared with a lag, not with
   another form;
2. one lag τ for all the model's temperature inputs, from LAG_GRID_S, each with its
   low-pass τ_f = τ·FILTER_RATIO (at least two of the log's steps): every candidate's
   model is fitted on the log with its inputs led and scored held out;
3. with few temperature inputs (≤ PER_INPUT_MAX), one pass over the inputs tries each
   one's own τ from the grid with the others held (an ambient sensor in air hardly lags,
   a sensor deep in a casting lags minutes);
4. the lead is kept only where it beats no lead clearly (holdout.clearly_better with
   MARGIN): a lead that does not help is noise, so it stays off;
5. the kind is fitted once more on the led log, with the choices of step 1 (its report
   says how they were made).

The model file carries the lead per input (`lead_s`, `lead_filter_s`), the report every
candidate's held-out RMSE (`lag`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from compd.core.errors import BadInput
from compd.identify import holdout
from compd.identify.data import FitResult, default_targets
from compd.log import Log
from compd.models.lead import InputLead

LAG_GRID_S = (0.0, 15.0, 30.0, 60.0, 120.0, 240.0, 480.0)
FILTER_RATIO = 0.2  # τ_f = 0.2 τ: the led input keeps a lag of 0.4 τ, its noise gain stays near 2.5
PER_INPUT_MAX = 4
MARGIN = 0.97  # a lead must cut the held-out RMSE by 3 % (and holdout.FLOOR_UM) to be kept


def parse(value: Any, inputs: list[str]) -> str | dict[str, float]:
    """The `lag` fit option: `auto` (searched), `off`, a number of seconds (every temperature
    input), or {input: seconds}. BadInput naming --option lag for anything else."""
    if value is None or value == "auto":
        return "auto"
    if value is False or value == "off" or value == 0:
        return "off"
    if isinstance(value, bool):
        raise BadInput("lag is auto, off, seconds, or {input: seconds}", path="--option lag")
    if isinstance(value, int | float):
        if not 0 <= value <= 3600:
            raise BadInput(f"a lag of {value:g} s: 0 … 3600 s", path="--option lag")
        return {"*": float(value)}
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if k not in inputs:
                raise BadInput(f"{k!r} is not an input of the model ({', '.join(inputs)})", path="--option lag")
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 <= v <= 3600:
                raise BadInput(f"the lag of {k} must be 0 … 3600 s, got {v!r}", path="--option lag")
            out[str(k)] = float(v)
        return out
    raise BadInput("lag is auto, off, seconds, or {input: seconds}", path="--option lag")


def step_s(log: Log) -> float:
    """The log's median step (s): the shortest low-pass worth having is two of them."""
    dt = np.diff(log.t_s)
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else 1.0


def filter_for(lag_s: float, log_step_s: float) -> float:
    """τ_f for a lag τ: FILTER_RATIO τ, at least two of the log's steps."""
    return max(FILTER_RATIO * lag_s, 2.0 * log_step_s)


def lead_lists(inputs: list[str], lags: dict[str, float], log_step_s: float) -> tuple[list[float], list[float]]:
    """(lead_s, lead_filter_s) in input order from {input: τ}; 0 and τ_f 0 where an input is not led."""
    lead = [float(lags.get(name, 0.0)) for name in inputs]
    filt = [filter_for(v, log_step_s) if v > 0 else 0.0 for v in lead]
    return lead, filt


def led(log: Log, inputs: list[str], lead_s: list[float], filter_s: list[float]) -> Log:
    """A copy of the log whose input columns are led as the model will lead them at run time."""
    lead = InputLead(lead_s, filter_s)
    if not lead.idx_list:
        return log
    data = log.data.copy()
    cols = [log.index(n) for n in inputs]
    X = data[:, cols]
    data[:, cols] = lead.filter(X, log.t_s)
    return Log(log.file, log.columns, data)


def with_lead(result: FitResult, lead_s: list[float], filter_s: list[float]) -> FitResult:
    """The fit's model with the lead in its params (the fit saw the led inputs)."""
    m = result.model
    if not any(v > 0 for v in lead_s):
        return result
    params = m.params.model_copy(update={"lead_s": lead_s, "lead_filter_s": filter_s})
    model = type(m)(params, m.inputs, m.outputs, m.fit_info)
    return FitResult(model, result.report)


FitFn = Callable[[Log, dict[str, Any]], FitResult]
# the option key by which the search hands a refit the inputs the first fit chose (compd.identify.identify
# takes it out and passes them as the fit's inputs): a refit per lag per fold chooses nothing again
HELD_INPUTS = "__inputs__"
# a fit's report of the choices its kind makes beyond the coefficients (what `choices` holds fixed)
CHOICE_KEYS = (
    "selection",
    "q2",
    "press",
    "cv",
    "q2_limit",
    "n_components",
    "c1_form",
    "form",
    "form_selection",
    "degree",
    "inputs_chosen",
    "ambient_chosen",
    "exchange_chosen",
    "at_bounds",
)


def fit_with_lag(
    log: Log,
    targets: list[str] | None,
    fit: FitFn,
    options: dict[str, Any],
    lag: Any,
    choices: Callable[[FitResult], dict[str, Any]],
) -> FitResult:
    """Fit `fit(log, options)` with the lead `lag` asks for (module doc); the report's `lag` says
    what was tried and kept."""
    temps_all = log.temperature_columns()
    spec = parse(lag, temps_all)
    dt = step_s(log)
    if isinstance(spec, dict):  # given: one fit on the led log (every temperature column for "*")
        lags = {n: spec.get(n, spec.get("*", 0.0)) for n in temps_all}
        names = [n for n, v in lags.items() if v > 0]
        lead, filt = lead_lists(names, lags, dt)
        result = fit(led(log, names, lead, filt), options)
        lead, filt = lead_lists(result.model.inputs, lags, dt)
        result = with_lead(result, lead, filt)
        result.report["lag"] = {
            "method": "given",
            "lead_s": {n: v for n, v in zip(result.model.inputs, lead, strict=True) if v > 0},
        }
        return result
    first = fit(log, options)
    inputs = list(first.model.inputs)
    temps = [n for n in inputs if n in temps_all]
    if spec == "off" or not temps:
        first.report["lag"] = {"method": "off" if spec == "off" else "no temperature inputs to lead"}
        return first
    target = default_targets(log, targets)
    fixed = {**options, **choices(first)}
    if isinstance(first.report.get("inputs_chosen"), dict):  # the inputs it chose are held too (the ξ sensor)
        fixed[HELD_INPUTS] = list(first.report["inputs_chosen"]["inputs"])

    def score(lags: dict[str, float]) -> float:
        lead, filt = lead_lists(inputs, lags, dt)
        # the inputs led once for every fold: a fold hides only its targets, which the lead does not touch
        led_log = led(log, inputs, lead, filt)
        hidden = [log.index(t) for t in target]

        def fit_on(lg: Log) -> FitResult:
            data = led_log.data.copy()
            data[:, hidden] = lg.data[:, hidden]
            return with_lead(fit(Log(lg.file, lg.columns, data), fixed), lead, filt)

        try:
            rmse = holdout.held_out_rmse(log, target, fit_on)
        except ValueError:
            return float("inf")
        return float(np.sqrt(np.mean(rmse**2)))

    tried: dict[str, float] = {}
    none = score({})
    tried["0"] = none
    best, best_lags = none, {}
    for tau in LAG_GRID_S[1:]:
        lags = dict.fromkeys(temps, tau)
        s = score(lags)
        tried[f"{tau:g}"] = s
        if s < best:
            best, best_lags = s, lags
    per_input: dict[str, dict[str, float]] = {}
    if best_lags and 1 < len(temps) <= PER_INPUT_MAX:
        for name in temps:
            per_input[name] = {}
            for tau in LAG_GRID_S:
                if tau == best_lags[name]:
                    continue
                lags = {**best_lags, name: tau}
                s = score(lags)
                per_input[name][f"{tau:g}"] = s
                if s < best:
                    best, best_lags = s, lags
    report: dict[str, Any] = {
        "method": holdout.METHOD
        + f"; one lag for every temperature input from {list(LAG_GRID_S)} s"
        + (", then each input's own" if per_input else "")
        + f", τ_f = {FILTER_RATIO:g} τ (≥ 2 log steps); kept below {MARGIN:g} × the held-out RMSE without",
        "held_out_rmse_um": tried,
        **({"per_input_rmse_um": per_input} if per_input else {}),
    }
    if not best_lags or not np.isfinite(none) or not holdout.clearly_better(best, none, MARGIN):
        report["kept"] = False
        report["reason"] = "no lead predicts the held-out folds clearly better than the readings as they are"
        first.report["lag"] = report
        return first
    lead, filt = lead_lists(inputs, best_lags, dt)
    result = with_lead(fit(led(log, inputs, lead, filt), fixed), lead, filt)
    # what the first fit chose, and how (the refit was told the choice, so its own report of it is moot)
    for key, value in first.report.items():
        if key in CHOICE_KEYS or key not in result.report:
            result.report[key] = value
    top = [n for n, v in best_lags.items() if v >= LAG_GRID_S[-1]]
    if top:
        report["at_bounds"] = [f"the lag of {', '.join(top)} is the longest tried ({LAG_GRID_S[-1]:g} s)"]
    report.update(
        kept=True,
        lead_s={n: v for n, v in zip(inputs, lead, strict=True) if v > 0},
        lead_filter_s={n: v for n, v in zip(inputs, filt, strict=True) if v > 0},
    )
    result.report["lag"] = report
    return result
