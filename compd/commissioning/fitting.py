"""`compd fit` / `predict` / `xi`: fit a model from a log (compd.identify), score it against MLR, write files."""

from __future__ import annotations

import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from compd import version
from compd.commissioning import recommend as rec
from compd.commissioning.recommend import SUM_MARGIN
from compd.commissioning.thermaltest import thermal_test
from compd.config import load_model_file, resolve_model
from compd.core.errors import BadInput
from compd.core.scoring import score_residual
from compd.cycle.contributions import Contributions
from compd.identify import CHOICES, FITS, KINDS, holdout, identify, option_names
from compd.identify.data import (
    columns,
    default_targets,
    progress,
)
from compd.log import Log, error_axis, read_log, write_log
from compd.models.base import Model


@dataclass
class FitOutcome:
    """One fitted model with its scores and report (what `compd fit` prints and writes)."""

    kind: str
    model: Model
    report: dict[str, Any]
    pred: np.ndarray
    warnings: list[str] = field(default_factory=list)
    # the warnings that rule the model out of `--kind all`'s recommendation (it did not converge, it
    # predicts almost nothing); the others only advise (compd.commissioning.recommend)
    blocking: list[str] = field(default_factory=list)
    fit_inputs: list[str] = field(default_factory=list)  # what the fit took as --inputs (its own choice)
    held_options: dict[str, Any] = field(default_factory=dict)  # the options a fold's refit takes (the kept lead, form)
    fold_rms_um: dict[str, list[float]] = field(default_factory=dict)  # per axis, each held-out fold's RMS


def parse_options(pairs: list[str] | None) -> dict[str, Any]:
    """`KEY=VALUE` strings → dict; values are read as YAML (numbers, lists, mappings)."""
    out: dict[str, Any] = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise BadInput(f"expected KEY=VALUE, got {pair!r}", path="--option")
        try:
            out[key.strip()] = yaml.safe_load(value) if value.strip() else None
        except yaml.YAMLError:
            raise BadInput(f"cannot read the value of {key!r}", path="--option") from None
    return out


def read_fit_log(file: str | Path) -> Log:
    """A log for fitting: empty cells allowed here, refused later only in the columns a fit uses."""
    return read_log(file, allow_nan=True)


def clone(model: Model) -> Model:
    """A fresh instance of a model (no run-time state), as a model file would load it."""
    return type(model)(model.params, model.inputs, model.outputs, model.fit_info)


def predict_log(model: Model, log: Log) -> np.ndarray:
    """Batch prediction on a log from a fresh start: (n × outputs) µm."""
    X = columns(log, model.inputs)
    return clone(model).predict(X, log.t_s)


def _targets_for(model: Model, log: Log, targets: list[str] | None) -> list[str]:
    if targets:
        return list(targets)
    return [f"err_{a}_um" for a in model.outputs]


def scores(model: Model, log: Log, targets: list[str], pred: np.ndarray) -> dict[str, dict[str, float]]:
    """RMSE and max |error| per output axis (µm) of prediction against the logged error, on the
    rows where it was measured (in sample: the rows the fit saw)."""
    Y = log.matrix(targets)
    out = {}
    for k, axis in enumerate(model.outputs):
        r = Y[:, k] - pred[:, k]
        r = r[np.isfinite(r)]
        out[axis] = {"rmse_um": float(np.sqrt(np.mean(r * r))), "max_abs_err_um": float(np.max(np.abs(r)))}
    return out


def held_out_rmse(
    kind: str, log: Log, inputs: list[str] | None, targets: list[str], options: dict[str, Any]
) -> np.ndarray:
    """RMSE per target (µm) on rows the fit did not see: compd.identify.holdout's folds (days or
    duty segments), every fold fitted (ValueError naming the fold that cannot be)."""
    return holdout.pooled_rmse(held_out_scores(kind, log, inputs, targets, options), len(targets))


def held_out_scores(
    kind: str, log: Log, inputs: list[str] | None, targets: list[str], options: dict[str, Any]
) -> list[holdout.FoldScore]:
    """Per held-out fold (`held_out_rmse`'s), the squared errors and rows per target, or why it could not be fitted."""
    return holdout.fold_errors(log, targets, lambda lg: identify(kind, lg, inputs, targets, **options))


def _fold_rms(scores: list[holdout.FoldScore], n_targets: int) -> list[list[float]]:
    """Per target, each fold's RMS (µm; the folds with rows for it)."""
    out: list[list[float]] = [[] for _ in range(n_targets)]
    for f in scores:
        if isinstance(f, str):
            continue
        for k in range(n_targets):
            if f[1][k] > 0:
                out[k].append(float(np.sqrt(f[0][k] / f[1][k])))
    return out


