"""Fit reports a person reads: the JSON report and the PNG (measured, predicted, residual; LVR influence; E(y))."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from compd.commissioning.fitting import clone
from compd.core.errors import BadInput
from compd.identify.data import columns
from compd.log import Log
from compd.models.feed_axis import error_profile_um


def write_json(path: str | Path, data: Any) -> None:
    """JSON with plain types (numpy scalars converted)."""

    def plain(o: Any) -> Any:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(f"not JSON: {type(o).__name__}")

    Path(path).write_text(json.dumps(data, indent=2, default=plain) + "\n", encoding="utf-8")


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise BadInput("--plot needs matplotlib: pip install 'compd[plot]'", path="--plot") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fit(outcome: Any, log: Log, path: str | Path) -> None:
    """Measured vs predicted vs residual over time per axis, plus the kind's own panel."""
    plt = _pyplot()
    model = outcome.model
    axes = model.outputs
    Y = columns(log, outcome.report["targets"])
    t_h = (log.t_s - log.t_s[0]) / 3600.0
    extra = outcome.kind in ("lvr", "feed_axis")
    n = len(axes) + extra
    fig, panels = plt.subplots(n, 1, figsize=(10, 3.2 * n), squeeze=False)
    panels = panels[:, 0]
    for k, axis in enumerate(axes):
        ax = panels[k]
        s = outcome.report["axes"][axis]
        ax.plot(t_h, Y[:, k], ".", ms=2, color="0.4", label="measured")
        ax.plot(t_h, outcome.pred[:, k], "-", lw=1.2, color="tab:blue", label="predicted")
        ax.plot(t_h, Y[:, k] - outcome.pred[:, k], "-", lw=0.8, color="tab:red", label="residual")
        ax.axhline(0.0, color="0.8", lw=0.5)
        ax.set_ylabel(f"{axis} error / µm")
        ax.set_title(f"{outcome.kind} — axis {axis}: RMSE {s['rmse_um']:.2f} µm, max {s['max_abs_err_um']:.2f} µm")
        ax.legend(loc="best", fontsize=8)
    panels[len(axes) - 1].set_xlabel("time / h")
    if outcome.kind == "lvr":
        _influence(panels[-1], outcome)
    elif outcome.kind == "feed_axis":
        _curves(panels[-1], outcome, log, Y[:, 0])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _influence(ax: Any, outcome: Any) -> None:
    """Paper 002's bar chart: standardised coefficient of each sensor per axis."""
    infl = outcome.report["details"]["influence"]
    names = list(infl)
    axes = outcome.model.outputs
    x = np.arange(len(names))
    width = 0.8 / len(axes)
    for k, axis in enumerate(axes):
        ax.bar(x + (k - (len(axes) - 1) / 2) * width, [infl[n][axis] for n in names], width, label=axis)
    ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("standardised coefficient")
    ax.set_title(f"sensor influence ({outcome.report['details']['n_components']} components)")
    ax.axhline(0.0, color="0.5", lw=0.5)
    ax.legend(fontsize=8)


def _curves(ax: Any, outcome: Any, log: Log, e: np.ndarray) -> None:
    """E(y) along the stroke at four heating times: the model's profile at that instant (line), and
    for the rows logged within ±`window` of it the measured error (dots) beside the model's
    prediction at those same rows (crosses): like with like, a misfit shows as dots off their
    crosses, not as dots from another time off a line of this one."""
    model = clone(outcome.model)
    X = log.matrix(model.inputs)
    t_rel, q = model.heating(X, log.t_s)
    pos = X[:, model._i_pos]
    pred = outcome.pred[:, 0]
    span = max(float(t_rel[-1]), 1.0)
    steps = np.diff(log.t_s)
    step = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 1.0
    window = max(2.0 * step, 120.0)  # thermal states hardly change in two minutes; strokes cover the axis
    p = model.params
    for frac in (0.25, 0.5, 0.75, 1.0):
        tt = frac * span
        if model.field_form:  # the field form's E(y) from the readings at that time
            y = p.stroke_start_mm + np.linspace(0.0, p.length_mm, 4 * p.segments + 1)
            row = X[min(int(np.searchsorted(t_rel, tt)), len(t_rel) - 1)]
            curve = model.field_profile_um(X, row, y)
        else:
            y, curve = error_profile_um(tt, float(np.interp(tt, t_rel, q)), p)
        line = ax.plot(y, curve, "-", lw=1.0, label=f"t = {tt / 60:.0f} min")[0]
        near = np.abs(t_rel - tt) <= window
        ax.plot(pos[near], e[near], ".", ms=4, color=line.get_color())
        ax.plot(pos[near], pred[near], "x", ms=4, color=line.get_color())
    ax.plot([], [], "k.", label="measured")
    ax.plot([], [], "kx", label="model, same rows")
    ax.set_xlabel("position / mm")
    ax.set_ylabel("E / µm")
    ax.set_title(
        f"E(t, y) along the stroke: lines the model at t; dots measured and crosses the model on the"
        f" rows within ±{window:.0f} s",
        fontsize=9,
    )
    ax.legend(fontsize=8, ncol=2)
