"""`compd fit --kind all`'s recommendation: the model that holds on an unseen day, and what it will do there.

The model is a sum of two stages where a second one pays; what it will do is stated with its range.

Every candidate is judged on the held-out folds of compd.identify.holdout (a log's days, else
its duty levels — a speed spectrum's levels, each predicted by a fit that never saw it — else
stretches cut at duty changes): what a fit never saw is what an unseen day brings.

* **One kind** (each with the lag lead its fit kept): its pooled held-out RMSE.
* **A sum of two stages** (`propose_sums`): a spindle model (`xi_spindle`, `ar1`) on its own
  sensors, then MLR on the other temperatures fitted on what it leaves — two heat sources on one
  axis (a spindle and a column or bed) that push it different ways. Scored *nested*: in each fold
  both stages are fitted on the other folds (the first on the error, the second on what the
  first leaves there) and the fold is predicted by their sum, so no stage has seen the fold. A
  sum is proposed only where it beats the best single model by `SUM_MARGIN` held out.
* **The choice** per axis: the smallest held-out RMSE among the candidates no warning rules out
  (`FitOutcome.blocking`: a fit that did not converge, or predicts almost nothing). A warning that
  only advises (a parameter at the edge of its search range, a lag at the longest tried, a named
  input the fit pins at zero) is shown, with what to do, and does not rule a model out: the
  held-out error already says what it costs on rows the fit did not see.
* **What it will do** (`stated`): the expected unseen-day RMS is the pooled held-out RMSE; its
  range runs from the best to the worst fold's RMS (a fold is an unseen duty, as a day is), never
  narrower than ÷/× `MIN_SPREAD` around the expectation, and for a sum whose stages cancel
  (|stage 1| + |stage 2| over |sum|, the cancel ratio, above `CANCEL_WARN`) the upper end grows by
  ratio / CANCEL_WARN (continuous where the warning starts): each stage's own error is of the size
  of that stage, not of their small sum. The reduction is stated against the training log's RMS
  error, with the same range.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compd.identify import holdout, identify
from compd.identify.data import FitResult, columns
from compd.log import Log, error_axis
from compd.models.base import Model

SUM_MARGIN = 0.9  # a sum of two stages must predict the held-out folds 10 % better than the best single model
CANCEL_WARN = 2.0  # stages whose sizes add to more than twice their sum cancel: said, and counted in the range
MIN_SPREAD = 1.5  # the stated range is at least expectation ÷ 1.5 … × 1.5: a few folds say little of the spread
SPINDLE_KINDS = ("xi_spindle", "ar1")  # first stages: a spindle's own heat, on its own sensors and the speed
SECOND_STAGE = "mlr"  # the structure (column, bed, air) on the other temperatures, fitted on what the first leaves


def fold_rms(scores: list[holdout.FoldScore], k: int) -> list[float]:
    """Per fold that could be fitted and has rows for target `k`: its RMS (µm)."""
    out = []
    for f in scores:
        if isinstance(f, str):
            continue
        sq, n = f
        if n[k] > 0:
            out.append(float(math.sqrt(sq[k] / n[k])))
    return out


def pooled(scores: list[holdout.FoldScore], k: int) -> float:
    """The pooled RMS (µm) of target `k` over the folds that could be fitted (NaN: none)."""
    sq = sum(float(f[0][k]) for f in scores if not isinstance(f, str))
    n = sum(int(f[1][k]) for f in scores if not isinstance(f, str))
    return math.sqrt(sq / n) if n else math.nan


@dataclass
class Stated:
    """What a model will do on an unseen day, as the held-out folds say: RMS (µm) with its range, and
    the reduction of the training log's RMS error (%) with the same range."""

    rms_um: float
    low_um: float
    high_um: float
    before_um: float
    folds: int
    cancel_ratio: float | None = None

    @staticmethod
    def of(fold_values: list[float], expected_um: float, before_um: float, cancel_ratio: float | None = None) -> Stated:
        lo = min(fold_values) if fold_values else expected_um
        hi = max(fold_values) if fold_values else expected_um
        lo = min(lo, expected_um / MIN_SPREAD)
        hi = max(hi, expected_um * MIN_SPREAD)
        if cancel_ratio is not None and cancel_ratio > CANCEL_WARN:
            hi *= cancel_ratio / CANCEL_WARN
        return Stated(expected_um, lo, hi, before_um, len(fold_values), cancel_ratio)

    def reduction_pct(self, rms_um: float) -> float:
        return 100.0 * (1.0 - rms_um / self.before_um) if self.before_um > 0 else math.nan

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "rms_um": round(self.rms_um, 4),
            "range_um": [round(self.low_um, 4), round(self.high_um, 4)],
            "before_um": round(self.before_um, 4),
            "reduction_pct": round(self.reduction_pct(self.rms_um), 2),
            "reduction_range_pct": [
                round(self.reduction_pct(self.high_um), 2),
                round(self.reduction_pct(self.low_um), 2),
            ],
            "folds": self.folds,
            "method": holdout.METHOD,
        }
        if self.cancel_ratio is not None:
            out["cancel_ratio"] = round(self.cancel_ratio, 3)
        return out

    def line(self, axis: str) -> str:
        lo_pct, hi_pct = self.reduction_pct(self.high_um), self.reduction_pct(self.low_um)
        return (
            f"expected on an unseen day, axis {axis}: RMS {self.rms_um:.2f} um ({self.low_um:.2f} to"
            f" {self.high_um:.2f}), {self.reduction_pct(self.rms_um):.0f} % less than the"
            f" {self.before_um:.2f} um of this log ({lo_pct:.0f} to {hi_pct:.0f} %)"
        )


