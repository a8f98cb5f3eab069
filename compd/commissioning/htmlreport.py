"""`compd report`: one self-contained HTML commissioning record from a fit report and a replay report."""

from __future__ import annotations

import base64
import html
import io
import json
import math
import unicodedata
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from compd import __version__
from compd.commissioning import fitting
from compd.commissioning.plots import pyplot, trend_from_replay, write_trend
from compd.commissioning.replay import replay_config, replay_model
from compd.commissioning.thermaltest import DEFAULT_EVERY_MIN, ThermalTest, plot_png, thermal_test
from compd.core.config import MODEL_MAX_BYTES, MODEL_MAX_VALUES, load_yaml
from compd.core.errors import BadInput
from compd.identify.data import ambient_columns
from compd.log import read_log

MAX_JSON_BYTES = 16 * 1024 * 1024
RECORD_TEXT_MAX = 200  # characters of one record field (--machine, --operator, --instrument): one line
AMBIENT_LIMITS_C = (-40.0, 60.0)  # the air of a shop; a value beyond is a typo (or °F)
UNIX_TIME_FROM_S = 1e9  # a log whose t_s is at least this (2001-09-09) is on Unix time, else on its own clock


def read_report(path: str | Path, flag: str) -> dict[str, Any]:
    """A report JSON as a dict; a missing, unreadable or malformed file is BadInput (file, line, flag)."""
    p = Path(path)
    try:
        if p.stat().st_size > MAX_JSON_BYTES:
            raise BadInput(
                f"larger than {MAX_JSON_BYTES // 1024 // 1024} MiB: not a compd report", file=str(p), path=flag
            )
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise BadInput(f"cannot read: {e.strerror or e}", file=str(p), path=flag) from None
    except UnicodeDecodeError:
        raise BadInput("not a UTF-8 text file: not a compd report", file=str(p), path=flag) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise BadInput(f"not JSON: {e.msg} (column {e.colno})", file=str(p), line=e.lineno, path=flag) from None
    if not isinstance(data, dict):
        raise BadInput(f"a report is a JSON object, not {type(data).__name__}", file=str(p), path=flag)
    return data


def _number(data: dict[str, Any], keys: tuple[str, ...], file: str) -> float:
    """data[k1][k2]... as a finite number, or BadInput naming the key path."""
    v: Any = data
    for k in keys:
        if not isinstance(v, dict) or k not in v:
            raise BadInput("missing", file=file, path=keys)
        v = v[k]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BadInput(f"not a finite number: {v!r}", file=file, path=keys)
    return float(v)


def _axes(data: dict[str, Any], file: str, hint: str) -> dict[str, Any]:
    axes = data.get("axes")
    if not isinstance(axes, dict) or not axes or not all(isinstance(v, dict) for v in axes.values()):
        raise BadInput(f"no per-axis figures (an `axes` object of objects): not {hint}", file=file, path="axes")
    return axes


def check_fit(data: dict[str, Any], file: str) -> None:
    """The keys the page shows of a `compd fit --report` JSON, or BadInput naming the first bad one."""
    if "kind" not in data and data and all(isinstance(v, dict) and "kind" in v for v in data.values()):
        raise BadInput("holds several fits (compd fit --kind all): give one kind's report", file=file, path="--fit")
    if not isinstance(data.get("kind"), str):
        raise BadInput("missing or not a string: not a `compd fit --report` file", file=file, path="kind")
    for axis in _axes(data, file, "a `compd fit --report` file"):
        _number(data, ("axes", axis, "rmse_um"), file)
        if "max_abs_err_um" in data["axes"][axis]:
            _number(data, ("axes", axis, "max_abs_err_um"), file)
    base = data.get("baseline_mlr")
    if base is not None:
        if not isinstance(base, dict) or not isinstance(base.get("axes", {}), dict):
            raise BadInput("not an object with per-axis figures", file=file, path="baseline_mlr")
        for axis, fig in base.get("axes", {}).items():
            for k in ("held_out_rmse_um", "mlr_held_out_rmse_um"):
                if not isinstance(fig, dict) or k in fig:
                    _number(data, ("baseline_mlr", "axes", axis, k), file)


REPLAY_KEYS = ("rms_before_um", "rms_after_um", "max_abs_after_um", "reduction_pct")


def check_replay(data: dict[str, Any], file: str) -> None:
    """The keys the page shows of a `compd replay --report` JSON, or BadInput naming the first bad one."""
    for axis in _axes(data, file, "a `compd replay --report` file"):
        for k in REPLAY_KEYS:
            _number(data, ("axes", axis, k), file)
    for k in ("rows", "codes_sent", "saturated"):
        if k in data:
            _number(data, (k,), file)
    if "faults" in data and not isinstance(data["faults"], dict):
        raise BadInput("not an object (count by kind)", file=file, path="faults")


def find_beside(name: Any, report: str) -> Path | None:
    """A file a report names: as written (relative to where the command ran), else beside the report."""
    if not isinstance(name, str) or not name:
        return None
    p = Path(name)
    for cand in (p, Path(report).parent / p) if not p.is_absolute() else (p,):
        if cand.is_file():
            return cand
    return None


# ------------------------------------------------------------------- the record's own facts

RECORD_OPTIONS = {
    "machine": "--machine",
    "operator": "--operator",
    "instrument": "--instrument",
    "ambient_c": "--ambient-c",
}


@dataclass(frozen=True)
class Record:
    """What the plant files with the figures and no report holds: the machine, who ran the test,
    what measured the error, the shop's air during the test (°C: one reading, or the lowest and
    the highest), and when the page was made (None: now)."""

    machine: str | None = None
    operator: str | None = None
    instrument: str | None = None
    ambient_c: tuple[float, ...] = ()
    made_at: datetime | None = None

    def missing(self) -> list[str]:
        """The options of the fields not given, in the page's order."""
        return [flag for key, flag in RECORD_OPTIONS.items() if not getattr(self, key)]