def compare_with_mlr(
    kind: str,
    log: Log,
    inputs: list[str],
    targets: list[str],
    options: dict[str, Any],
    axes: list[str],
    warnings: list[str],
    ours: np.ndarray | None = None,
    folds_out: dict[str, list[float]] | None = None,
) -> dict[str, Any]:
    """The fitted kind against MLR on the same log and the same inputs, both scored held out
    (`held_out_rmse`; `ours`, the kind's, when already computed on the same folds); a warning per
    axis where MLR predicts the unseen rows better. `folds_out` gets each fold's RMS per axis."""
    try:
        if ours is None:
            scores = held_out_scores(kind, log, inputs, targets, options)
            ours = holdout.pooled_rmse(scores, len(targets))
            if folds_out is not None:
                folds_out.update(zip(axes, _fold_rms(scores, len(targets)), strict=True))
        # MLR on temperature rises (the papers' baseline): a speed, position or current input stays out;
        # a model that takes none (the analytic feed axis) is compared with MLR on every one
        mlr_inputs = [c for c in inputs if c in log.temperature_columns()] or log.temperature_columns()
        mlr = held_out_rmse("mlr", log, mlr_inputs, targets, {})
    except (BadInput, ValidationError, np.linalg.LinAlgError, ValueError) as e:
        return {"skipped": f"the held-out comparison could not fit a fold: {e}"}
    out: dict[str, Any] = {
        "method": holdout.METHOD,
        "inputs": mlr_inputs,
        "axes": {},
    }
    for a, axis in enumerate(axes):
        out["axes"][axis] = {"held_out_rmse_um": float(ours[a]), "mlr_held_out_rmse_um": float(mlr[a])}
        if ours[a] > mlr[a]:
            warnings.append(
                f"{kind}: axis {axis} held-out RMSE {ours[a]:.3f} um is worse than MLR's {mlr[a]:.3f} um"
                f" on the same inputs ({', '.join(mlr_inputs)})"
            )
    return out


@dataclass
class Stage:
    """What `compd fit --on-residual-of` fits on: the models fitted before, evaluated over the log as
    `compd predict` evaluates them (from a cold start, each input's lead included), and the targets less
    their sum."""

    info: list[dict[str, Any]]  # per model file: file, path, sha256, kind, inputs, outputs, fitted_at, log
    models: list[Model]
    pred_um: dict[str, np.ndarray]  # per axis they predict: the summed prediction (NaN where one is not finite)
    covered: dict[str, list[str]]  # per target column: the files whose prediction it has subtracted ([]: none)
    left_out: dict[str, int]  # per covered target: rows blanked, the prediction not finite there
    log: Log  # each covered target less the prediction, blank where that is not finite
    whole: Log  # the same cells blank, the error whole: what the single-stage comparisons fit


def residual_stage(log: Log, files: list[str], targets: list[str] | None) -> Stage:
    """The log a fit `--on-residual-of` FILES takes: each target whose axis the models output, less the
    sum of their predictions. A model's input missing from the log, the same file twice, or models
    that predict none of the targets' axes are BadInput."""
    tcols = default_targets(log, targets)
    info: list[dict[str, Any]] = []
    models: list[Model] = []
    pred_um: dict[str, np.ndarray] = {}
    producers: dict[str, list[str]] = {}
    seen: set[Path] = set()
    for file in files:
        if Path(file).resolve() in seen:
            raise BadInput(
                "given twice (its prediction would be subtracted twice)", file=str(file), path="--on-residual-of"
            )
        seen.add(Path(file).resolve())
        model = load_model(file)
        for name in model.inputs:
            if name not in log.columns:
                raise BadInput(
                    f"column {name!r}, an input of {file} (--on-residual-of), is not in the log", file=log.file
                )
        pred = predict_log(model, log)
        name = Path(file).name
        for k, axis in enumerate(model.outputs):
            pred_um[axis] = pred_um[axis] + pred[:, k] if axis in pred_um else pred[:, k].astype(float)
            producers.setdefault(axis, []).append(name)
        models.append(model)
        info.append(
            {
                "file": name,
                "path": str(file),
                "sha256": hashlib.sha256(Path(file).read_bytes()).hexdigest(),
                "kind": model.kind,
                "inputs": list(model.inputs),
                "outputs": list(model.outputs),
                "fitted_at": model.fit_info.get("fitted_at"),
                "log": model.fit_info.get("log"),
            }
        )
    covered: dict[str, list[str]] = {}
    left_out: dict[str, int] = {}
    residual, whole = log.data.copy(), log.data.copy()
    for t in tcols:
        axis = error_axis(t) or t
        covered[t] = producers.get(axis, [])
        if covered[t]:
            j, p = log.index(t), pred_um[axis]
            bad = ~np.isfinite(p)
            left_out[t] = int(np.count_nonzero(bad & np.isfinite(log.data[:, j])))
            residual[:, j] = np.where(bad, np.nan, log.data[:, j] - np.where(bad, 0.0, p))
            whole[bad, j] = np.nan
    if not any(covered.values()):
        names = ", ".join(i["file"] for i in info)
        verb = "predicts" if len(info) == 1 else "predict"
        noun = "axis" if len(pred_um) == 1 else "axes"
        those = "that axis" if len(pred_um) == 1 else "those axes"
        raise BadInput(
            f"{names} {verb} {noun} {', '.join(sorted(pred_um))}, and no target is of {those}"
            f" (targets: {', '.join(tcols)})",
            path="--on-residual-of",
        )
    return Stage(
        info,
        models,
        pred_um,
        covered,
        left_out,
        Log(log.file, list(log.columns), residual),
        Log(log.file, list(log.columns), whole),
    )


def stage_line(stage: Stage) -> str:
    """One line saying what a fit `--on-residual-of` is fitted on."""
    models = ", ".join(
        f"{i['file']} ({i['kind']}, fitted on {i['log'] or 'a log it does not name'})" for i in stage.info
    )
    its = "its" if len(stage.info) == 1 else "their"
    parts = [
        f"{t} less {its} prediction" if files else f"{t} as is (no model before predicts it)"
        for t, files in stage.covered.items()
    ]
    left = sum(stage.left_out.values())
    tail = f"; {left} rows left out where the prediction is not finite" if left else ""
    leave = "leaves" if len(stage.info) == 1 else "leave"
    return f"fitting on what {models} {leave}: {', '.join(parts)}{tail}"


