"""`compd fit` / `compd predict` / `compd xi`: fit a model from a log (compd.identify), score it against MLR, write files."""

from __future__ import annotations

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
from compd.commissioning.scoring import score_residual
from compd.errors import BadInput
from compd.identify import FITS, KINDS, holdout, identify, option_names
from compd.identify.data import (
    HELD_OUT_METHOD,
    columns,
    default_targets,
    progress,
)
from compd.log import Log, error_axis, read_log
from compd.models.base import Model


@dataclass
class FitOutcome:
    """One fitted model with its scores and report (what `compd fit` prints and writes)."""

    kind: str
    model: Model
    report: dict[str, Any]
    pred: np.ndarray
    warnings: list[str] = field(default_factory=list)


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
    return holdout.held_out_rmse(log, targets, lambda lg: identify(kind, lg, inputs, targets, **options))


def compare_with_mlr(
    kind: str, log: Log, inputs: list[str], targets: list[str], options: dict[str, Any], axes: list[str],
    warnings: list[str],
) -> dict[str, Any]:
    """The fitted kind against MLR on the same log and the same inputs, both scored held out
    (`held_out_rmse`); a warning per axis where MLR predicts the unseen rows better."""
    try:
        ours = held_out_rmse(kind, log, inputs, targets, options)
        # MLR on temperature rises (the papers' baseline): a speed, position or current input stays out;
        # a model that takes none (the analytic feed axis) is compared with MLR on every one
        mlr_inputs = [c for c in inputs if c in log.temperature_columns()] or log.temperature_columns()
        mlr = held_out_rmse("mlr", log, mlr_inputs, targets, {})
    except (BadInput, ValidationError, np.linalg.LinAlgError, ValueError) as e:
        return {"skipped": f"the held-out comparison could not fit a fold: {e}"}
    out: dict[str, Any] = {
        "method": HELD_OUT_METHOD,
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


# a fit that leaves more than this share of the error's RMS, in sample, removes almost nothing
REMOVES_NOTHING = 0.9


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
) -> FitOutcome:
    """Fit `kind` (compd.identify), score it on the log, compare with MLR on the same targets."""
    FITS.get(kind, path="--kind")  # an unknown kind: BadInput naming --kind
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
    if result.report.get("converged") is False:
        warnings.append(f"{kind}: the fit did not converge ({result.report.get('optimizer', 'see report')})")
    if result.report.get("warning"):
        warnings.append(f"{kind}: {result.report['warning']}")
    for why in result.report.get("at_bounds", []) + result.report.get("lag", {}).get("at_bounds", []):
        warnings.append(f"{kind}: {why}")
    for axis, s in axes.items():
        before = _rms(log.matrix([t for t in tcols if error_axis(t) == axis] or tcols[:1])[:, 0])
        if before > 0 and s["rmse_um"] > REMOVES_NOTHING * before:
            warnings.append(
                f"{kind}: axis {axis}: the model removes almost nothing of the error it was fitted to"
                f" (RMSE {s['rmse_um']:.3f} um of {before:.3f} um in sample)"
            )
    report: dict[str, Any] = {
        "kind": kind,
        "log": log.file,
        "rows": len(log),
        "inputs": model.inputs,
        "targets": tcols,
        "fit_time_s": fit_s,
        "axes": axes,
        "details": result.report,
    }
    if baseline and kind != "mlr":
        held_options = dict(options)
        if "form" in result.report:  # score the form the fit kept (feed_axis form: auto)
            held_options["form"] = result.report["form"]
        # ... and the lead it kept: a fold refits the coefficients, not the lag search
        lead = result.model.params.model_dump().get("lead_s")
        led = {n: v for n, v in zip(model.inputs, lead or [], strict=False) if v > 0}
        held_options["lag"] = led or "off"
        # what the fit took as --inputs (a kind that chose its own says which)
        fit_inputs = inputs or result.report.get("fit_inputs")
        fit_inputs = list(model.inputs if fit_inputs is None else fit_inputs)
        report["baseline_mlr"] = compare_with_mlr(kind, log, fit_inputs, tcols, held_options,
                                                  model.outputs, warnings)
    if baseline and kind == "mlr":  # the baseline's own held-out figure (the probe adapter's σ_m, the tables)
        try:
            held = held_out_rmse("mlr", log, inputs, tcols, options)
            report["held_out_rmse_um"] = dict(zip(model.outputs, map(float, held), strict=True))
        except (BadInput, ValidationError, np.linalg.LinAlgError, ValueError) as e:
            report["held_out_rmse_um"] = {"skipped": f"the held-out comparison could not fit a fold: {e}"}
    report["warnings"] = warnings
    fit_info: dict[str, Any] = {
        "fitted_at": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "compd_version": version(),
        "log": Path(log.file).name,
        "rows": len(log),
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
    for key in ("selection", "q2", "press", "cv", "n_components", "ljung_box", "converged", "dt_s",
                "c2_at_unseen_speeds"):
        if key in result.report:
            fit_info[key] = result.report[key]
    model.fit_info = json.loads(json.dumps(fit_info))
    return FitOutcome(kind, model, report, pred, warnings)


def score_model(model: Model, log: Log) -> dict[str, Any]:
    """`compd score`: a fitted model on a log with the measured errors (a day it has not seen).

    Per axis the error before (`err_<axis>_um`) and after (error − prediction), scored as every
    report is (compd.commissioning.scoring); blank error cells between measurements are left out. The baseline
    is the fit report's: MLR on the model's temperature inputs (all the log's temperatures if it
    has none), each fold of this log predicted by an MLR fitted on the others (HELD_OUT_METHOD),
    beside the model's RMS on the same rows."""
    targets = [f"err_{a}_um" for a in model.outputs]
    Y = log.matrix(targets)  # a missing err_<axis>_um column is BadInput naming it
    pred = predict_log(model, log)
    axes = {axis: score_residual(Y[:, k], Y[:, k] - pred[:, k]) for k, axis in enumerate(model.outputs)}
    for axis, s in axes.items():
        if s["rows"] == 0:
            raise BadInput(f"no measured error to score axis {axis} against", file=log.file,
                           path=f"err_{axis}_um")
    temps = log.temperature_columns()
    mlr_inputs = [c for c in model.inputs if c in temps] or temps
    baseline: dict[str, Any] = {"method": HELD_OUT_METHOD, "inputs": mlr_inputs}
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
    return {"kind": model.kind, "log": log.file, "rows": len(log), "inputs": model.inputs,
            "axes": axes, "baseline_mlr": baseline}


def write_model(model: Model, path: str | Path) -> None:
    """The model YAML (kind, inputs, outputs, params, fit; docs/formats.md)."""
    data = json.loads(json.dumps(model.to_dict()))
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True), encoding="utf-8")