def record_text(value: str | None, flag: str) -> str | None:
    """A record field as given: one line of text (≤ RECORD_TEXT_MAX characters), or BadInput naming the option."""
    if value is None:
        return None
    text = value.strip()
    if not text:
        raise BadInput("empty: give the text, or leave the option out (the page then says it was not given)", path=flag)
    if any(unicodedata.category(c) in ("Cc", "Zl", "Zp") for c in text):
        raise BadInput("one line of text, without control characters (a newline, a tab)", path=flag)
    if len(text) > RECORD_TEXT_MAX:
        raise BadInput(f"{len(text)} characters: at most {RECORD_TEXT_MAX} (one line of the record)", path=flag)
    return text


def make_record(
    machine: str | None = None,
    operator: str | None = None,
    instrument: str | None = None,
    ambient_c: list[float] | tuple[float, ...] | None = None,
    made_at: datetime | None = None,
) -> Record:
    """The record from `compd report`'s options, each checked (BadInput names the option)."""
    temps = tuple(ambient_c or ())
    if len(temps) > 2:
        raise BadInput(f"one temperature, or the lowest and the highest: {len(temps)} values given", path="--ambient-c")
    lo, hi = AMBIENT_LIMITS_C
    for t in temps:
        if not (math.isfinite(t) and lo <= t <= hi):
            raise BadInput(
                f"{t:g} °C is not the air of a shop ({lo:g} to {hi:g} °C; in °C, not °F)", path="--ambient-c"
            )
    return Record(
        record_text(machine, "--machine"),
        record_text(operator, "--operator"),
        record_text(instrument, "--instrument"),
        tuple(sorted(temps)),
        made_at,
    )


@dataclass
class LogFacts:
    """What a log that a report names covers: rows, first and last t_s, when the file was last
    written, and the range of each column named for the air; or why it was not read."""

    role: str  # "fit", "unseen day"
    name: str | None  # as the report names it
    why_not: str = ""
    rows: int = 0
    first_t_s: float = math.nan
    last_t_s: float = math.nan
    modified: datetime | None = None
    ambient_c: dict[str, tuple[float, float]] = field(default_factory=dict)  # column → (lowest, highest), °C


def log_facts(role: str, report: dict[str, Any], report_file: str, flag: str) -> LogFacts:
    """The facts of the log `report` names (looked up as written, then beside the report)."""
    name = report.get("log")
    if not isinstance(name, str) or not name:
        return LogFacts(role, None, why_not=f"the {flag} report names no log")
    path = find_beside(name, report_file)
    if path is None:
        return LogFacts(role, name, why_not=f"not found (looked up as written and beside {report_file})")
    import numpy as np

    try:
        log = read_log(path, allow_nan=True)
    except BadInput as e:
        return LogFacts(role, name, why_not=f"could not be read: {e}")
    facts = LogFacts(role, name, rows=len(log))
    if len(log):
        facts.first_t_s, facts.last_t_s = float(log.t_s[0]), float(log.t_s[-1])
    try:
        facts.modified = datetime.fromtimestamp(path.stat().st_mtime, UTC)
    except OSError:
        facts.modified = None
    for col in ambient_columns(log):
        v = log.col(col)
        v = v[np.isfinite(v)]
        if v.size:
            facts.ambient_c[col] = (float(v.min()), float(v.max()))
    return facts


@dataclass
class Figure:
    """An image for the page: PNG bytes and a caption, or why it could not be drawn."""

    caption: str
    png: bytes | None = None
    why_not: str = ""


@dataclass
class Page:
    """Everything the page shows."""

    fit: dict[str, Any]
    fit_file: str
    replay: dict[str, Any]
    replay_file: str
    config_text: str | None = None
    config_file: str | None = None
    model_params: dict[str, Any] | None = None
    model_file: str | None = None
    model_fit: dict[str, Any] | None = None  # the model file's `fit` block (fitted_at, compd_version)
    model_why_not: str = ""  # why the model file's params are not shown
    figures: list[Figure] = field(default_factory=list)
    record: Record = field(default_factory=Record)
    logs: list[LogFacts] = field(default_factory=list)
    thermal: ThermalTest | None = None  # the thermal test's figures, None: not shown (thermal_why_not)
    thermal_why_not: str = ""
    thermal_from: str = ""  # where its log came from, in words
    thermal_png: bytes | None = None


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    pyplot().close(fig)
    return buf.getvalue()


def fit_figure(fit: dict[str, Any], fit_file: str) -> Figure:
    """The fit's model over its log: measured, predicted and residual per axis."""
    caption = "The fit: measured and predicted thermal error over the fitting log"
    given = find_beside(fit.get("plot"), fit_file)
    if given is not None and given.suffix.lower() == ".png":
        return Figure(caption + f" ({given.name}, from compd fit --plot)", given.read_bytes())
    model_file = find_beside(fit.get("model"), fit_file)
    log_file = find_beside(fit.get("log"), fit_file)
    if model_file is None or log_file is None:
        missing = "model" if model_file is None else "log"
        return Figure(caption, why_not=f"not drawn: the fit report's {missing} file {fit.get(missing)!r} is not found")
    import numpy as np

    model = fitting.load_model(model_file)
    log = fitting.read_fit_log(log_file)
    pred = fitting.predict_log(model, log)
    plt = pyplot()
    axes = [a for a in model.outputs if f"err_{a}_um" in log.columns]
    if not axes:
        return Figure(caption, why_not=f"not drawn: {log_file.name} has no err_<axis>_um column of the model's axes")
    fig, panels = plt.subplots(len(axes), 1, figsize=(11, 2.8 * len(axes)), squeeze=False, sharex=True)
    t_h = (log.t_s - log.t_s[0]) / 3600.0
    for ax, axis in zip(panels[:, 0], axes, strict=True):
        k = model.outputs.index(axis)
        e = log.col(f"err_{axis}_um")
        ax.plot(t_h, e, ".", ms=2, color="0.4", label="measured")
        ax.plot(t_h, pred[:, k], lw=1.2, color="tab:blue", label="predicted")
        ax.plot(t_h, e - pred[:, k], lw=0.8, color="tab:red", label="residual")
        ax.axhline(0.0, color="0.7", lw=0.5)
        ax.set_ylabel(f"{axis} error / µm")
        rmse = float(np.sqrt(np.nanmean((e - pred[:, k]) ** 2)))
        ax.set_title(f"{model.kind}, axis {axis}: RMSE {rmse:.2f} µm on {log_file.name}", fontsize=9, loc="left")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
        ax.grid(True, color="0.92", lw=0.6)
    panels[-1, 0].set_xlabel("time since the first row / h")
    fig.tight_layout()
    return Figure(caption, _png(fig))