def stagewise_note(stage: Stage, log_file: str) -> str:
    """What the held-out figures of a stage-by-stage fit can and cannot say about the models before."""
    name = Path(log_file).name
    groups = {
        "fitted on this log: the sum and the first alone have seen every fold's errors through that fit"
        " (which flatters both against the single-stage fits, refitted per fold)": [
            i for i in stage.info if i["log"] == name
        ],
        "fitted on another log, so on this one the sum and the first alone are held out as well": [
            i for i in stage.info if i["log"] not in (name, None)
        ],
        "fitted on a log its file does not name: the figures cannot say whether it saw this one": [
            i for i in stage.info if i["log"] is None
        ],
    }
    text = "the models fitted before are used as given in every fold: their coefficients are not refitted per fold"
    for what, infos in groups.items():
        if infos:
            files = ", ".join(f"{i['file']}" + (f" ({i['log']})" if i["log"] else "") for i in infos)
            text += f"; {files} {'was' if len(infos) == 1 else 'were'} {what}"
    return text


STAGEWISE_FORMS = {
    "sum_held_out_rmse_um": "the models fitted before, as given, plus the kind refitted per fold on what they"
    " leave in the other folds",
    "alone_held_out_rmse_um": "the kind on the same inputs fitted on the whole error, no model before it",
    "first_alone_rmse_um": "the models fitted before alone, as given, on the same rows",
    "mlr_all_inputs_held_out_rmse_um": "MLR on the temperature inputs of every model, on the whole error",
}


def _fold_rows(cut: list[holdout.Fold], n: int) -> np.ndarray:
    mask = np.zeros(n, dtype=bool)
    for fold in cut:
        for lo, hi in fold:
            mask[lo:hi] = True
    return mask


def compare_stagewise(
    kind: str,
    stage: Stage,
    inputs: list[str],
    targets: list[str],
    options: dict[str, Any],
    axes: list[str],
    warnings: list[str],
) -> tuple[dict[str, Any], np.ndarray | None]:
    """The stage-by-stage fit against the single-stage ones, per axis, on the same folds as the report's
    `baseline_mlr` (compd.identify.holdout) and the same rows: the sum (the models before, as given, plus
    `kind` refitted per fold on their residual), `kind` alone on the whole error, the models before
    alone, MLR on every model's temperature inputs. Returns the report's `stagewise` block and the
    sum's held-out RMSE per target (None if a fold could not be fitted)."""
    cut, how = holdout.folds(stage.whole)
    temps = stage.whole.temperature_columns()
    both = list(dict.fromkeys([*(n for m in stage.models for n in m.inputs), *inputs]))
    mlr_inputs = [c for c in both if c in temps] or temps
    forms = {
        "sum_held_out_rmse_um": (stage.log, lambda lg: identify(kind, lg, inputs, targets, **options)),
        "alone_held_out_rmse_um": (stage.whole, lambda lg: identify(kind, lg, inputs, targets, **options)),
        "mlr_all_inputs_held_out_rmse_um": (stage.whole, lambda lg: identify("mlr", lg, mlr_inputs, targets)),
    }
    held: dict[str, np.ndarray] = {}
    skipped: dict[str, str] = {}
    for key, (lg, fit_on) in forms.items():
        try:
            held[key] = holdout.pooled_rmse(holdout.fold_errors(lg, targets, fit_on, cut), len(targets))
        except holdout.FIT_ERRORS as e:
            skipped[key] = f"the held-out comparison could not fit a fold: {e}"
    scored = _fold_rows(cut, len(stage.whole))
    Y = stage.whole.matrix(targets)
    first = " + ".join(i["file"] for i in stage.info)
    out_axes: dict[str, Any] = {}
    for k, (axis, t) in enumerate(zip(axes, targets, strict=True)):
        if not stage.covered.get(t):
            out_axes[axis] = {
                "on_residual": False,
                "note": f"{first} {'predicts' if len(stage.info) == 1 else 'predict'} no axis"
                f" {axis}: {kind} fitted on {t} as is",
            }
            continue
        r = (Y[:, k] - stage.pred_um[error_axis(t) or t])[scored]
        r = r[np.isfinite(r)]
        entry: dict[str, Any] = {
            "on_residual": True,
            "residual_of": stage.covered[t],
            "rows_without_prediction": stage.left_out[t],
            "held_out_rows": int(r.size),
        }
        for key in STAGEWISE_FORMS:  # in the order the forms are described
            if key == "first_alone_rmse_um":
                entry[key] = float(np.sqrt(np.mean(r * r))) if r.size else None
            else:
                entry[key] = float(held[key][k]) if key in held else None
        out_axes[axis] = entry
        total, alone = entry["sum_held_out_rmse_um"], entry["alone_held_out_rmse_um"]
        mlr = entry["mlr_all_inputs_held_out_rmse_um"]
        if total is not None and alone is not None and total > alone:
            warnings.append(
                f"{kind}: axis {axis}: {first} + {kind} predicts held out worse ({total:.3f} um)"
                f" than {kind} alone on the whole error ({alone:.3f} um)"
            )
        if total is not None and mlr is not None and total > mlr:
            warnings.append(
                f"{kind}: axis {axis}: {first} + {kind} predicts held out worse ({total:.3f} um)"
                f" than MLR on {', '.join(mlr_inputs)} ({mlr:.3f} um)"
            )
    block: dict[str, Any] = {
        "method": holdout.METHOD,
        "folds": how,
        "first": [i["file"] for i in stage.info],
        "first_refitted_per_fold": False,
        "note": stagewise_note(stage, stage.log.file),
        "kind": kind,
        "inputs": list(inputs),
        "mlr_inputs": mlr_inputs,
        "forms": STAGEWISE_FORMS,
        "axes": out_axes,
    }
    if skipped:
        block["skipped"] = skipped
    return block, held.get("sum_held_out_rmse_um")