def load_model(path: str | Path) -> Model:
    """A model from its YAML file, validated like a config's `model: {kind, file}`."""
    from compd.config import load_model_file, resolve_model

    doc, data = load_model_file(path)
    p = Path(path).resolve()
    spec = resolve_model({"kind": data["kind"], "file": str(p)}, doc, (), p.parent)
    return spec.cls(spec.params, spec.inputs, spec.outputs, spec.fit)


def write_prediction(path: str | Path, t_s: np.ndarray, axes: list[str], pred: np.ndarray) -> None:
    """PRED.csv: t_s and one pred_<axis>_um column per axis."""
    from compd.log import write_log

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


def fit_all(log: Log, inputs: list[str] | None, targets: list[str] | None, options: dict[str, Any]) -> list[Row]:
    """Every applicable kind on the same log: (kind, label, outcome or None, why skipped).

    Without `inputs` each kind takes its own defaults (every temperature for lvr, mlr and the
    feed axis; the ar1 structure sensors and the ξ sensor chosen held out); each is scored held
    out against MLR on its inputs (compd.identify.holdout), MLR itself too."""
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
                out.append((kind, label, fit_model(kind, log, inputs, tc, opts), None))
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


def recommend(rows: list[Row]) -> dict[str, tuple[str, float]]:
    """Per axis, the fit with the smallest held-out RMSE among those without a warning: {axis: (label, µm)}.

    A fit that warns (a parameter at the edge of its search range, worse than MLR held out, removes
    almost nothing, did not converge) is never the recommendation."""
    best: dict[str, tuple[str, float]] = {}
    for _, label, oc, _ in rows:
        if oc is None or oc.warnings:
            continue
        for axis in oc.report["axes"]:
            v = held_out_of(oc, axis)
            if v is not None and (axis not in best or v < best[axis][1]):
                best[axis] = (label, v)
    return best


def comparison_table(rows: list[Row]) -> str:
    """One line per model and axis: RMSE in sample (the rows it was fitted to) and held out
    (compd.identify.holdout), MLR held out on the same inputs, max error, fit time; then the
    recommendation per axis."""
    lines = [f"{'model':<16} {'axis':<8} {'in-sample':>10} {'held-out':>9} {'MLR held':>9} {'max_um':>8}"
             f" {'fit_s':>7}  (RMSE um)"]
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
            note = f"  {len(oc.warnings)} warning(s)" if oc.warnings else ""
            lines.append(
                f"{label:<16} {axis:<8} {s['rmse_um']:>10.3f} {f(held)} {f(mlr)} {s['max_abs_err_um']:>8.3f}"
                f" {oc.report['fit_time_s']:>7.2f}{note}"
            )
    best = recommend(rows)
    for axis, (label, v) in best.items():
        lines.append(f"recommended for {axis}: {label} (held-out RMSE {v:.3f} um, no warning)")
    axes = {a for _, _, oc, _ in rows if oc is not None for a in oc.report["axes"]}
    for axis in sorted(axes - set(best)):
        lines.append(f"no recommendation for {axis}: every fit warns or could not be scored held out")
    return "\n".join(lines)


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