@dataclass
class SumOutcome:
    """A two-stage sum on one axis: the stages fitted on the whole log, scored nested held out."""

    axis: str
    target: str
    first: FitResult
    second: FitResult
    first_kind: str
    second_inputs: list[str]
    scores: list[holdout.FoldScore]
    held_out_um: float
    cancel_ratio: float
    warnings: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.first_kind}+{SECOND_STAGE}" + ("" if self.axis == "z" else f"_{self.axis}")


def predict_fresh(model: Model, log: Log) -> np.ndarray:
    """A model's prediction over the log from a cold start (n × outputs), NaN where an input is blank."""
    fresh = type(model)(model.params, model.inputs, model.outputs, model.fit_info)
    return fresh.predict(columns(log, model.inputs), log.t_s)


def _with_target(log: Log, target: str, values: np.ndarray) -> Log:
    data = log.data.copy()
    data[:, log.index(target)] = values
    return Log(log.file, log.columns, data)


def _stage_pair(
    log: Log, target: str, fit_first: Callable[[Log], FitResult], second_inputs: list[str], axis: str
) -> tuple[FitResult, FitResult, np.ndarray]:
    """Both stages on `log` (its target's blank cells not fitted): the first on the error, the second
    (MLR) on what the first leaves; and their summed prediction over every row."""
    first = fit_first(log)
    k1 = first.model.outputs.index(axis)
    p1 = predict_fresh(first.model, log)[:, k1]
    rest = _with_target(log, target, log.col(target) - p1)
    second = identify(SECOND_STAGE, rest, second_inputs, [target])
    p2 = predict_fresh(second.model, log)[:, 0]
    return first, second, p1 + p2


def nested_scores(
    log: Log, target: str, axis: str, fit_first: Callable[[Log], FitResult], second_inputs: list[str]
) -> list[holdout.FoldScore]:
    """Per fold of compd.identify.holdout: both stages fitted with the fold's errors hidden, the fold
    predicted by their sum (sum of squares, rows), or why it could not be."""
    cut = holdout.folds(log)[0]
    y = log.col(target)
    out: list[holdout.FoldScore] = []
    for k, fold in enumerate(cut):
        rows = np.concatenate([np.arange(lo, hi) for lo, hi in fold]) if fold else np.zeros(0, dtype=np.intp)
        if not np.isfinite(y[rows]).any():
            out.append(f"fold {k + 1}: no measured error")
            continue
        try:
            _, _, pred = _stage_pair(holdout.hide(log, [target], fold), target, fit_first, second_inputs, axis)
        except holdout.FIT_ERRORS as exc:
            out.append(f"fold {k + 1}: {exc}")
            continue
        r = (y - pred)[rows]
        ok = np.isfinite(r)
        out.append((np.array([float((r[ok] ** 2).sum())]), np.array([int(ok.sum())])))
    return out