def stagewise_lines(oc: FitOutcome) -> list[str]:
    """The printed summary of a fit `--on-residual-of`: per axis the held-out RMSE of the sum, the kind
    alone, the models before alone and MLR on every input (or why an axis was fitted as is)."""
    block = oc.report.get("stagewise")
    if not block:
        return []
    first = " + ".join(block["first"])
    f = lambda v: "-" if v is None else f"{v:.3f} um"  # noqa: E731
    lines = []
    for axis, e in block["axes"].items():
        if not e["on_residual"]:
            lines.append(f"{oc.kind} axis {axis}: {e['note']}")
            continue
        lines.append(
            f"{oc.kind} axis {axis} held out: {first} + {oc.kind} {f(e['sum_held_out_rmse_um'])},"
            f" {oc.kind} on {' '.join(block['inputs'])} alone {f(e['alone_held_out_rmse_um'])},"
            f" {first} alone {f(e['first_alone_rmse_um'])}"
            f" (as given, not refitted), MLR on {' '.join(block['mlr_inputs'])}"
            f" {f(e['mlr_all_inputs_held_out_rmse_um'])}"
        )
    for key, why in block.get("skipped", {}).items():
        lines.append(f"{oc.kind}: {key}: {why}")
    return lines


# a fit that leaves more than this share of the error's RMS, in sample, removes almost nothing
REMOVES_NOTHING = 0.9


def rows_fitted(details: dict[str, Any], log: Log, targets: list[str], inputs: list[str]) -> int:
    """The rows a fit's loss counted: the kind's own count where it has one (LVR's library of
    differences), else the rows with an error measured and every input read."""
    if isinstance(details.get("fit_rows"), int):
        return int(details["fit_rows"])
    ok = np.isfinite(log.matrix(targets)).any(axis=1)
    if inputs:
        ok &= np.isfinite(log.matrix(inputs)).all(axis=1)
    return int(ok.sum())