def replay_figure(replay: dict[str, Any], replay_file: str) -> Figure:
    """The replay's trend (compd.commissioning.plots), replayed again from the log and config or model it names."""
    caption = "The unseen day: replayed through model, guard and codec into a software copy of the output device"
    log_file = find_beside(replay.get("log"), replay_file)
    what = "config" if "config" in replay else "model"
    source = find_beside(replay.get(what), replay_file)
    if log_file is None or source is None:
        given = find_beside(replay.get("plot"), replay_file)
        if given is not None and given.suffix.lower() == ".png":
            return Figure(caption + f" ({given.name}, from compd replay --plot)", given.read_bytes())
        missing = "log" if log_file is None else what
        return Figure(
            caption, why_not=f"not drawn: the replay report's {missing} file {replay.get(missing)!r} is not found"
        )
    result = (replay_config if what == "config" else replay_model)(source, log_file)
    pyplot()
    buf = io.BytesIO()
    write_trend(trend_from_replay(result), buf, dpi=90)
    return Figure(caption, buf.getvalue())


def thermal_from_files(log_file: str | Path, model_file: str | Path | None, every_s: float) -> ThermalTest:
    """The thermal test's figures of a log file and a model file (its prediction over the whole log,
    from a cold start as `compd predict` gives it); BadInput for a bad file, or a model input the log lacks."""
    log = fitting.read_fit_log(log_file)
    if len(log) == 0:
        raise BadInput("the log has no rows", file=str(log_file))
    if model_file is None:
        return thermal_test(log, every_s=every_s)
    model = fitting.load_model(model_file)
    for name in model.inputs:
        if name not in log.columns:
            raise BadInput(
                f"column {name!r}, an input of {Path(model_file).name}, is not in the log", file=str(log_file)
            )
    return thermal_test(log, list(model.outputs), fitting.predict_log(model, log), str(model_file), every_s)


def load_thermal(page: Page, test_log: str | None, test_model: str | None, every_s: float) -> None:
    """The thermal test's figures on `page`: from `test_log` (default: the log the fit report
    names) and `test_model` (default: the fit report's model file). What the options name and
    cannot be read is BadInput; what the fit report names and is gone, the section says."""
    fit, fit_file = page.fit, page.fit_file
    given = test_log is not None or test_model is not None
    if test_log is None:
        found = find_beside(fit.get("log"), fit_file)
        if found is None:
            why = (
                f"the log {fit['log']!r} that {fit_file} names is not found (looked up as written and beside"
                f" {fit_file}): give it with --test-log"
                if isinstance(fit.get("log"), str)
                else f"{fit_file} names no log: give the test's log with --test-log"
            )
            if given:
                raise BadInput(why, path="--test-log")
            page.thermal_why_not = why
            return
        log_file, page.thermal_from = str(found), f"the log the fit report {fit_file} names"
    else:
        log_file, page.thermal_from = test_log, "--test-log"
    model_file: str | None = test_model
    no_model = ""
    if model_file is None:
        found = find_beside(fit.get("model"), fit_file)
        model_file = str(found) if found else None
        if found is None:
            no_model = (
                f"no model: the model file {fit['model']!r} that {fit_file} names is not found (give --model)"
                if isinstance(fit.get("model"), str)
                else f"no model: {fit_file} names none (give --model)"
            )
    try:
        tt = thermal_from_files(log_file, model_file, every_s)
    except BadInput as e:
        if given:
            raise
        page.thermal_why_not = f"the test's figures could not be computed: {e}"
        return
    for ax in tt.axes:
        if ax.predicted_um is None and no_model:
            ax.why_no_prediction = no_model
    page.thermal = tt


