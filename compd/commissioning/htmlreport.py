"""`compd report`: one self-contained HTML commissioning page from a fit report and a replay report."""

from __future__ import annotations

import base64
import html
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from compd.errors import BadInput

MAX_JSON_BYTES = 16 * 1024 * 1024


def read_report(path: str | Path, flag: str) -> dict[str, Any]:
    """A report JSON as a dict; a missing, unreadable or malformed file is BadInput (file, line, flag)."""
    p = Path(path)
    try:
        if p.stat().st_size > MAX_JSON_BYTES:
            raise BadInput(f"larger than {MAX_JSON_BYTES // 1024 // 1024} MiB: not a compd report", file=str(p), path=flag)
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
    figures: list[Figure] = field(default_factory=list)


def _png(fig: Any) -> bytes:
    from compd.commissioning.plots import pyplot

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

    from compd.commissioning import fitting
    from compd.commissioning.plots import pyplot

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
        return Figure(caption, why_not=f"not drawn: the replay report's {missing} file {replay.get(missing)!r} is not found")
    from compd.commissioning.plots import pyplot, trend_from_replay, write_trend
    from compd.commissioning.replay import replay_config, replay_model

    result = (replay_config if what == "config" else replay_model)(source, log_file)
    pyplot()
    buf = io.BytesIO()
    write_trend(trend_from_replay(result), buf, dpi=90)
    return Figure(caption, buf.getvalue())


def build_page(fit_file: str, replay_file: str, config_file: str | None = None,
               pngs: list[str] | None = None) -> Page:
    """Read and check both reports (BadInput on the first bad key) and draw the figures."""
    fit = read_report(fit_file, "--fit")
    check_fit(fit, fit_file)
    replay = read_report(replay_file, "--replay")
    check_replay(replay, replay_file)
    page = Page(fit, fit_file, replay, replay_file)
    if config_file is None and isinstance(replay.get("config"), str):
        found = find_beside(replay["config"], replay_file)
        config_file = str(found) if found else None
    if config_file is not None:
        try:
            page.config_text = Path(config_file).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise BadInput(f"cannot read: {getattr(e, 'strerror', None) or e}", file=config_file, path="--config") from None
        page.config_file = config_file
    model_file = find_beside(fit.get("model"), fit_file)
    if model_file is not None:
        from compd.config import MODEL_MAX_BYTES, MODEL_MAX_VALUES, load_yaml

        doc = load_yaml(model_file, max_bytes=MODEL_MAX_BYTES, max_values=MODEL_MAX_VALUES)
        if isinstance(doc.data, dict) and isinstance(doc.data.get("params"), dict):
            page.model_params = doc.data["params"]
            page.model_file = str(model_file)
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
    return page