def _rms(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else 0.0


def fit_model(
    kind: str,
    log: Log,
    inputs: list[str] | None,
    targets: list[str] | None,
    options: dict[str, Any],
    *,
    baseline: bool = True,
    stage: Stage | None = None,
) -> FitOutcome:
    """Fit `kind` (compd.identify), score it on the log, compare with MLR on the same targets.

    With `stage` (`compd fit --on-residual-of`, built by `residual_stage` from this log) the fit
    runs on `stage.log`, the targets less the models fitted before; the report adds
    `on_residual_of` and the held-out comparison `stagewise` (`compare_stagewise`)."""
    FITS.get(kind, path="--kind")  # an unknown kind: BadInput naming --kind
    if stage is not None:
        log = stage.log
    t0 = time.perf_counter()
    try:
        result = identify(kind, log, inputs, targets, **options)
    except ValidationError as e:  # the data drove a coefficient out of its physical range
        err = e.errors()[0]
        key = ".".join(str(p) for p in err["loc"])
        raise BadInput(
            f"the {kind} fit gives params.{key} out of range: {err['msg']} (got {err.get('input')!r})",
            file=log.file,
        ) from None
    fit_s = time.perf_counter() - t0
    model = result.model
    tcols = _targets_for(model, log, targets)
    pred = predict_log(model, log)
    axes = scores(model, log, tcols, pred)
    warnings: list[str] = []
    blocking: list[str] = []  # what rules the model out of --kind all's recommendation
    if result.report.get("converged") is False:
        blocking.append(f"{kind}: the fit did not converge ({result.report.get('optimizer', 'see report')})")
        warnings.append(blocking[-1])
    if result.report.get("warning"):
        warnings.append(f"{kind}: {result.report['warning']}")
    for why in result.report.get("at_bounds", []):
        warnings.append(f"{kind}: {why}")
    for why in result.report.get("lag", {}).get("at_bounds", []):
        warnings.append(
            f"{kind}: {why}: the sensor may lag more than the lead goes; the lead kept still predicts"
            " the held-out folds better than none (its held-out RMSE below says by how much): keep it,"
            " or mount the sensor closer to the heat"
        )
    for axis, s in axes.items():
        before = _rms(log.matrix([t for t in tcols if error_axis(t) == axis] or tcols[:1])[:, 0])
        if before > 0 and s["rmse_um"] > REMOVES_NOTHING * before:
            blocking.append(
                f"{kind}: axis {axis}: the model removes almost nothing of the error it was fitted to"
                f" (RMSE {s['rmse_um']:.3f} um of {before:.3f} um in sample)"
            )
            warnings.append(blocking[-1])
    rows = rows_fitted(result.report, log, tcols, list(model.inputs))
    report: dict[str, Any] = {
        "kind": kind,
        "log": log.file,
        "rows": rows,
        "log_rows": len(log),
        "inputs": model.inputs,
        "targets": tcols,
        "fit_time_s": fit_s,
        "axes": axes,
        "details": result.report,
    }
    held_options = dict(options)
    if "form" in result.report:  # score the form the fit kept (feed_axis form: auto)
        held_options["form"] = result.report["form"]
    if kind == "ar1":  # ... and AR(1)'s C1 form, ambient and exchange sensors (as its structure sensors)
        chosen = CHOICES.get(kind)(result)
        held_options.update({k: chosen[k] for k in ("c1_by_speed", "ambient", "exchange") if k in chosen})
    # ... and the lead it kept: a fold refits the coefficients, not the lag search
    lead = result.model.params.model_dump().get("lead_s")
    led = {n: v for n, v in zip(model.inputs, lead or [], strict=False) if v > 0}
    held_options["lag"] = led or "off"
    # what the fit took as --inputs (a kind that chose its own says which)
    fit_inputs = inputs or result.report.get("fit_inputs")
    fit_inputs = list(model.inputs if fit_inputs is None else fit_inputs)
    ours: np.ndarray | None = None  # the kind's held-out RMSE, once (the stagewise sum is the same figure)
    fold_rms: dict[str, list[float]] = {}
    if stage is not None:
        report["on_residual_of"] = stage.info
        if baseline:
            report["stagewise"], ours = compare_stagewise(
                kind, stage, fit_inputs, tcols, held_options, model.outputs, warnings
            )
    kept = result.report.get("c1_form", {}).get("held_out_folds")
    if stage is None and kept and len(tcols) == 1:  # AR(1) scored its chosen form on these folds already
        folds: list[holdout.FoldScore] = [(np.array([sq]), np.array([n])) for sq, n in kept]
        ours = holdout.pooled_rmse(folds, 1)
        fold_rms.update(zip(model.outputs, _fold_rms(folds, 1), strict=True))
    if baseline and kind != "mlr":
        report["baseline_mlr"] = compare_with_mlr(
            kind, log, fit_inputs, tcols, held_options, model.outputs, warnings, ours, fold_rms
        )
    if baseline and kind == "mlr":  # the baseline's own held-out figure (the probe adapter's σ_m, the tables)
        try:
            if ours is not None:
                held = ours
            else:
                folds = held_out_scores("mlr", log, inputs, tcols, options)
                held = holdout.pooled_rmse(folds, len(tcols))
                fold_rms.update(zip(model.outputs, _fold_rms(folds, len(tcols)), strict=True))
            report["held_out_rmse_um"] = dict(zip(model.outputs, map(float, held), strict=True))
        except (BadInput, ValidationError, np.linalg.LinAlgError, ValueError) as e:
            report["held_out_rmse_um"] = {"skipped": f"the held-out comparison could not fit a fold: {e}"}
    if fold_rms:
        report["held_out_fold_rmse_um"] = fold_rms
    if stage is None:  # the test's own figures, ISO 230-3's drift beside this model's residual (in sample)
        report["thermal_test"] = thermal_test_block(log, model, pred)
    report["warnings"] = warnings
    fit_info: dict[str, Any] = {
        "fitted_at": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "compd_version": version(),
        "log": Path(log.file).name,
        "rows": rows,
        "log_rows": len(log),
        "rmse_um": {a: s["rmse_um"] for a, s in axes.items()},
        "max_abs_err_um": {a: s["max_abs_err_um"] for a, s in axes.items()},
    }
    ranges = {}  # the readings the fit saw: a remote model is checked against the guard's clamp over them
    for name, col in zip(model.inputs, log.matrix(list(model.inputs)).T, strict=True):
        seen = col[np.isfinite(col)]
        if seen.size:
            ranges[name] = [float(seen.min()), float(seen.max())]
    fit_info["input_range"] = ranges
    held = {a: v["held_out_rmse_um"] for a, v in report.get("baseline_mlr", {}).get("axes", {}).items()}
    held = held or {a: v for a, v in report.get("held_out_rmse_um", {}).items() if isinstance(v, float)}
    if held:  # how far off the model is on rows its fit did not see (the probe adapter's σ_m)
        fit_info["held_out_rmse_um"] = held
    for key in (
        "selection",
        "q2",
        "press",
        "cv",
        "n_components",
        "ljung_box",
        "converged",
        "dt_s",
        "c2_at_unseen_speeds",
    ):
        if key in result.report:
            fit_info[key] = result.report[key]
    if stage is not None:  # what was subtracted before the fit: a later check can tell it is the same model
        before = [
            {k: i[k] for k in ("file", "sha256", "kind", "fitted_at")}
            for i in stage.info
            if set(i["outputs"]) & set(model.outputs)
        ]  # those on this model's axes
        if before:
            fit_info["on_residual_of"] = before
    model.fit_info = json.loads(json.dumps(fit_info))
    return FitOutcome(kind, model, report, pred, warnings, blocking, fit_inputs, held_options, fold_rms)


def thermal_test_block(log: Log, model: Model, pred: np.ndarray) -> dict[str, Any]:
    """The fit report's `thermal_test` (compd.commissioning.thermaltest) of the log the model was
    fitted on, or `skipped` with the reason (a log that measures no axis)."""
    try:
        return thermal_test(log, list(model.outputs), pred).as_dict()
    except BadInput as e:
        return {"skipped": e.message}


def score_model(model: Model, log: Log) -> dict[str, Any]:
    """`compd score`: a fitted model on a log with the measured errors (a day it has not seen).

    Per axis the error before (`err_<axis>_um`) and after (error − prediction), scored as every
    report is (compd.core.scoring); blank error cells between measurements are left out. The baseline
    is the fit report's: MLR on the model's temperature inputs (all the log's temperatures if it
    has none), each fold of this log predicted by an MLR fitted on the others (holdout.METHOD),
    beside the model's RMS on the same rows."""
    targets = [f"err_{a}_um" for a in model.outputs]
    Y = log.matrix(targets)  # a missing err_<axis>_um column is BadInput naming it
    pred = predict_log(model, log)
    axes = {axis: score_residual(Y[:, k], Y[:, k] - pred[:, k]) for k, axis in enumerate(model.outputs)}
    for axis, s in axes.items():
        if s["rows"] == 0:
            raise BadInput(f"no measured error to score axis {axis} against", file=log.file, path=f"err_{axis}_um")
    temps = log.temperature_columns()
    mlr_inputs = [c for c in model.inputs if c in temps] or temps
    baseline: dict[str, Any] = {"method": holdout.METHOD, "inputs": mlr_inputs}
    measured = np.isfinite(Y).all(axis=1)  # MLR scores the rows with every error measured
    try:
        mlr = held_out_rmse("mlr", log, mlr_inputs, targets, {})
    except (BadInput, ValidationError, np.linalg.LinAlgError, ValueError) as e:
        baseline["skipped"] = f"the held-out MLR could not fit a fold: {e}"
    else:
        baseline["axes"] = {}
        for k, axis in enumerate(model.outputs):
            r = (Y[:, k] - pred[:, k])[measured]
            r = r[np.isfinite(r)]
            baseline["axes"][axis] = {
                "model_rmse_um": float(np.sqrt(np.mean(r * r))) if r.size else float("nan"),
                "mlr_held_out_rmse_um": float(mlr[k]),
            }
    return {
        "kind": model.kind,
        "log": log.file,
        "rows": len(log),
        "inputs": model.inputs,
        "axes": axes,
        "baseline_mlr": baseline,
    }


def write_model(model: Model, path: str | Path) -> None:
    """The model YAML (kind, inputs, outputs, params, fit; docs/formats.md)."""
    data = json.loads(json.dumps(model.to_dict()))
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True), encoding="utf-8")


