"""Trend plots a person reads: inputs, error, commanded and applied correction (µm), enable/fault bands."""

from __future__ import annotations

import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from compd.codec import byte_to_um, decode_byte
from compd.config import load_config
from compd.core.errors import BadInput
from compd.cycle.limiter import FAULT, RECOVERING
from compd.log import Log, is_temperature_column

# the colours every trend uses, so a reader learns them once
C_ERROR, C_RESIDUAL, C_PRED = "0.45", "tab:green", "tab:purple"
C_GUARD, C_WORD, C_APPLIED = "tab:orange", "tab:blue", "tab:red"
C_DISABLED, C_FAULT = "0.85", "tab:red"


@dataclass
class Trend:
    """What a trend plot draws; arrays are rows × axes unless said otherwise, NaN where unknown."""

    t_s: np.ndarray  # rows
    axes: list[str]  # the model's outputs
    signals: dict[str, np.ndarray]  # the model's inputs, by name (temperatures in °C)
    word: np.ndarray  # rows: the 16-bit word sent
    word_axes: list[str]  # the axes on the word's high byte, then its low byte
    lsb_um: float
    applied_um: np.ndarray  # what the device applied
    error_um: np.ndarray | None = None  # logged thermal error (err_<axis>_um)
    pred_um: np.ndarray | None = None  # the model's predicted error
    # a sum of contributions: (name, axis, each row's share of the axis's prediction)
    parts: list[tuple[str, str, np.ndarray]] = field(default_factory=list)
    corr_um: np.ndarray | None = None  # the guard's correction (before the word's LSB steps)
    fault: np.ndarray | None = None  # bool: the guard had the axis in fault (or recovering)
    fault_label: str = "guard fault or recovering"
    probe_um: np.ndarray | None = None  # probe measurements of the whole thermal error, NaN between
    # what the device was commanded (the word's correction, the NC's target); None: the word
    # decoded on the word's axes. Against `applied_um` it shows the device trailing.
    commanded_um: np.ndarray | None = None
    commanded_label: str = "commanded (word)"
    resolution_um: float | None = None  # the device's smallest step (a difference below it is no trailing)
    scores: dict[str, Any] = field(default_factory=dict)  # per axis: the replay report's figures
    title: str = ""
    notes: list[str] = field(default_factory=list)  # one-line remarks under the title