# ------------------------------------------------------------------- HTML

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1100px;
color:#222;padding:0 1em;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.8em}
table{border-collapse:collapse;margin:.6em 0}th,td{border:1px solid #ccc;padding:.25em .7em;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}.muted{color:#666}.warn{color:#a40}
pre{background:#f7f7f7;border:1px solid #ddd;padding:.8em;overflow-x:auto;font-size:.85em}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}figcaption{color:#444;font-size:.9em}
.good{color:#060}.bad{color:#a00}
"""


def _e(v: Any) -> str:
    return html.escape(str(v))


def _f(v: Any, digits: int = 2) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return _e(v)
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _table(head: list[str], rows: list[list[str]], left: int = 1) -> str:
    th = "".join(f'<th class="l">{h}</th>' if i < left else f"<th>{h}</th>" for i, h in enumerate(head))
    body = "".join(
        "<tr>" + "".join(f'<td class="l">{c}</td>' if i < left else f"<td>{c}</td>" for i, c in enumerate(r)) + "</tr>"
        for r in rows
    )
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _flat(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """Nested params as (dotted name, value) rows."""
    if isinstance(d, dict):
        out = []
        for k, v in d.items():
            out += _flat(v, f"{prefix}.{k}" if prefix else str(k))
        return out
    return [(prefix, d)]


def _text(v: Any, limit: int = 12) -> str:
    """A parameter as a person reads it: six significant digits, long lists cut after `limit` values."""
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        inner = ", ".join(_text(x, limit) for x in v[:limit])
        return f"[{inner}{f', … ({len(v)} values)' if len(v) > limit else ''}]"
    return "null" if v is None else str(v)


def _value(v: Any) -> str:
    return _e(_text(v))


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
    base = (fit.get("baseline_mlr") or {}).get("axes", {})
    head = ["axis", "RMSE on the fitting log / µm", "max |error| / µm"]
    if base:
        head += ["held-out RMSE / µm", "MLR baseline held-out RMSE / µm"]
    rows = []
    for axis, s in fit["axes"].items():
        r = [_e(axis), _f(s["rmse_um"]), _f(s.get("max_abs_err_um", "–"))]
        if base:
            b = base.get(axis, {})
            r += [_f(b.get("held_out_rmse_um", "–")), _f(b.get("mlr_held_out_rmse_um", "–"))]
        rows.append(r)
    out.append(_table(head, rows))
    method = (fit.get("baseline_mlr") or {}).get("method")
    if method:
        out.append(f'<p class="muted">Held out: {_e(method)}.</p>')
    skipped = (fit.get("baseline_mlr") or {}).get("skipped")
    if skipped:
        out.append(f'<p class="warn">No held-out comparison with MLR: {_e(skipped)}.</p>')
    for w in fit.get("warnings") or []:
        out.append(f'<p class="warn">warning: {_e(w)}</p>')
    if page.model_params is not None:
        out.append(f"<h3>Coefficients (<code>{_e(page.model_file)}</code>, params)</h3>")
        out.append(_table(["name", "value"], [[_e(k), _value(v)] for k, v in _flat(page.model_params)], left=2))
    details = fit.get("details")
    if isinstance(details, dict) and details:
        out.append("<h3>Fit details</h3>")
        out.append(_table(["name", "value"], [[_e(k), _value(v)] for k, v in _flat(details)], left=2))
    return "\n".join(out)


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
    out.append(f'<p class="muted">{"; ".join(facts)}</p>')
    rows = []
    for axis, s in rep["axes"].items():
        red = s["reduction_pct"]
        cls = "good" if red >= 50 else "bad"
        rows.append([_e(axis), _f(s["rms_before_um"]), _f(s["rms_after_um"]), _f(s.get("max_abs_before_um", "–")),
                     _f(s["max_abs_after_um"]), f'<span class="{cls}">{red:.1f} %</span>'])
    out.append(_table(["axis", "RMS before / µm", "RMS after / µm", "max |error| before / µm",
                       "max |error| after / µm", "reduction"], rows))
    faults = rep.get("faults") or {}
    text = ", ".join(f"{_e(k)}: {_e(v)}" for k, v in faults.items()) if faults else "none"
    out.append(f"<p>Guard events during the replay (the report's <code>faults</code>, by kind): {text}.</p>")
    return "\n".join(out)


def summary_section(page: Page) -> str:
    """At a glance: the unseen day's reduction per axis and the fit's held-out RMSE against MLR."""
    items = []
    for axis, r in page.replay["axes"].items():
        items.append(f"<li>axis {_e(axis)}, unseen day: RMS {r['rms_before_um']:.2f} → {r['rms_after_um']:.2f} µm,"
                     f" <b>{r['reduction_pct']:.0f} % less</b>; largest error left {r['max_abs_after_um']:.2f} µm</li>")
    for axis, b in ((page.fit.get("baseline_mlr") or {}).get("axes") or {}).items():
        own, mlr = b.get("held_out_rmse_um"), b.get("mlr_held_out_rmse_um")
        if isinstance(own, (int, float)) and isinstance(mlr, (int, float)):
            verdict = ('<span class="good">better than</span>' if own < mlr
                       else '<span class="bad">not better than</span>')
            items.append(f"<li>axis {_e(axis)}, fit: held-out RMSE {own:.2f} µm, {verdict} the MLR baseline"
                         f" ({mlr:.2f} µm)</li>")
    faults = {k: v for k, v in (page.replay.get("faults") or {}).items() if str(k).startswith(("fault", "bad"))}
    if faults:
        items.append(f'<li class="warn">the replay had guard faults or bad inputs: '
                     f'{_e(", ".join(f"{k} {v}" for k, v in faults.items()))}</li>')
    return "<h2>At a glance</h2><ul>" + "".join(items) + "</ul>"


def figures_section(page: Page) -> str:
    out = ["<h2>Plots</h2>"]
    for fig in page.figures:
        if fig.png is None:
            out.append(f'<p class="warn">{_e(fig.caption)}: {_e(fig.why_not)}</p>')
            continue
        uri = "data:image/png;base64," + base64.b64encode(fig.png).decode("ascii")
        out.append(f'<figure><img src="{uri}" alt="{_e(fig.caption)}"><figcaption>{_e(fig.caption)}</figcaption></figure>')
    return "\n".join(out)


def config_section(page: Page) -> str:
    if page.config_text is None:
        return '<h2>The config</h2><p class="muted">No config given (--config CONFIG.yaml).</p>'
    return f"<h2>The config: <code>{_e(page.config_file)}</code></h2><pre>{_e(page.config_text)}</pre>"


def render(page: Page) -> str:
    """The page as one HTML document: no scripts, no external resources, images as data URIs."""
    from compd import __version__

    axes = ", ".join(page.replay["axes"])
    title = f"compd commissioning report: {page.fit['kind']} on {axes}"
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1>",
        f'<p class="muted">Made by compd {_e(__version__)} from <code>{_e(page.fit_file)}</code> and'
        f" <code>{_e(page.replay_file)}</code>.</p>",
        summary_section(page), fit_section(page), replay_section(page), figures_section(page), config_section(page),
        "</body></html>",
    ]) + "\n"


def write_report(out: str | Path, fit_file: str, replay_file: str, config_file: str | None = None,
                 pngs: list[str] | None = None) -> Page:
    """Build the page and write it to `out`."""
    page = build_page(fit_file, replay_file, config_file, pngs)
    Path(out).write_text(render(page), encoding="utf-8")
    return page