def load_model(path: str | Path) -> Model:
    """A model from its YAML file, validated like a config's `model: {kind, file}`."""
    doc, data = load_model_file(path)
    p = Path(path).resolve()
    spec = resolve_model({"kind": data["kind"], "file": str(p)}, doc, (), p.parent)
    cls = Contributions if spec.cls is None else spec.cls  # a sum: the cycle's stage (compd.cycle.pipeline)
    return cls(spec.params, spec.inputs, spec.outputs, spec.fit)


def write_prediction(path: str | Path, t_s: np.ndarray, axes: list[str], pred: np.ndarray) -> None:
    """PRED.csv: t_s and one pred_<axis>_um column per axis."""
    write_log(path, ["t_s"] + [f"pred_{a}_um" for a in axes], np.column_stack([t_s, pred]))


def applicable(kind: str, log: Log, inputs: list[str] | None, options: dict[str, Any]) -> str | None:
    """Why `kind` cannot be fitted on this log in `--kind all` (None if it can)."""
    if kind == "ar1" and "speed_rpm" not in log.columns:
        return "no speed_rpm column (the AR(1) spindle term is driven by the speed)"
    if kind == "feed_axis" and not any(c.startswith("pos_") for c in log.columns):
        return "no pos_<axis>_mm column"
    speed = options.get("speed_input", "speed_rpm")
    if kind == "xi_spindle" and inputs and len([c for c in inputs if c != speed]) != 1:
        return "needs exactly one ξ sensor (--inputs, and the speed for the lift)"
    return None


Row = tuple[str, str, FitOutcome | None, str | None]


def fit_all(
    log: Log,
    inputs: list[str] | None,
    targets: list[str] | None,
    options: dict[str, Any],
    stage: Stage | None = None,
) -> list[Row]:
    """Every applicable kind on the same log: (kind, label, outcome or None, why skipped).

    Without `inputs` each kind takes its own defaults (every temperature for lvr, mlr and the
    feed axis; the ar1 structure sensors and the ξ sensor chosen held out); each is scored held
    out against MLR on its inputs (compd.identify.holdout), MLR itself too. With `stage` each kind
    is fitted on what the models before it leave (`fit_model`)."""
    tcols = default_targets(log, targets)
    single_axis = {"feed_axis", "ar1", "xi_spindle"}
    jobs: list[tuple[str, list[str]]] = []
    for kind in KINDS:
        if kind in single_axis:
            jobs += [(kind, [t]) for t in tcols]
        else:
            jobs.append((kind, tcols))
    known = {k: option_names(k) for k in KINDS}
    unknown = set(options) - set().union(*known.values())
    if unknown:
        raise BadInput(f"no model takes fit option {sorted(unknown)[0]!r}", path="--option")
    out: list[Row] = []
    for kind, tc in progress(jobs, desc="fitting"):
        label = kind if kind not in single_axis or len(tcols) == 1 else f"{kind}_{tc[0][4:-3]}"
        why = applicable(kind, log, inputs, options)
        if why is None:
            try:
                opts = {k: v for k, v in options.items() if k in known[kind]}
                out.append((kind, label, fit_model(kind, log, inputs, tc, opts, stage=stage), None))
                continue
            except (BadInput, ValueError) as e:
                why = str(e)
        out.append((kind, label, None, why))
    return out


def held_out_of(oc: FitOutcome, axis: str) -> float | None:
    """A fit's held-out RMSE on `axis` (µm), None where it could not be scored."""
    if "held_out_rmse_um" in oc.report:
        v = oc.report["held_out_rmse_um"].get(axis)
        return v if isinstance(v, float) else None
    return oc.report.get("baseline_mlr", {}).get("axes", {}).get(axis, {}).get("held_out_rmse_um")