def decode_words(word: np.ndarray, lsb_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row and byte (high, low): the correction the word commands (µm) and its enable bit.

    Decoded with compd.codec (byte_to_um, decode_byte) through a 256-entry table."""
    table_um = np.array([byte_to_um(b, lsb_um) for b in range(256)])
    table_en = np.array([decode_byte(b).enable for b in range(256)])
    w = np.asarray(word, dtype=np.int64) & 0xFFFF
    bytes_ = np.stack([w >> 8, w & 0xFF], axis=1)
    return table_um[bytes_], table_en[bytes_]


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Start and end (exclusive) row of every run of True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist(), strict=True))


def _band(ax: Any, x: np.ndarray, mask: np.ndarray, color: str, alpha: float, label: str, hatch: bool = False) -> bool:
    """Shade the spans where `mask` holds (each row until the next), as one artist however many
    spans there are; True when anything was shaded."""
    runs = _runs(mask)
    if not runs:
        return False
    sliver = (x[-1] - x[0]) / max(len(x), 1) * 0.5  # a run of the last row: half a row wide
    spans = [(x[i], (x[j] if j < len(x) else x[-1] + sliver) - x[i]) for i, j in runs]
    style = {"facecolors": "none", "edgecolors": color, "hatch": "///"} if hatch else {"facecolors": color}
    ax.broken_barh(spans, (0, 1), transform=ax.get_xaxis_transform(), alpha=alpha, lw=0, label=label, zorder=0, **style)
    return True


def _time_axis(t_s: np.ndarray) -> tuple[np.ndarray, str]:
    span_s = float(t_s[-1] - t_s[0]) if len(t_s) else 0.0
    rel = t_s - t_s[0]
    if span_s >= 3 * 3600:
        return rel / 3600.0, "h"
    if span_s >= 180:
        return rel / 60.0, "min"
    return rel, "s"


LEGEND_ROWS = 8  # entries per legend column: a panel's legend never runs down past the panel


def _legend(ax: Any, handles: list[Any] | None = None, labels: list[str] | None = None, x: float = 1.01) -> None:
    """The panel's legend to its right, in as many columns as keep it within the panel's height."""
    if handles is None or labels is None:
        handles, labels = ax.get_legend_handles_labels()
    if handles:
        ncol = -(-len(handles) // LEGEND_ROWS)
        ax.legend(
            handles,
            labels,
            loc="upper left",
            bbox_to_anchor=(x, 1.0),
            fontsize=8 if ncol == 1 else 7,
            frameon=False,
            ncol=ncol,
            columnspacing=0.8,
            handlelength=1.5,
        )


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend, or BadInput naming the extra to install."""
    try:
        import matplotlib
    except ImportError:
        raise BadInput("plots need matplotlib: pip install 'compd[plot]'", path="--plot") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_trend(trend: Trend, path: str | Path, dpi: int = 100) -> None:
    """The trend as an image: the model's inputs, then per axis its error and its correction."""
    plt = pyplot()
    n = len(trend.t_s)
    if n == 0:
        raise BadInput("nothing to plot: no rows", file=str(path))
    x, unit = _time_axis(trend.t_s)
    word_um, word_en = decode_words(trend.word, trend.lsb_um)
    commanded = commanded_matrix(trend, word_um)
    has_err = trend.error_um is not None and bool(np.isfinite(trend.error_um).any())
    rows: list[tuple[str, int]] = [("inputs", -1)]
    for a in range(len(trend.axes)):
        if (
            trend.pred_um is not None
            or has_err
            and np.isfinite(trend.error_um[:, a]).any()
            or (  # type: ignore[index]
                trend.probe_um is not None and np.isfinite(trend.probe_um[:, a]).any()
            )
        ):
            rows.append(("error", a))
        rows.append(("correction", a))
        if np.isfinite(commanded[:, a]).any():
            rows.append(("trailing", a))
    heights = [0.6 if kind == "trailing" else 1.0 for kind, _ in rows]
    fig, panels = plt.subplots(
        len(rows),
        1,
        figsize=(12, 2.5 * sum(heights) + 0.6),
        sharex=True,
        squeeze=False,
        gridspec_kw={"height_ratios": heights},
    )
    panels = panels[:, 0]
    for ax, (kind, a) in zip(panels, rows, strict=True):
        if kind == "inputs":
            _inputs_panel(ax, x, trend)
        elif kind == "error":
            _error_panel(ax, x, trend, a)
        elif kind == "trailing":
            _trailing_panel(ax, x, trend, a, commanded[:, a])
        else:
            _correction_panel(ax, x, trend, a, commanded[:, a], word_en)
        ax.grid(True, color="0.92", lw=0.6)
        if kind != "inputs":  # the inputs panel places its own (it may have a right axis)
            _legend(ax)
    start = float(trend.t_s[0])
    if start > 1e9:  # Unix time (a wall clock): say when
        import datetime

        when = datetime.datetime.fromtimestamp(start, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
        panels[-1].set_xlabel(f"time since {when} / {unit}")
    else:
        panels[-1].set_xlabel(f"time since the first row (t_s = {start:.6g} s) / {unit}")
    lines = [trend.title or "compd trend"] + [w for note in trend.notes for w in textwrap.wrap(note, 140)]
    fig.suptitle("\n".join(lines), fontsize=10, x=0.01, ha="left", va="top", y=0.998)
    fig.tight_layout()  # leaves room for the suptitle's lines
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)


def _inputs_panel(ax: Any, x: np.ndarray, trend: Trend) -> None:
    temps = {k: v for k, v in trend.signals.items() if is_temperature_column(k)}
    others = {k: v for k, v in trend.signals.items() if k not in temps}
    for name, v in temps.items():
        ax.plot(x, v, lw=1, label=f"{name} (°C)")
    if not temps:
        ax.set_yticks([])
    ax.set_ylabel("temperature / °C")
    ax.set_title("the model's inputs", fontsize=9, loc="left")
    if not others:
        _legend(ax)
        return
    twin = ax.twinx()
    units = []
    for k, (name, v) in enumerate(others.items()):
        unit = name.rsplit("_", 1)[-1] if "_" in name else ""
        units.append(unit)
        twin.plot(
            x,
            v,
            lw=0.9,
            ls="--",
            color=("0.3", "tab:brown", "tab:olive", "tab:cyan")[k % 4],
            label=f"{name} ({unit}, right axis)" if unit else f"{name} (right axis)",
        )
    twin.set_ylabel(" / ".join(dict.fromkeys(u for u in units if u)) or "other inputs", fontsize=9)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = twin.get_legend_handles_labels()
    _legend(ax, h1 + h2, l1 + l2, x=1.07)


def _error_panel(ax: Any, x: np.ndarray, trend: Trend, a: int) -> None:
    axis = trend.axes[a]
    if trend.error_um is not None and np.isfinite(trend.error_um[:, a]).any():
        e = trend.error_um[:, a]
        ax.plot(x, e, lw=1, color=C_ERROR, label="error without compensation")
        ax.plot(
            x, e + trend.applied_um[:, a], lw=1, color=C_RESIDUAL, label="left with compensation\n(error + applied)"
        )
    if trend.pred_um is not None:
        ax.plot(x, trend.pred_um[:, a], lw=1, ls="--", color=C_PRED, label="predicted error (model)")
    for name, axis, share in trend.parts:
        if axis == trend.axes[a]:
            ax.plot(x, share, lw=0.9, ls=":", label=f"contribution {name}")
    if trend.probe_um is not None and np.isfinite(trend.probe_um[:, a]).any():
        ax.plot(x, trend.probe_um[:, a], "D", ms=4, color="black", label="probe (measured error)")
    ax.axhline(0.0, color="0.6", lw=0.5)
    ax.set_ylabel(f"{axis} error / µm")
    s = trend.scores.get(axis)
    head = f"axis {axis}: thermal error"
    if s:
        head += (
            f" — RMS {s['rms_before_um']:.2f} → {s['rms_after_um']:.2f} µm,"
            f" max |left| {s['max_abs_after_um']:.2f} µm ({s['reduction_pct']:.0f} % less)"
        )
    ax.set_title(head, fontsize=9, loc="left")


def commanded_matrix(trend: Trend, word_um: np.ndarray | None = None) -> np.ndarray:
    """What the device was commanded per row and axis (µm): the trend's `commanded_um`, else
    the word decoded on the word's axes; NaN where neither says."""
    if trend.commanded_um is not None:
        return np.asarray(trend.commanded_um, dtype=float)
    if word_um is None:
        word_um, _ = decode_words(trend.word, trend.lsb_um)
    out = np.full((len(trend.t_s), len(trend.axes)), np.nan)
    for slot, axis in enumerate(trend.word_axes[:2]):
        if axis in trend.axes:
            out[:, trend.axes.index(axis)] = word_um[:, slot]
    return out


def _correction_panel(ax: Any, x: np.ndarray, trend: Trend, a: int, commanded: np.ndarray, word_en: np.ndarray) -> None:
    axis = trend.axes[a]
    on_word = axis in trend.word_axes
    if trend.corr_um is not None:
        ax.plot(x, trend.corr_um[:, a], lw=0.8, color=C_GUARD, label="guard's correction")
    if np.isfinite(commanded).any():
        label = trend.commanded_label
        if on_word and trend.commanded_um is None:
            label += f", {'high' if trend.word_axes.index(axis) == 0 else 'low'} byte"
        ax.step(x, commanded, where="post", lw=2.2, alpha=0.55, color=C_WORD, label=label)
    if on_word:
        slot = trend.word_axes.index(axis)
        _band(ax, x, ~word_en[:, slot], C_DISABLED, 1.0, "disabled (enable bit off)")
    ax.step(x, trend.applied_um[:, a], where="post", lw=1, ls=(0, (4, 2)), color=C_APPLIED, label="applied (device)")
    if trend.fault is not None:
        _band(ax, x, trend.fault[:, a], C_FAULT, 0.5, trend.fault_label, hatch=True)
    ax.axhline(0.0, color="0.6", lw=0.5)
    ax.set_ylabel(f"{axis} correction / µm")
    where = "" if on_word else " (not on the word)"
    ax.set_title(f"axis {axis}: correction{where}, LSB {trend.lsb_um:g} µm", fontsize=9, loc="left")


def trailing_um(trend: Trend, a: int, commanded: np.ndarray | None = None) -> np.ndarray:
    """Per row, applied − commanded on axis `a` (µm): how far the device trails its command."""
    if commanded is None:
        commanded = commanded_matrix(trend)[:, a]
    return np.asarray(trend.applied_um[:, a], dtype=float) - commanded


def _trailing_panel(ax: Any, x: np.ndarray, trend: Trend, a: int, commanded: np.ndarray) -> None:
    """applied − commanded on its own scale: the device trailing its command (a PMC stepping at
    its rate, an NC ramping) shows however briefly it lasts or small it is beside the correction."""
    axis = trend.axes[a]
    d = trailing_um(trend, a, commanded)
    ok = np.isfinite(d)
    ax.fill_between(x, np.where(ok, d, 0.0), step="post", color=C_APPLIED, alpha=0.3, lw=0)
    ax.step(x, d, where="post", lw=0.9, color=C_APPLIED, label="applied − commanded")
    ax.axhline(0.0, color="0.6", lw=0.5)
    res = trend.resolution_um
    tol = 0.5 * res if res else 1e-6  # below half the device's step: the device's rounding, not trailing
    worst = float(np.max(np.abs(d[ok]))) if ok.any() else 0.0
    if worst <= tol:
        ax.set_ylim(-max(res or 1.0, 1e-3), max(res or 1.0, 1e-3))
        head = f"axis {axis}: applied − commanded — the device applied its command at every row"
    else:
        off = np.abs(d[ok]) > tol
        share = 100.0 * float(np.sum(np.diff(trend.t_s, append=trend.t_s[-1])[ok][off]))
        share /= max(float(trend.t_s[-1] - trend.t_s[0]), 1e-9)
        head = (
            f"axis {axis}: applied − commanded — the device trailing its command by up to {worst:.2f} µm,"
            f" {share:.1f} % of the time"
        )
    ax.set_ylabel("trailing / µm")
    ax.set_title(head, fontsize=9, loc="left")


# ------------------------------------------------------------- trends from a data log


def _axes_of(log: Log) -> list[str]:
    axes = []
    for c in log.columns:
        if c.startswith("applied_") and c.endswith("_um"):
            axes.append(c[len("applied_") : -3])
    return axes


def trend_from_log(log: Log, config: str | Path | None = None) -> Trend:
    """The trend of a running daemon's data log (docs/formats.md: `pred_`, `corr_`, `applied_`
    per axis and `word`); with the daemon's config, its codec (LSB, the word's axes) and the
    model's inputs, else LSB 1 µm, the logged axes in order and every temperature column."""
    axes = _axes_of(log)
    if len(log) == 0:
        raise BadInput("the log has no rows: nothing to plot", file=log.file)
    if not axes or "word" not in log.columns:
        raise BadInput(
            "not a log that compd wrote: it needs applied_<axis>_um and word columns"
            " (the daemon's log.path); for a simulator or machine log use compd replay --plot",
            file=log.file,
        )
    lsb_um = 1.0
    word_axes = axes[:2]
    inputs: list[str] | None = None
    notes = []
    k0_sink = False  # the config's sink sends the guard's correction (K0), not the word
    if config is not None:
        cfg = load_config(config)
        k0_sink = cfg.sink[1].kind == "siemens"
        lsb_um = cfg.codec.lsb_um
        inputs = list(cfg.model.inputs)
        word_axes = list(cfg.codec.axes or cfg.model.outputs[:2])
        missing = [a for a in word_axes if a not in axes]
        if missing:
            raise BadInput(
                f"the config's word axis {missing[0]!r} is not in the log (axes: {', '.join(axes)})",
                file=log.file,
                path="codec.axes",
            )
    else:
        notes.append("no --config: LSB 1 µm and the logged axes in order on the word")
    if inputs is None:
        inputs = [c for c in log.temperature_columns() if not c.startswith(("probe_pos_",))]
    signals = {name: log.col(name) for name in inputs if name in log.columns}
    w = log.col("word")
    if not np.isfinite(w).all() or (w < 0).any() or (w > 0xFFFF).any() or (w != np.round(w)).any():
        bad = int(np.flatnonzero(~np.isfinite(w) | (w < 0) | (w > 0xFFFF) | (w != np.round(w)))[0])
        raise BadInput(
            f"the word is not an integer 0..65535 (got {w[bad]:g} in the row at t_s = {log.t_s[bad]:g})",
            file=log.file,
            path="word",
        )

    def block(prefix: str) -> np.ndarray:
        return np.column_stack([log.col(f"{prefix}_{a}_um") for a in axes])

    pred = block("pred") if all(f"pred_{a}_um" in log.columns for a in axes) else None
    corr = block("corr") if all(f"corr_{a}_um" in log.columns for a in axes) else None
    err = None
    if any(f"err_{a}_um" in log.columns for a in axes):
        err = np.column_stack(
            [log.col(f"err_{a}_um") if f"err_{a}_um" in log.columns else np.full(len(log), np.nan) for a in axes]
        )
    fault = ~np.isfinite(pred) if pred is not None else None
    probe = probe_matrix(log, axes)
    applied = np.nan_to_num(block("applied"), nan=0.0)
    if not applied.any() and w.any():
        notes.append("applied is 0 throughout: observe mode, or a device that applies nothing")
    commanded = None
    if k0_sink:  # the NC is sent the guard's correction; without it logged nothing says what it was
        commanded = corr if corr is not None else np.full((len(log), len(axes)), np.nan)
    return Trend(
        t_s=log.t_s.copy(),
        axes=axes,
        signals=signals,
        word=w.astype(np.int64),
        word_axes=word_axes,
        lsb_um=lsb_um,
        applied_um=applied,
        error_um=err,
        pred_um=pred,
        corr_um=corr,
        fault=fault,
        fault_label="no prediction (guard fault)",
        title=f"compd trend of {Path(log.file).name}",
        notes=notes,
        probe_um=probe,
        commanded_um=commanded,
        commanded_label="commanded (K0, the guard's correction)" if k0_sink else "commanded (word)",
        parts=[
            (c[len(f"pred_{a}_") : -3], a, log.col(c))
            for a in axes
            for c in log.columns
            if c.startswith(f"pred_{a}_") and c.endswith("_um") and c != f"pred_{a}_um"
        ],
    )


def probe_matrix(log: Log, axes: list[str]) -> np.ndarray | None:
    """The `probe_<axis>_um` columns (NaN between probes) as rows × axes, or None without any."""
    if not any(f"probe_{a}_um" in log.columns for a in axes):
        return None
    return np.column_stack(
        [log.col(f"probe_{a}_um") if f"probe_{a}_um" in log.columns else np.full(len(log), np.nan) for a in axes]
    )


def trend_from_replay(result: Any) -> Trend:
    """The trend of a `compd replay` (a compd.commissioning.replay.ReplayResult): the guard's states give the
    fault bands (fault and recovering)."""
    ex = result.extra
    state = ex.get("guard_state")
    fault = None if state is None else (state == FAULT) | (state == RECOVERING)
    rep = result.report
    faults = rep.get("faults") or {}
    device = rep.get("device") or f"the software PLC ({rep.get('plc', '?')})"
    notes = [
        f"replayed into {device}: {rep.get('rows', len(result.t_s))} rows,"
        f" {rep.get('codes_sent', 0)} codes sent, {rep.get('saturated', 0)} saturated words,"
        f" guard events: {', '.join(f'{k} {v}' for k, v in faults.items()) or 'none'}"
    ]
    name = Path(str(ex.get("log", ""))).name
    limits = rep.get("device_limits") or {}
    return Trend(
        t_s=result.t_s,
        axes=list(result.axes),
        signals=dict(ex.get("signals", {})),
        word=result.word,
        word_axes=list(ex.get("word_axes", result.axes[:2])),
        lsb_um=float(ex.get("lsb_um", 1.0)),
        applied_um=result.applied_um,
        error_um=result.error_um,
        pred_um=ex.get("pred_um"),
        corr_um=ex.get("corr_um"),
        fault=fault,
        scores=dict(rep.get("axes", {})),
        title=f"compd replay of {name}" if name else "compd replay",
        notes=notes,
        probe_um=ex.get("probe_um"),
        commanded_um=ex.get("commanded_um"),
        commanded_label="commanded (the device's target)",
        resolution_um=limits.get("resolution_um"),
        parts=list(ex.get("parts") or []),
    )