def _rms(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else 0.0


def cancel_ratio(p1: np.ndarray, p2: np.ndarray) -> float:
    """(RMS of stage 1 + RMS of stage 2) / RMS of their sum: 1 when they push the same way, large
    when two big contributions cancel to a small error."""
    whole = _rms(p1 + p2)
    return (_rms(p1) + _rms(p2)) / whole if whole > 0 else math.inf


def propose_sums(log: Log, firsts: list[tuple[str, str, list[str], list[str], dict[str, Any]]]) -> list[SumOutcome]:
    """For each spindle kind fitted on a target (`firsts`: (kind, target, the inputs its fit took, the
    inputs its model reads, the options a fold's refit takes)), a sum: that kind on those inputs, then
    MLR on every temperature column its model does not read, on what it leaves; scored nested held out
    (`nested_scores`). A kind whose model reads every temperature column leaves the second stage nothing."""
    out: list[SumOutcome] = []
    temps = log.temperature_columns()
    for kind, target, inputs, model_inputs, options in firsts:
        axis = error_axis(target) or target
        rest = [c for c in temps if c not in model_inputs]
        if not rest:
            continue
        opts = dict(options)

        def fit_first(
            lg: Log, kind: str = kind, inputs: list[str] = inputs, opts: dict[str, Any] = opts, target: str = target
        ) -> FitResult:
            return identify(kind, lg, inputs, [target], **opts)

        try:
            first, second, pred = _stage_pair(log, target, fit_first, rest, axis)
            scores = nested_scores(log, target, axis, fit_first, rest)
        except holdout.FIT_ERRORS:
            continue
        if any(isinstance(f, str) for f in scores):
            continue
        k1 = first.model.outputs.index(axis)
        p1 = predict_fresh(first.model, log)[:, k1]
        p2 = predict_fresh(second.model, log)[:, 0]
        ratio = cancel_ratio(p1, p2)
        so = SumOutcome(axis, target, first, second, kind, rest, scores, pooled(scores, 0), ratio)
        if ratio > CANCEL_WARN:
            so.warnings.append(
                f"{so.label}: axis {axis}: the two stages cancel: {_rms(p1):.1f} um and {_rms(p2):.1f} um RMS add to"
                f" {_rms(p1 + p2):.1f} um (ratio {ratio:.1f}); each stage's own error is of its own size, so the"
                " stated range is widened by that ratio: check each stage against a measurement of its source"
                " alone (err_<axis>_um_<part>) where one can be made"
            )
        out.append(so)
    return out


@dataclass
class Candidate:
    """One model `--kind all` may recommend: a fitted kind, or a sum of two stages, with its held-out
    figures per axis it covers."""

    label: str
    axes: dict[str, float]  # axis → pooled held-out RMSE (µm)
    folds: dict[str, list[float]]  # axis → each fold's RMS (µm)
    single: Any = None  # the FitOutcome (compd.commissioning.fitting), for one kind
    sum: SumOutcome | None = None

    def score(self, axes: list[str]) -> float:
        """The held-out RMSE over `axes` (the root of the mean of squares; inf when one is not covered)."""
        if any(a not in self.axes for a in axes):
            return math.inf
        return math.sqrt(sum(self.axes[a] ** 2 for a in axes) / len(axes))


@dataclass
class Pick:
    """`--kind all`'s recommendation: the candidate, and what it will do per axis on an unseen day."""

    candidate: Candidate
    stated: dict[str, Stated]
    runner_up: Candidate | None = None


def candidates(
    rows: list[Any], sums: list[SumOutcome], held_out_of: Callable[[Any, str], float | None]
) -> list[Candidate]:
    """The fitted kinds no blocking warning rules out, and the sums (see the module)."""
    out = []
    for _, label, oc, _ in rows:
        if oc is None or oc.blocking:
            continue
        held = {a: held_out_of(oc, a) for a in oc.report["axes"]}
        held = {a: float(v) for a, v in held.items() if v is not None and math.isfinite(v)}
        if held:
            out.append(Candidate(label, held, {a: list(oc.fold_rms_um.get(a, [])) for a in held}, single=oc))
    for s in sums:
        out.append(Candidate(s.label, {s.axis: s.held_out_um}, {s.axis: fold_rms(s.scores, 0)}, sum=s))
    return out


def choose(cands: list[Candidate], axes: list[str], before_um: dict[str, float]) -> Pick | None:
    """The candidate with the smallest held-out RMSE over every axis; a sum only where it beats the best
    single model by SUM_MARGIN. With its stated accuracy per axis. None: no candidate covers every axis."""
    singles = sorted((c for c in cands if c.sum is None and math.isfinite(c.score(axes))), key=lambda c: c.score(axes))
    sums = sorted((c for c in cands if c.sum is not None and math.isfinite(c.score(axes))), key=lambda c: c.score(axes))
    if not singles and not sums:
        return None
    best = singles[0] if singles else None
    runner = singles[1] if len(singles) > 1 else None
    if sums and (best is None or sums[0].score(axes) < SUM_MARGIN * best.score(axes)):
        best, runner = sums[0], best
    assert best is not None
    stated = {}
    for a in axes:
        ratio = best.sum.cancel_ratio if best.sum is not None else None
        stated[a] = Stated.of(best.folds.get(a, []), best.axes[a], before_um.get(a, math.nan), ratio)
    return Pick(best, stated, runner)