def comparison_table(rows: list[Row]) -> str:
    """One line per model and axis: RMSE in sample (the rows it was fitted to) and held out
    (compd.identify.holdout), MLR held out on the same inputs, max error, fit time (the
    recommendation follows: `recommendation_lines`)."""
    lines = [
        f"{'model':<16} {'axis':<8} {'in-sample':>10} {'held-out':>9} {'MLR held':>9} {'max_um':>8}"
        f" {'fit_s':>7}  (RMSE um)"
    ]
    for _, label, oc, why in rows:
        if oc is None:
            lines.append(f"{label:<16} {'-':<8} {'-':>10} {'-':>9} {'-':>9} {'-':>8} {'-':>7}  skipped: {why}")
            continue
        for axis, s in oc.report["axes"].items():
            held = held_out_of(oc, axis)
            mlr = oc.report.get("baseline_mlr", {}).get("axes", {}).get(axis, {}).get("mlr_held_out_rmse_um")
            if oc.kind == "mlr":
                mlr = held
            f = lambda v: f"{v:>9.3f}" if v is not None else f"{'-':>9}"  # noqa: E731
            note = (
                f"  ruled out: {len(oc.blocking)} warning(s)"
                if oc.blocking
                else f"  {len(oc.warnings)} warning(s)"
                if oc.warnings
                else ""
            )
            lines.append(
                f"{label:<16} {axis:<8} {s['rmse_um']:>10.3f} {f(held)} {f(mlr)} {s['max_abs_err_um']:>8.3f}"
                f" {oc.report['fit_time_s']:>7.2f}{note}"
            )
    return "\n".join(lines + _stagewise_table(rows))


def _stagewise_table(rows: list[Row]) -> list[str]:
    """`--kind all --on-residual-of`: per kind and axis the held-out RMSE of the sum, the kind alone,
    the models before alone and MLR on every input (the report's `stagewise`)."""
    fits = [(label, oc) for _, label, oc, _ in rows if oc is not None and "stagewise" in oc.report]
    if not fits:
        return []
    first = " + ".join(fits[0][1].report["stagewise"]["first"])
    lines = [
        f"held out, each kind fitted on what {first} leaves ({first} as given, not refitted per fold):",
        f"{'model':<16} {'axis':<8} {'sum':>9} {'alone':>9} {'first':>9} {'MLR all':>9}  (RMSE um)",
    ]
    f = lambda v: f"{v:>9.3f}" if v is not None else f"{'-':>9}"  # noqa: E731
    for label, oc in fits:
        for axis, e in oc.report["stagewise"]["axes"].items():
            if not e["on_residual"]:
                lines.append(f"{label:<16} {axis:<8} {e['note']}")
                continue
            lines.append(
                f"{label:<16} {axis:<8} {f(e['sum_held_out_rmse_um'])} {f(e['alone_held_out_rmse_um'])}"
                f" {f(e['first_alone_rmse_um'])} {f(e['mlr_all_inputs_held_out_rmse_um'])}"
            )
    return lines