def build_page(
    fit_file: str,
    replay_file: str,
    config_file: str | None = None,
    pngs: list[str] | None = None,
    record: Record | None = None,
    *,
    test_log: str | None = None,
    test_model: str | None = None,
    every_s: float = DEFAULT_EVERY_MIN * 60.0,
) -> Page:
    """Read and check both reports (BadInput on the first bad key), compute the thermal test's
    figures (`load_thermal`), read what the logs cover and draw the figures."""
    fit = read_report(fit_file, "--fit")
    check_fit(fit, fit_file)
    replay = read_report(replay_file, "--replay")
    check_replay(replay, replay_file)
    page = Page(fit, fit_file, replay, replay_file, record=record or Record())
    load_thermal(page, test_log, test_model, every_s)  # before any drawing: a bad --test-log fails at once
    if config_file is None and isinstance(replay.get("config"), str):
        found = find_beside(replay["config"], replay_file)
        config_file = str(found) if found else None
    if config_file is not None:
        try:
            page.config_text = Path(config_file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise BadInput(
                f"cannot read: {getattr(e, 'strerror', None) or e}", file=config_file, path="--config"
            ) from None
        page.config_file = config_file
    model_file = find_beside(fit.get("model"), fit_file)
    if model_file is not None:
        doc = load_yaml(model_file, max_bytes=MODEL_MAX_BYTES, max_values=MODEL_MAX_VALUES)
        if isinstance(doc.data, dict) and isinstance(doc.data.get("params"), dict):
            page.model_params = doc.data["params"]
            page.model_file = str(model_file)
            page.model_fit = doc.data["fit"] if isinstance(doc.data.get("fit"), dict) else {}
        else:
            page.model_why_not = f"{model_file} has no `params` mapping: not a compd model file"
    elif isinstance(fit.get("model"), str):
        page.model_why_not = (
            f"the model file {fit['model']!r} that {fit_file} names is not found"
            f" (looked up as written and beside {fit_file})"
        )
    else:
        page.model_why_not = f"{fit_file} names no model file (a report of compd fit --kind all, or an older compd)"
    page.logs = [log_facts("fit", fit, fit_file, "--fit"), log_facts("unseen day", replay, replay_file, "--replay")]
    for png in pngs or []:
        try:
            data = Path(png).read_bytes()
        except OSError as e:
            raise BadInput(f"cannot read: {e.strerror or e}", file=png, path="--png") from None
        if not data.startswith(b"\x89PNG\r\n\x1a\n"):
            raise BadInput("not a PNG file", file=png, path="--png")
        page.figures.append(Figure(Path(png).name, data))
    if not pngs:
        page.figures = [fit_figure(fit, fit_file), replay_figure(replay, replay_file)]
    if page.thermal is not None:
        page.thermal_png = plot_png(page.thermal)
        if test_log is not None:
            page.logs.append(log_facts("thermal test", {"log": test_log}, "./", "--test-log"))
    return page


# ------------------------------------------------------------------- what an empty value means

NOT_SET_C0 = "set when the daemon starts: the readings at start are the reference (the file fixes none)"


def _feed_axis_form(params: dict[str, Any]) -> str:
    if params.get("field") is not None:
        return "field"
    if params.get("position_poly") is not None:
        return "position-regression"
    return "analytic"


def why_param_empty(kind: str, name: str, params: dict[str, Any]) -> str:
    """Why a model file's parameter `name` (dotted) is empty (null), in the words of its kind
    (docs/formats.md, the model file; docs/configuration.md, model: kind …, params)."""
    key = name.rsplit(".", 1)[-1]
    if key == "t0_c":
        return NOT_SET_C0
    if kind == "xi_spindle":
        if name == "xi_mm":
            return (
                "not recorded: where the ξ sensor sits is documentation only, the model does not use it"
                " (compd xi --profile finds the point)"
            )
        if name == "lift":
            return "not used: no centrifugal lift, the fit had no speed input (--inputs T_xi speed_rpm fits it)"
        if name == "radial":
            return "not used: no radial output (the bearing-ring model is fitted with a second, radial target)"
        if name == "radial.k_um_per_rpm2":
            return "not used: the lift is the model's `lift` (this key is how older files carried it)"
    if kind == "ar1":
        if name == "c2_exponent":
            return (
                "not set: outside the C2 table, C2 is linear from (0, 0) below the first speed and held above"
                " the last (the rule of files written before the key)"
            )
        if name == "c3_um_per_k":
            return "not used by this ar1 model: no ambient input (the paper's recursion without C3)"
    if kind == "feed_axis":
        form = _feed_axis_form(params)
        analytic_only = (
            "chi_per_m",
            "eta",
            "u1_k",
            "u2_k",
            "slide_volume_m3",
            "power_w",
            "r_cu_ohm",
            "cooling_time_s",
            "ref_power_w",
        )
        if form != "analytic" and name in analytic_only:
            return f"not used by the {form} form (a parameter of the analytic form)"
        if name in ("field", "position_poly"):
            return f"not used: the model is in the {form} form"
        if name == "slide_volume_m3":
            return "not given: η is per m³ of the slide (the rule of files written before the key)"
        if name == "power_w":
            return "not fixed: the motor loss comes from the current input"
        if name == "r_cu_ohm":
            return "not used: the motor loss is the constant power_w"
        if name in ("cooling_time_s", "ref_power_w"):
            return "not used: no duty-cycle form, the paper's heating run from rest"
        if name == "linear_p0_mm":
            return "not used: the output is E at the axis's position (no straight line K0 + tanβ (y − P0))"
    if kind in ("lvr", "mlr") and name in ("rise_mean_k", "rise_cov_k2"):
        return (
            "not recorded in the model file: without the fit data's rises the model has no degraded mode"
            " for a bad input"
        )
    return (
        f"empty in the model file: the {kind} model takes the rule for an absent value"
        f" (docs/configuration.md, model: kind {kind}, params)"
    )


def why_detail_empty(name: str, value: Any) -> str:
    """Why a figure of the fit report's `details` is empty or not finite."""
    key = name.rsplit(".", 1)[-1]
    if "held_out_rmse" in name:  # compd.identify scores a choice it could not fit on a fold as inf
        return "not computed: a fit of this choice failed on a held-out fold"
    if value is None:
        if key == "library_span":
            return "not used: the whole log is the sample library (no --option library_span)"
        return "empty in the fit report: nothing of this in this fit"
    return f"not computed ({value})"


# ------------------------------------------------------------------- HTML

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1100px;
color:#222;padding:0 1em;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}\
h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.8em}
table{border-collapse:collapse;margin:.6em 0}th,td{border:1px solid #ccc;padding:.25em .7em;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}.muted{color:#666}.warn{color:#a40}
pre{background:#f7f7f7;border:1px solid #ddd;padding:.8em;overflow-x:auto;font-size:.85em}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}figcaption{color:#444;font-size:.9em}
.good{color:#060}.bad{color:#a00}.none{color:#777;font-style:italic}
table.record{width:100%}table.record th{width:13em;vertical-align:top}table.record td{text-align:left}
table.sign{width:100%;margin-top:1em}table.sign th,table.sign td{text-align:left}
table.sign td{height:3.2em;vertical-align:middle}table.sign td.role{width:24%}table.sign td.name{width:30%}
table.sign td.date{width:16%}table.sign td.signature{width:30%}
.remarks{border:1px solid #ccc;height:6em;padding:.3em .7em;color:#666;margin-top:1em}
table.measure{font-size:.85em}table.measure td,table.measure th{padding:.1em .5em}
@page{size:A4;margin:14mm 12mm 14mm 12mm}
@media print{
body{max-width:none;margin:0;padding:0;font-size:9.5pt;line-height:1.3;color:#000}
h1{font-size:15pt}h2{font-size:12pt;margin-top:1.2em;break-after:avoid;page-break-after:avoid}
h3{break-after:avoid;page-break-after:avoid}
tr,figure,table.record,.signoff{break-inside:avoid;page-break-inside:avoid}
.signoff{break-before:auto}
th{background:#eee !important;-webkit-print-color-adjust:exact;print-color-adjust:exact}
th,td{padding:.15em .5em}
pre{white-space:pre-wrap;overflow-wrap:anywhere;font-size:7.5pt;overflow:visible}
figure img{max-width:100%;max-height:240mm}
.muted,.none{color:#444}
}
"""


def _e(v: Any) -> str:
    return html.escape(str(v))


def _none(why: str) -> str:
    """An empty value on the page: why it is empty, never a bare null or a blank."""
    return f'<span class="none">{_e(why)}</span>'


def _f(v: Any, digits: int = 2, why: str = "not in the report") -> str:
    """A figure to `digits` decimals; an absent or non-finite one says why."""
    if v is None:
        return _none(why)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return _e(_text(v))
    if isinstance(v, float) and not math.isfinite(v):
        return _none(f"not computed ({v})")
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _table(head: list[str], rows: list[list[str]], left: int = 1, cls: str = "") -> str:
    th = "".join(f'<th class="l">{h}</th>' if i < left else f"<th>{h}</th>" for i, h in enumerate(head))
    body = "".join(
        "<tr>" + "".join(f'<td class="l">{c}</td>' if i < left else f"<td>{c}</td>" for i, c in enumerate(r)) + "</tr>"
        for r in rows
    )
    attr = f' class="{cls}"' if cls else ""
    return f"<table{attr}><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _flat(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """Nested params as (dotted name, value) rows."""
    if isinstance(d, dict):
        out = []
        for k, v in d.items():
            out += _flat(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    return [(prefix, d)]


def _text(v: Any, limit: int = 12) -> str:
    """A value as a person reads it: six significant digits, yes/no, long lists cut after `limit` values."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else "not computed"
    if isinstance(v, list):
        inner = ", ".join(_text(x, limit) for x in v[:limit])
        return f"[{inner}{f', … ({len(v)} values)' if len(v) > limit else ''}]"
    return "none" if v is None else str(v)


def _empty(v: Any) -> bool:
    return v is None or (isinstance(v, float) and not math.isfinite(v))


def _when(dt: datetime) -> str:
    """A date and time with its offset from UTC, to the minute."""
    off = dt.utcoffset()
    if off is None or off.total_seconds() == 0:
        return f"{dt:%Y-%m-%d %H:%M} UTC"
    minutes = int(off.total_seconds() // 60)
    sign = "+" if minutes >= 0 else "−"
    return f"{dt:%Y-%m-%d %H:%M} UTC{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"


def _span(lf: LogFacts) -> str:
    """What a log covers, in words: its rows, its first and last t_s, when the file was last written."""
    if lf.why_not:
        what = f"<code>{_e(lf.name)}</code>: " if lf.name else ""
        return what + _none(lf.why_not)
    head = f"<code>{_e(lf.name)}</code>, {lf.rows} rows"
    if lf.rows == 0:
        return head + ": " + _none("no rows, so no time span")
    first, last = lf.first_t_s, lf.last_t_s
    span = f"t_s {first:.1f} s to {last:.1f} s ({(last - first) / 3600:.2f} h)"
    if first >= UNIX_TIME_FROM_S:
        t0, t1 = (datetime.fromtimestamp(t, UTC) for t in (first, last))
        span += f": {_when(t0)} to {_when(t1)}"
    else:
        span += " on the log's own clock (compd's t_s is not a calendar time)"
    written = (
        f"; the file was last written {_when(lf.modified.astimezone())}"
        if lf.modified
        else "; " + _none("when the file was written is not known")
    )
    return f"{head}, {span}{written}"


def _ambient(page: Page) -> str:
    """The air during the test: as stated (--ambient-c), and as the logs' columns named for the air read it."""
    rec = page.record
    parts = []
    if len(rec.ambient_c) == 2:
        parts.append(f"{rec.ambient_c[0]:.1f} to {rec.ambient_c[1]:.1f} °C (as stated, --ambient-c)")
    elif rec.ambient_c:
        parts.append(f"{rec.ambient_c[0]:.1f} °C (as stated, --ambient-c)")
    else:
        parts.append(_none("not given (use --ambient-c)"))
    logged = []
    for lf in page.logs:
        for col, (lo, hi) in lf.ambient_c.items():
            logged.append(f"{_e(col)} read {lo:.1f} to {hi:.1f} °C in <code>{_e(lf.name)}</code> ({_e(lf.role)})")
    read = [lf for lf in page.logs if not lf.why_not]
    if logged:
        parts.append("; ".join(logged))
    elif len(read) == len(page.logs) > 0:
        parts.append(_none("the logs have no column named for the air (amb, room, air)"))
    elif read:
        parts.append(
            _none(
                f"{', '.join(str(lf.name) for lf in read)} has no column named for the air"
                " (amb, room, air); the other log was not read"
            )
        )
    else:
        parts.append(_none("no log read, so no logged air temperature"))
    return "<br>".join(parts)


def _model_made(page: Page) -> str:
    if page.model_fit is None:
        return _none(page.model_why_not or "no model file")
    at, version = page.model_fit.get("fitted_at"), page.model_fit.get("compd_version")
    if not isinstance(at, str) or not at:
        return f"<code>{_e(page.model_file)}</code>: " + _none(
            "the fit date is not recorded (a model file written before compd kept fitted_at)"
        )
    by = f" by compd {_e(version)}" if isinstance(version, str) and version else ""
    return f"<code>{_e(page.model_file)}</code>, fitted {_e(at.replace('T', ' ').replace('Z', ' UTC'))}{by}"


def record_section(page: Page, made_at: datetime) -> str:
    """Who, which machine, with what, in what air, when: the facts a plant files the page by."""
    rec = page.record

    def given(value: str | None, flag: str) -> str:
        return _e(value) if value else _none(f"not given (use {flag})")

    rows = [
        ("machine", given(rec.machine, "--machine")),
        ("operator (ran the test)", given(rec.operator, "--operator")),
        ("measuring instrument", given(rec.instrument, "--instrument")),
        ("ambient temperature during the test", _ambient(page)),
        *[(f"data: the {lf.role} log", _span(lf)) for lf in page.logs],
        ("model", _model_made(page)),
        (
            "this report",
            f"made {_when(made_at)} by compd {_e(__version__)} from <code>{_e(page.fit_file)}</code>"
            f" and <code>{_e(page.replay_file)}</code>",
        ),
    ]
    body = "".join(f'<tr><th class="l">{_e(k)}</th><td class="l">{v}</td></tr>' for k, v in rows)
    return f'<h2>The record</h2><table class="record"><tbody>{body}</tbody></table>'


def signoff_section(page: Page) -> str:
    """Lines to sign on paper: the commissioning engineer's and the plant owner's."""
    rows = "".join(
        f'<tr><td class="role">{role}</td><td class="name"></td><td class="date"></td><td class="signature"></td></tr>'
        for role in ("Commissioning engineer", "Plant owner")
    )
    machine = f" of {_e(page.record.machine)}" if page.record.machine else ""
    return (
        '<section class="signoff"><h2>Sign-off</h2>'
        f"<p>The commissioning engineer confirms that the thermal-error compensation{machine} was commissioned"
        " and measured as this record shows; the plant owner accepts it for production with the output"
        " enabled.</p>"
        '<table class="sign"><thead><tr><th>role</th><th>name</th><th>date</th><th>signature</th></tr></thead>'
        f"<tbody>{rows}</tbody></table>"
        '<div class="remarks">remarks:</div>'
        '<p class="muted">Name, date, signature and remarks are left empty on purpose: they are filled in by hand'
        " on the printed page.</p></section>"
    )


def fit_section(page: Page) -> str:
    fit = page.fit
    out = [f"<h2>The fit: {_e(fit['kind'])}</h2>"]
    facts = [f"report <code>{_e(page.fit_file)}</code>"]
    if "log" in fit:
        facts.append(f"log <code>{_e(fit['log'])}</code>")
    if "rows" in fit:
        facts.append(f"{_e(fit['rows'])} rows")
    if isinstance(fit.get("inputs"), list):
        facts.append("inputs " + ", ".join(f"<code>{_e(x)}</code>" for x in fit["inputs"]))
    out.append(f'<p class="muted">{"; ".join(facts)}</p>')
    baseline = fit.get("baseline_mlr") or {}
    base = baseline.get("axes", {})
    head = ["axis", "RMSE on the fitting log / µm", "max |error| / µm"]
    if base:
        head += ["held-out RMSE / µm", "MLR baseline held-out RMSE / µm"]
    rows = []
    for axis, s in fit["axes"].items():
        r = [
            _e(axis),
            _f(s["rmse_um"]),
            _f(s.get("max_abs_err_um"), why="not in the fit report (written by an older compd)"),
        ]
        if base:
            b = base.get(axis) or {}
            why = "not computed for this axis"
            r += [_f(b.get("held_out_rmse_um"), why=why), _f(b.get("mlr_held_out_rmse_um"), why=why)]
        rows.append(r)
    out.append(_table(head, rows))
    method = baseline.get("method")
    if method:
        text = method if str(method).lower().startswith("held out") else f"held out: {method}"
        out.append(f'<p class="muted">{_e(text[:1].upper() + text[1:])}.</p>')
    skipped = baseline.get("skipped")
    if skipped:
        out.append(f'<p class="warn">No held-out comparison with MLR: {_e(skipped)}.</p>')
    elif not base:
        out.append(
            f'<p class="warn">No held-out comparison with MLR: {_e(page.fit_file)} has no'
            " <code>baseline_mlr</code> figures.</p>"
        )
    for w in fit.get("warnings") or []:
        out.append(f'<p class="warn">warning: {_e(w)}</p>')
    if page.model_params is not None:
        kind = str(fit["kind"])
        params = page.model_params
        rows = [
            [_e(k), _none(why_param_empty(kind, k, params)) if v is None else _e(_text(v))] for k, v in _flat(params)
        ]
        out.append(f"<h3>Coefficients (<code>{_e(page.model_file)}</code>, params)</h3>")
        out.append(_table(["name", "value"], rows, left=2))
    else:
        out.append(f'<h3>Coefficients</h3><p class="warn">Not shown: {_e(page.model_why_not)}.</p>')
    details = fit.get("details")
    if isinstance(details, dict) and details:
        rows = [[_e(k), _none(why_detail_empty(k, v)) if _empty(v) else _e(_text(v))] for k, v in _flat(details)]
        out.append("<h3>Fit details</h3>")
        out.append(_table(["name", "value"], rows, left=2))
    return "\n".join(out)


IDLE_WHERE = {
    "start": "at the start: the machine at rest, the environment alone",
    "end": "at the end: the cool-down after the last run, with the environment",
    "whole": "the whole log: the spindle never ran, the environment alone",
}


def _hours(t_s: float, t0_s: float) -> str:
    return f"{(t_s - t0_s) / 3600.0:.2f}"


def thermal_section(page: Page) -> str:
    """The thermal test as ISO 230-3 evaluates it: per axis the drift from the first measurement,
    its largest value and range, the idle stretches' drift, and beside them the model's residual
    (what the machine would still show with the model compensating); the plot; every measurement."""
    out = ["<h2>The thermal test: drift per axis (ISO 230-3)</h2>"]
    tt = page.thermal
    if tt is None:
        out.append(f'<p class="warn">Not shown: {_e(page.thermal_why_not)}.</p>')
        return "\n".join(out)
    model = f"model <code>{_e(tt.model)}</code>" if tt.model else _none("no model")
    out.append(
        f'<p class="muted">log <code>{_e(tt.log)}</code> ({_e(page.thermal_from)}), {tt.rows} rows; {model};'
        " times from the log's first row.</p>"
    )
    out.append(
        "<p>Per axis, the <b>drift</b> is each measurement less the first one, and the test's figures are"
        " its largest absolute value (and when) and its range, the largest less the smallest measurement."
        " The <b>residual</b> is each measurement less the model's prediction at that row (the model run"
        " over the whole log from its first row): what the machine would still show with the model"
        " compensating. Its range is the same figure after compensation.</p>"
    )
    head = [
        "axis",
        "measured",
        "measurements",
        "first measurement / µm",
        "largest |drift| / µm",
        "at / h",
        "drift range / µm",
        "residual RMS / µm",
        "largest |residual| / µm",
        "residual range / µm",
    ]
    rows = []
    for ax in tt.axes:
        d, r = ax.drift(), ax.residual()
        row = [
            _e(ax.axis),
            f"<code>{_e(ax.source)}</code>, {_e(ax.sampled)}",
            str(ax.rows.size),
            _f(ax.first_um),
            _f(d.max_abs_um),
            _hours(d.at_t_s, tt.t0_s),
            _f(d.range_um),
        ]
        if r is None:
            why = ax.why_no_prediction or "the model's prediction is not finite at any measurement"
            row += [_none(why)] * 3
        else:
            row += [_f(r.rms_um), _f(r.max_abs_um), _f(r.range_um)]
        rows.append(row)
    out.append(_table(head, rows, left=2))
    for axis, why in tt.not_measured.items():
        out.append(f'<p class="warn">The model\'s axis {_e(axis)} is not measured: {_e(why)}.</p>')
    out.append("<h3>Idle stretches: the spindle stopped</h3>")
    if tt.idle:
        few = _none("fewer than two measurements in the stretch")
        rows = []
        for st in tt.idle:
            for ax in tt.axes:
                f = st.figures(ax)
                rng = few if f.range_um is None else _f(f.range_um)
                change = few if f.change_um is None else _f(f.change_um)
                res = (
                    _f(f.residual_range_um)
                    if f.residual_range_um is not None
                    else few
                    if f.range_um is None
                    else _none(ax.why_no_prediction or "no finite prediction in the stretch")
                )
                rows.append(
                    [
                        _e(IDLE_WHERE[st.where]),
                        _hours(st.from_t_s, tt.t0_s),
                        _hours(st.to_t_s, tt.t0_s),
                        _e(ax.axis),
                        str(f.measurements),
                        rng,
                        change,
                        res,
                    ]
                )
        out.append(
            _table(
                [
                    "stretch",
                    "from / h",
                    "to / h",
                    "axis",
                    "measurements",
                    "range / µm",
                    "last − first / µm",
                    "residual range / µm",
                ],
                rows,
            )
        )
        out.append(
            '<p class="muted">The stretch at the start, before the spindle first runs, is the environment\'s'
            " drift (ISO 230-3's environmental temperature variation error, for as long as the log has it);"
            " the stretch after the last run is mostly the machine cooling down.</p>"
        )
    else:
        out.append(f'<p class="muted">{_e(tt.idle_why_not)}.</p>')
    uri = "data:image/png;base64," + base64.b64encode(page.thermal_png or b"").decode("ascii")
    caption = "The thermal test: drift and residual over time per axis (µm)" + (
        ", under the spindle speed" if tt.speed_rpm is not None else ""
    )
    out.append(f'<figure><img src="{uri}" alt="{_e(caption)}"><figcaption>{_e(caption)}</figcaption></figure>')
    out.append(_measurements(tt))
    return "\n".join(out)


def _measurements(tt: ThermalTest) -> str:
    """Every measurement: time, the speed then, and per axis its drift, the model's prediction and
    the residual (an axis not measured at that row says so)."""
    import numpy as np

    every = np.unique(np.concatenate([ax.rows for ax in tt.axes]))
    speed = tt.speed_rpm
    head = ["time / h", "t_s / s"] + (["speed / rpm"] if speed is not None else [])
    for ax in tt.axes:  # an axis without a prediction has its drift only (the caption says why)
        head += [f"{_e(ax.axis)} drift / µm"]
        if ax.predicted_um is not None:
            head += [f"{_e(ax.axis)} model / µm", f"{_e(ax.axis)} residual / µm"]
    at = [dict(zip(ax.rows.tolist(), range(ax.rows.size), strict=True)) for ax in tt.axes]
    rows = []
    for i in every.tolist():
        row = [_hours(float(tt.t_s[i]), tt.t0_s), f"{tt.t_s[i]:.1f}"]
        if speed is not None:
            v = float(speed[i])
            row.append(_f(v if math.isfinite(v) else None, 0, why="not logged"))
        for ax, where in zip(tt.axes, at, strict=True):
            k = where.get(i)
            cols = 1 if ax.predicted_um is None else 3
            if k is None:
                row += [_none("not measured")] * cols
                continue
            row.append(_f(float(ax.drift_um[k])))
            if ax.predicted_um is not None:
                row += [_f(float(ax.predicted_um[k])), _f(float(ax.residual_um[k]))]  # type: ignore[index]
        rows.append(row)
    sources = "; ".join(
        f"{_e(ax.axis)}: <code>{_e(ax.source)}</code>, first measurement {ax.first_um:.2f} µm"
        + (f" (no model or residual: {_e(ax.why_no_prediction)})" if ax.predicted_um is None else "")
        for ax in tt.axes
    )
    return (
        f"<h3>The measurements ({every.size})</h3>"
        f'<p class="muted">{sources}. The drift is the measurement less the first one; the residual is the'
        " measurement less the model.</p>" + _table(head, rows, left=0, cls="measure")
    )


def _limits(rep: dict[str, Any]) -> str:
    """The replayed device's limits (the report's device_limits), an absent one said as what it means."""
    lim = rep.get("device_limits")
    if not isinstance(lim, dict):
        return ""
    res, top, rate = lim.get("resolution_um"), lim.get("max_abs_um"), lim.get("max_rate_um_per_s")
    num = (int, float)
    parts = [
        f"resolution {res:g} µm" if isinstance(res, num) else "resolution not in the report",
        f"largest correction {top:g} µm"
        if isinstance(top, num)
        else "no clamp of its own (only guard.max_abs_um clamps)",
        f"at most {rate:g} µm/s" if isinstance(rate, num) else "no rate limit of its own",
    ]
    return "device limits: " + ", ".join(parts)


def replay_section(page: Page) -> str:
    rep = page.replay
    out = ["<h2>The unseen day: replay</h2>"]
    facts = [f"report <code>{_e(page.replay_file)}</code>"]
    for key, label in (("log", "log"), ("config", "config"), ("model", "model")):
        if isinstance(rep.get(key), str):
            facts.append(f"{label} <code>{_e(rep[key])}</code>")
    for key, label in (("rows", "rows"), ("codes_sent", "codes sent"), ("saturated", "saturated words")):
        if key in rep:
            facts.append(f"{_e(rep[key])} {label}")
    if "device" in rep:
        facts.append(f"device {_e(rep['device'])}")
    elif "plc" in rep:
        facts.append(f"PLC {_e(rep['plc'])}")
    if _limits(rep):
        facts.append(_e(_limits(rep)))
    if isinstance(rep.get("inhibit"), str):
        facts.append(f"inhibit: {_e(rep['inhibit'])}")
    out.append(f'<p class="muted">{"; ".join(facts)}</p>')
    adapted = any(isinstance(s.get("without_adaptation"), dict) for s in rep["axes"].values())
    rows = []
    for axis, s in rep["axes"].items():
        red = s["reduction_pct"]
        cls = "good" if red >= 50 else "bad"
        row = [
            _e(axis),
            _f(s["rms_before_um"]),
            _f(s["rms_after_um"]),
            _f(s.get("max_abs_before_um"), why="not in the replay report (written by an older compd)"),
            _f(s["max_abs_after_um"]),
            f'<span class="{cls}">{red:.1f} %</span>',
        ]
        if adapted:
            plain = s.get("without_adaptation")
            if isinstance(plain, dict):
                row += [_f(plain.get("rms_after_um")), _f(plain.get("reduction_pct"), 1)]
            else:
                row += [_none("no probes of this axis in the log")] * 2
        rows.append(row)
    head = [
        "axis",
        "RMS before / µm",
        "RMS after / µm",
        "max |error| before / µm",
        "max |error| after / µm",
        "reduction",
    ]
    if adapted:
        head += ["RMS after, model alone / µm", "reduction, model alone / %"]
    out.append(_table(head, rows))
    if adapted:
        out.append(
            '<p class="muted">The log has probe columns: "after" is with the probes adapting the model;'
            ' "model alone" is the same replay with the probes ignored.</p>'
        )
    faults = rep.get("faults") or {}
    text = ", ".join(f"{_e(k)}: {_e(v)}" for k, v in faults.items()) if faults else "none"
    out.append(f"<p>Guard events during the replay (the report's <code>faults</code>, by kind): {text}.</p>")
    return "\n".join(out)


def summary_section(page: Page) -> str:
    """At a glance: the unseen day's reduction per axis and the fit's held-out RMSE against MLR."""
    items = []
    for axis, r in page.replay["axes"].items():
        items.append(
            f"<li>axis {_e(axis)}, unseen day: RMS {r['rms_before_um']:.2f} → {r['rms_after_um']:.2f} µm,"
            f" <b>{r['reduction_pct']:.0f} % less</b>; largest error left {r['max_abs_after_um']:.2f} µm</li>"
        )
    for axis, b in ((page.fit.get("baseline_mlr") or {}).get("axes") or {}).items():
        own, mlr = b.get("held_out_rmse_um"), b.get("mlr_held_out_rmse_um")
        if isinstance(own, (int, float)) and isinstance(mlr, (int, float)):
            verdict = (
                '<span class="good">better than</span>' if own < mlr else '<span class="bad">not better than</span>'
            )
            items.append(
                f"<li>axis {_e(axis)}, fit: held-out RMSE {own:.2f} µm, {verdict} the MLR baseline ({mlr:.2f} µm)</li>"
            )
    tt = page.thermal
    for ax in tt.axes if tt is not None else []:
        d, r = ax.drift(), ax.residual()
        left = f"; left with the model: range {r.range_um:.2f} µm, RMS {r.rms_um:.2f} µm" if r is not None else ""
        items.append(
            f"<li>axis {_e(ax.axis)}, thermal test: largest drift <b>{d.max_abs_um:.2f} µm</b>,"
            f" range {d.range_um:.2f} µm{left}</li>"
        )
    faults = {k: v for k, v in (page.replay.get("faults") or {}).items() if str(k).startswith(("fault", "bad"))}
    if faults:
        items.append(
            f'<li class="warn">the replay had guard faults or bad inputs: '
            f"{_e(', '.join(f'{k} {v}' for k, v in faults.items()))}</li>"
        )
    return "<h2>At a glance</h2><ul>" + "".join(items) + "</ul>"


def figures_section(page: Page) -> str:
    out = ["<h2>Plots</h2>"]
    for fig in page.figures:
        if fig.png is None:
            out.append(f'<p class="warn">{_e(fig.caption)}: {_e(fig.why_not)}</p>')
            continue
        uri = "data:image/png;base64," + base64.b64encode(fig.png).decode("ascii")
        out.append(
            f'<figure><img src="{uri}" alt="{_e(fig.caption)}"><figcaption>{_e(fig.caption)}</figcaption></figure>'
        )
    return "\n".join(out)


def config_section(page: Page) -> str:
    if page.config_text is None:
        return (
            '<h2>The config</h2><p class="muted">Not shown: no config given (--config CONFIG.yaml), and the'
            " replay report names none (a replay of a bare model file).</p>"
        )
    return f"<h2>The config: <code>{_e(page.config_file)}</code></h2><pre>{_e(page.config_text)}</pre>"


def render(page: Page) -> str:
    """The page as one HTML document: no scripts, no external resources, images as data URIs."""
    made_at = page.record.made_at or datetime.now().astimezone()
    axes = ", ".join(page.replay["axes"])
    what = f"{page.fit['kind']} on {axes}"
    title = (
        f"compd commissioning report: {page.record.machine}, {what}"
        if page.record.machine
        else f"compd commissioning report: {what}"
    )
    return (
        "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en"><head><meta charset="utf-8">',
                '<meta name="viewport" content="width=device-width, initial-scale=1">',
                f"<title>{_e(title)}</title><style>{CSS}</style></head><body>",
                f"<h1>{_e(title)}</h1>",
                '<p class="muted">Thermal-error compensation: the record of its commissioning, made'
                f" {_when(made_at)}.</p>",
                record_section(page, made_at),
                summary_section(page),
                fit_section(page),
                thermal_section(page),
                replay_section(page),
                figures_section(page),
                config_section(page),
                signoff_section(page),
                "</body></html>",
            ]
        )
        + "\n"
    )


def write_report(
    out: str | Path,
    fit_file: str,
    replay_file: str,
    config_file: str | None = None,
    pngs: list[str] | None = None,
    record: Record | None = None,
    *,
    test_log: str | None = None,
    test_model: str | None = None,
    every_s: float = DEFAULT_EVERY_MIN * 60.0,
) -> Page:
    """Build the page and write it to `out`."""
    page = build_page(
        fit_file, replay_file, config_file, pngs, record, test_log=test_log, test_model=test_model, every_s=every_s
    )
    Path(out).write_text(render(page), encoding="utf-8")
    return page