def read_profile(file: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A temperature profile CSV: two columns x (mm) and T (°C); a header row is optional."""
    x, t = [], []
    try:
        lines = Path(file).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise BadInput(f"cannot read profile: {e}", file=str(file)) from None
    for lineno, line in enumerate(lines, start=1):
        cells = [c.strip() for c in line.split(",")]
        if not line.strip():
            continue
        if len(cells) < 2:
            raise BadInput("a profile row needs two cells: x, T", file=str(file), line=lineno)
        try:
            xv, tv = float(cells[0]), float(cells[1])
        except ValueError:
            if lineno == 1:
                continue  # header
            raise BadInput(f"not a number in {cells[:2]}", file=str(file), line=lineno) from None
        if not (math.isfinite(xv) and math.isfinite(tv)):
            raise BadInput("not a finite number", file=str(file), line=lineno)
        x.append(xv)
        t.append(tv)
    if len(x) < 2:
        raise BadInput("a profile needs at least two rows", file=str(file))
    return np.asarray(x), np.asarray(t)


def warn(lines: list[str]) -> None:
    for w in lines:
        print(f"compd: warning: {w}", file=sys.stderr)


# --- `--kind all`'s recommendation (compd.commissioning.recommend) ---------------------------------

STAGE_NAMES = ("spindle", "structure")  # the contributions of a recommended sum: the spindle's heat, then the rest


def recommendation(
    log: Log, rows: list[Row], targets: list[str] | None, stage: Stage | None = None
) -> tuple[Any, list[Any]]:
    """`--kind all`'s pick over every target (compd.commissioning.recommend.choose) and the sums it
    weighed: for each spindle kind fitted (xi_spindle, ar1), that kind then MLR on the other
    temperatures, scored nested held out. (None, sums) when no candidate covers every target."""
    tcols = default_targets(log, targets)
    firsts = []
    if stage is None:  # a sum of stages on a log already less other models' predictions: not proposed
        for kind, _, oc, _ in rows:
            if oc is not None and kind in rec.SPINDLE_KINDS and not oc.blocking:
                for t in oc.report["targets"]:
                    firsts.append((kind, t, list(oc.fit_inputs), list(oc.model.inputs), dict(oc.held_options)))
    sums = rec.propose_sums(log, firsts)
    axes = [error_axis(t) or t for t in tcols]
    before = {a: _rms(log.col(t)) for a, t in zip(axes, tcols, strict=True)}
    return rec.choose(rec.candidates(rows, sums, held_out_of), axes, before), sums


def recommended_model_dict(pick: Any, log: Log) -> dict[str, Any]:
    """The model file of `--kind all`'s pick: the fitted kind's own file, or a file of two contributions
    (kind `contributions`: docs/formats.md) — each with its fit — and in either `fit.expected_unseen`:
    per axis the stated RMS and reduction with their ranges (compd.commissioning.recommend.Stated)."""
    cand = pick.candidate
    expected = {a: s.as_dict() for a, s in pick.stated.items()}
    selection = {
        "method": "held out (compd fit --kind all): the smallest held-out RMSE among the fits no warning rules"
        " out; a sum of two stages only where it beats the best single model by"
        f" {round((1 - SUM_MARGIN) * 100):g} %",
        "label": cand.label,
        "held_out_rmse_um": {a: round(v, 4) for a, v in cand.axes.items()},
    }
    if pick.runner_up is not None:
        selection["runner_up"] = {
            "label": pick.runner_up.label,
            "held_out_rmse_um": {a: round(v, 4) for a, v in pick.runner_up.axes.items()},
        }
    if cand.single is not None:
        doc = json.loads(json.dumps(cand.single.model.to_dict()))
        doc["fit"] = {**doc.get("fit", {}), "expected_unseen": expected, "recommended": selection}
        return doc
    so = cand.sum
    assert so is not None
    stamp = datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    parts = []
    for name, res, target in ((STAGE_NAMES[0], so.first, so.target), (STAGE_NAMES[1], so.second, so.target)):
        m = res.model
        d = json.loads(json.dumps(m.to_dict()))
        d["fit"] = {
            "fitted_at": stamp,
            "log": Path(log.file).name,
            "stage": 1 if name == STAGE_NAMES[0] else 2,
            "target": target if name == STAGE_NAMES[0] else f"{target} less the {STAGE_NAMES[0]} stage",
            "input_range": _input_range(m, log),
        }
        parts.append({"name": name, **d})
    inputs = list(dict.fromkeys(n for p in parts for n in p["inputs"]))
    fit = {
        "fitted_at": stamp,
        "compd_version": version(),
        "log": Path(log.file).name,
        "rows": int(np.isfinite(log.col(so.target)).sum()),
        "log_rows": len(log),
        "held_out_rmse_um": {so.axis: round(so.held_out_um, 4)},
        "held_out_method": "nested: in each fold both"
        " stages fitted without it (the second on what the first leaves), the fold predicted by their sum",
        "cancel_ratio": round(so.cancel_ratio, 3),
        "expected_unseen": expected,
        "recommended": selection,
        "input_range": {k: v for p in parts for k, v in p["fit"]["input_range"].items()},
    }
    return {
        "kind": "contributions",
        "inputs": inputs,
        "outputs": [so.axis],
        "params": {"contributions": parts},
        "fit": fit,
    }


def _input_range(model: Model, log: Log) -> dict[str, list[float]]:
    out = {}
    for name in model.inputs:
        col = log.col(name)
        seen = col[np.isfinite(col)]
        if seen.size:
            out[name] = [float(seen.min()), float(seen.max())]
    return out


def write_recommended(pick: Any, log: Log, path: str | Path) -> None:
    data = json.loads(json.dumps(recommended_model_dict(pick, log)))  # no YAML aliases for shared lists
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True), encoding="utf-8")


def recommendation_lines(pick: Any, sums: list[Any]) -> list[str]:
    """What `--kind all` prints of its pick: the sums weighed, the recommendation, what it will do."""
    lines = []
    for so in sums:
        lines.append(
            f"{so.label:<16} {so.axis:<8} {'-':>10} {so.held_out_um:>9.3f} {'-':>9} {'-':>8} {'-':>7}"
            f"  nested held out: {so.first_kind} on {', '.join(so.first.model.inputs)}, then mlr on"
            f" {', '.join(so.second_inputs)}" + (f"; cancels ({so.cancel_ratio:.1f})" if so.cancel_ratio > 2 else "")
        )
    if pick is None:
        return lines + ["no recommendation: no fit without a blocking warning covers every axis"]
    cand = pick.candidate
    held = ", ".join(f"{a} {v:.3f} um" for a, v in cand.axes.items())
    lines.append(f"recommended: {cand.label} (held-out RMSE {held})")
    lines += [s.line(a) for a, s in pick.stated.items()]
    return lines


def recommendation_report(pick: Any, sums: list[Any], path: Path) -> dict[str, Any]:
    """The `--kind all` report's `recommended` (the pick, its held-out figures and what it will do per
    axis, the runner-up) and `sums` (each sum weighed: its stages and nested held-out RMSE)."""
    out: dict[str, Any] = {
        "sums": {
            so.label: {
                "axis": so.axis,
                "first": {"kind": so.first_kind, "inputs": list(so.first.model.inputs)},
                "second": {"kind": "mlr", "inputs": list(so.second_inputs)},
                "held_out_rmse_um": so.held_out_um,
                "cancel_ratio": so.cancel_ratio,
                "warnings": so.warnings,
            }
            for so in sums
        }
    }
    if pick is not None:
        cand = pick.candidate
        out["recommended"] = {
            "label": cand.label,
            "file": str(path),
            "held_out_rmse_um": cand.axes,
            "expected_unseen": {a: s.as_dict() for a, s in pick.stated.items()},
            "runner_up": None
            if pick.runner_up is None
            else {"label": pick.runner_up.label, "held_out_rmse_um": pick.runner_up.axes},
        }
    return out
