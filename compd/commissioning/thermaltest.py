"""The thermal test's own figures, as ISO 230-3 evaluates a test, beside the model's residual.

Per axis: the drift from the first measurement, its largest value and range, the idle stretches' drift.

A thermal test logs the machine's displacement at fixed intervals while the spindle runs its
speed spectrum (docs/formats.md, the log CSV): `probe_<axis>_um` at the rows where it was
measured, or `err_<axis>_um` measured continuously. The standard's figure of an axis is its
drift, each measurement less the first one, over the test, and the largest change; an idle
stretch (the spindle stopped at the start or the end) gives the environment's share. Beside
each measurement the fitted model's prediction and the residual (measurement − prediction),
what the machine would still show with the model compensating: the same figures on the
residual are the test's figure after compensation. Pure functions over a log; `plot` draws it.
"""

from __future__ import annotations

import io
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from compd.commissioning.plots import pyplot
from compd.core.errors import BadInput
from compd.log import Log, error_axis

DEFAULT_EVERY_MIN = 10.0  # the sampling of a continuous err_<axis>_um where the log has no probe rows
EVERY_MIN_LIMITS = (0.1, 24 * 60.0)  # from 6 s to a day between measurements


def probe_axis(name: str) -> str | None:
    """`probe_z_um` → `z`; None for other columns (`probe_pos_z_mm` included)."""
    if name.startswith("probe_") and name.endswith("_um") and len(name) > 9 and not name.startswith("probe_pos_"):
        return name[6:-3]
    return None


def measured_axes(log: Log) -> list[str]:
    """The axes the log measures (a `probe_<axis>_um` or `err_<axis>_um` column), in column order."""
    axes: list[str] = []
    for c in log.columns:
        a = probe_axis(c) or error_axis(c)
        if a is not None and a not in axes:
            axes.append(a)
    return axes


def check_every_min(every_min: float, flag: str = "--test-every-min") -> float:
    """The sampling interval in s, or BadInput naming the option."""
    lo, hi = EVERY_MIN_LIMITS
    if not (math.isfinite(every_min) and lo <= every_min <= hi):
        raise BadInput(f"{every_min:g} min: between {lo:g} and {hi:g} min between measurements", path=flag)
    return every_min * 60.0


def _finite_rows(log: Log, column: str) -> np.ndarray:
    return np.flatnonzero(np.isfinite(log.col(column)))


def every_rows(t_s: np.ndarray, rows: np.ndarray, every_s: float) -> np.ndarray:
    """Of `rows` (indices in time order), the first at or after each time t_first + k·every_s:
    a measurement every `every_s` from the first one, as a test measures at fixed intervals."""
    if rows.size == 0:
        return rows
    t = t_s[rows]
    k = np.floor((t - t[0]) / every_s + 1e-9)  # the interval each row falls in
    return rows[np.concatenate([[True], np.diff(k) > 0])]


@dataclass(frozen=True)
class DriftFigures:
    """An axis's drift over the test (µm): the largest |drift| and the `t_s` of its row, the smallest
    and the largest drift, and their range (the same as the measurements')."""

    max_abs_um: float
    at_t_s: float
    min_um: float
    max_um: float
    range_um: float


@dataclass(frozen=True)
class ResidualFigures:
    """The residual over the measurements with a finite prediction (µm): how many, its RMS, the
    largest |residual| and the `t_s` of its row, and its range (the drift left with compensation)."""

    rows: int
    rms_um: float
    max_abs_um: float
    at_t_s: float
    range_um: float


@dataclass(frozen=True)
class IdleFigures:
    """An axis inside an idle stretch: its measurements there, their range and change (last − first),
    and the residual's range (µm; None with fewer than two)."""

    measurements: int
    range_um: float | None
    change_um: float | None
    residual_range_um: float | None


@dataclass
class AxisDrift:
    """One axis's measurements over the test (µm), the model's prediction at the same rows."""

    axis: str
    source: str  # the column measured: probe_<axis>_um or err_<axis>_um
    sampled: str  # how its rows were chosen, in words
    rows: np.ndarray  # the log's rows of the measurements
    t_s: np.ndarray
    measured_um: np.ndarray
    predicted_um: np.ndarray | None  # None: the model does not predict this axis (or no model)
    why_no_prediction: str = ""

    @property
    def first_um(self) -> float:
        return float(self.measured_um[0])

    @property
    def drift_um(self) -> np.ndarray:
        """Each measurement less the first: the standard's drift."""
        return self.measured_um - self.measured_um[0]

    @property
    def residual_um(self) -> np.ndarray | None:
        """Measurement − prediction: what the machine would show with the model compensating."""
        return None if self.predicted_um is None else self.measured_um - self.predicted_um

    def drift(self) -> DriftFigures:
        """The largest |drift| and when, and the range (max − min) of the measurements."""
        d = self.drift_um
        k = int(np.argmax(np.abs(d)))
        return DriftFigures(
            float(abs(d[k])), float(self.t_s[k]), float(d.min()), float(d.max()), float(d.max() - d.min())
        )

    def residual(self) -> ResidualFigures | None:
        """RMS, largest |residual| and when, and the range of the residual (the drift left), over the
        measurements with a finite prediction; None without one."""
        r = self.residual_um
        if r is None:
            return None
        ok = np.isfinite(r)
        if not ok.any():
            return None
        rr, tt = r[ok], self.t_s[ok]
        k = int(np.argmax(np.abs(rr)))
        return ResidualFigures(
            int(ok.sum()), float(np.sqrt(np.mean(rr * rr))), float(abs(rr[k])), float(tt[k]), float(rr.max() - rr.min())
        )


@dataclass
class IdleStretch:
    """A stretch with the spindle stopped at the start or the end of the log: rows [first, end)."""

    where: str  # "start", "end", or "whole" (the spindle never ran)
    first: int
    end: int
    from_t_s: float
    to_t_s: float

    def figures(self, ax: AxisDrift) -> IdleFigures:
        """The axis's measurements inside the stretch: their count, the range and the change
        (last − first) of the measurement, and the range of the residual."""
        inside = (ax.rows >= self.first) & (ax.rows < self.end)
        m = ax.measured_um[inside]
        if m.size < 2:
            return IdleFigures(int(m.size), None, None, None)
        res = None
        r = ax.residual_um
        if r is not None:
            r = r[inside]
            r = r[np.isfinite(r)]
            res = float(r.max() - r.min()) if r.size >= 2 else None
        return IdleFigures(int(m.size), float(m.max() - m.min()), float(m[-1] - m[0]), res)


def idle_stretches(log: Log) -> tuple[list[IdleStretch], str]:
    """The stretches with speed_rpm 0 from the log's first row and up to its last (an empty cell
    is not a stop), and why there are none when there are none."""
    if "speed_rpm" not in log.columns:
        return [], "the log has no speed_rpm column: idle stretches are not found without it"
    n = len(log)
    t = log.t_s
    running = np.flatnonzero(log.col("speed_rpm") != 0)  # NaN != 0: an unknown speed is no stop
    if running.size == 0:
        return [IdleStretch("whole", 0, n, float(t[0]), float(t[-1]))], ""
    out = []
    if running[0] > 0:  # stopped until the row where it first runs
        out.append(IdleStretch("start", 0, int(running[0]), float(t[0]), float(t[running[0]])))
    if running[-1] < n - 1:  # stopped from the row after the last one it ran
        out.append(IdleStretch("end", int(running[-1]) + 1, n, float(t[running[-1] + 1]), float(t[-1])))
    why = "" if out else "the spindle runs at the log's first and last rows: no idle stretch at the start or the end"
    return out, why


@dataclass
class ThermalTest:
    """The figures of one thermal test's log (and of a model over it)."""

    log: str  # the log as named
    model: str | None  # the model file as named, None without one
    rows: int
    t0_s: float  # the log's first t_s: times are shown from it
    every_s: float
    speed_rpm: np.ndarray | None  # per row of the log, None without the column
    t_s: np.ndarray  # the log's t_s (the plot's speed panel)
    axes: list[AxisDrift]
    idle: list[IdleStretch]
    idle_why_not: str = ""
    not_measured: dict[str, str] = field(default_factory=dict)  # model axes the log does not measure: why

    def speed_at(self, ax: AxisDrift) -> np.ndarray | None:
        return None if self.speed_rpm is None else self.speed_rpm[ax.rows]

    def as_dict(self) -> dict[str, Any]:
        """The JSON block (`thermal_test` of `compd fit --report`; `compd report --test-json`)."""
        axes = {}
        for ax in self.axes:
            speed, residual = self.speed_at(ax), ax.residual()
            axes[ax.axis] = {
                "source": ax.source,
                "sampled": ax.sampled,
                "measurements": int(ax.rows.size),
                "first_um": ax.first_um,
                "drift": asdict(ax.drift()),
                "residual": None if residual is None else asdict(residual),
                **({"why_no_residual": ax.why_no_prediction} if ax.predicted_um is None else {}),
                "t_s": _plain(ax.t_s),
                "speed_rpm": None if speed is None else _plain(speed),
                "measured_um": _plain(ax.measured_um),
                "drift_um": _plain(ax.drift_um),
                "predicted_um": None if ax.predicted_um is None else _plain(ax.predicted_um),
                "residual_um": None if ax.residual_um is None else _plain(ax.residual_um),
            }
        idle = [
            {
                "where": s.where,
                "from_t_s": s.from_t_s,
                "to_t_s": s.to_t_s,
                "duration_s": s.to_t_s - s.from_t_s,
                "axes": {ax.axis: asdict(s.figures(ax)) for ax in self.axes},
            }
            for s in self.idle
        ]
        out: dict[str, Any] = {
            "log": self.log,
            "model": self.model,
            "rows": self.rows,
            "every_s": self.every_s,
            "axes": axes,
            "idle": idle,
        }
        if self.idle_why_not:
            out["idle_why_not"] = self.idle_why_not
        if self.not_measured:
            out["not_measured"] = dict(self.not_measured)
        return out


def _plain(a: np.ndarray) -> list[float | None]:
    """Numbers for JSON: NaN as null (JSON has no NaN)."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(a, dtype=float)]


def thermal_test(
    log: Log,
    outputs: list[str] | None = None,
    pred_um: np.ndarray | None = None,
    model: str | None = None,
    every_s: float = DEFAULT_EVERY_MIN * 60.0,
) -> ThermalTest:
    """The thermal test's figures of `log`: per axis it measures, the measurements (its
    `probe_<axis>_um` rows; else `err_<axis>_um` at the log's probe rows, or every `every_s` from
    the first measurement), their drift and, where `outputs` (the model's axes) has the axis, the
    prediction `pred_um` (rows × outputs, over the whole log) and the residual. BadInput when the
    log measures no axis."""
    outputs = list(outputs or [])
    axes = measured_axes(log)
    if not axes:
        raise BadInput("no probe_<axis>_um or err_<axis>_um column: not the log of a thermal test", file=log.file)
    probe_cols = [c for c in log.columns if probe_axis(c)]
    probe_rows = np.flatnonzero(np.isfinite(log.matrix(probe_cols)).any(axis=1)) if probe_cols else np.array([], int)
    series: list[AxisDrift] = []
    for a in [*[o for o in outputs if o in axes], *[a for a in axes if a not in outputs]]:
        probe, err = f"probe_{a}_um", f"err_{a}_um"
        rows = _finite_rows(log, probe) if probe in log.columns else np.array([], int)
        if rows.size:
            source, sampled = probe, "at its probe rows"
        elif err in log.columns and probe_rows.size:
            source, sampled = err, "at the log's probe rows"
            rows = probe_rows[np.isfinite(log.col(err)[probe_rows])]
        elif err in log.columns:
            source, sampled = err, f"every {every_s / 60:g} min"
            rows = every_rows(log.t_s, _finite_rows(log, err), every_s)
        else:
            source, sampled = probe, "no measurement"
        if rows.size == 0:
            continue  # a column with no value: said below as not measured
        measured = log.col(source)[rows]
        predicted, why = None, ""
        if a in outputs and pred_um is not None:
            predicted = np.asarray(pred_um, dtype=float)[rows, outputs.index(a)]
        elif pred_um is None:
            why = "no model"
        else:
            why = f"not an output of {Path(model).name if model else 'the model'}"
        series.append(AxisDrift(a, source, sampled, rows, log.t_s[rows], measured, predicted, why))
    if not series:
        raise BadInput("its probe_<axis>_um and err_<axis>_um columns hold no value: no measurement", file=log.file)
    shown = {s.axis for s in series}
    not_measured = {
        a: "the log has no value in its probe_ or err_ column of the axis"
        if a in axes
        else "the log has no probe_ or err_ column of the axis"
        for a in outputs
        if a not in shown
    }
    idle, why_not = idle_stretches(log)
    return ThermalTest(
        log.file,
        model,
        len(log),
        float(log.t_s[0]),
        every_s,
        log.col("speed_rpm").copy() if "speed_rpm" in log.columns else None,
        log.t_s.copy(),
        series,
        idle,
        why_not,
        not_measured,
    )


# ------------------------------------------------------------------- the plot

C_DRIFT, C_RESIDUAL, C_IDLE = "black", "tab:green", "tab:blue"


def plot_png(tt: ThermalTest, dpi: int = 90) -> bytes:
    """Per axis the drift and the residual over the test (µm), under the spindle's speed when the
    log has it; the idle stretches shaded. PNG bytes."""
    plt = pyplot()
    speed = tt.speed_rpm is not None
    heights = ([0.55] if speed else []) + [1.0] * len(tt.axes)
    fig, panels = plt.subplots(
        len(heights),
        1,
        figsize=(11, 0.6 + 2.7 * sum(heights)),
        sharex=True,
        squeeze=False,
        gridspec_kw={"height_ratios": heights},
    )
    panels = list(panels[:, 0])

    def shade(ax: Any, label: bool) -> None:
        for k, s in enumerate(tt.idle):
            ax.axvspan(
                (s.from_t_s - tt.t0_s) / 3600.0,
                (s.to_t_s - tt.t0_s) / 3600.0,
                color=C_IDLE,
                alpha=0.08,
                lw=0,
                label="spindle stopped (idle)" if label and k == 0 else None,
            )

    if speed:
        ax = panels.pop(0)
        ax.step((tt.t_s - tt.t0_s) / 3600.0, tt.speed_rpm, where="post", lw=1.0, color="0.3")
        shade(ax, True)
        ax.set_ylabel("speed / rpm")
        ax.set_title("spindle speed", fontsize=9, loc="left")
        ax.grid(True, color="0.92", lw=0.6)
        if tt.idle:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    for ax, s in zip(panels, tt.axes, strict=True):
        h = (s.t_s - tt.t0_s) / 3600.0
        d = s.drift()
        ax.plot(h, s.drift_um, "o-", ms=3, lw=1.0, color=C_DRIFT, label=f"drift: {s.source} − first")
        k = int(np.argmax(np.abs(s.drift_um)))
        ax.plot(
            h[k],
            s.drift_um[k],
            "o",
            ms=9,
            mfc="none",
            mec="tab:red",
            mew=1.5,
            label=f"largest drift {d.max_abs_um:.2f} µm",
        )
        title = f"axis {s.axis}: largest drift {d.max_abs_um:.2f} µm at {h[k]:.2f} h, range {d.range_um:.2f} µm"
        r = s.residual()
        if r is not None:
            ax.plot(
                h,
                s.residual_um,
                "s-",
                ms=3,
                lw=1.0,
                color=C_RESIDUAL,
                label="residual: measured − model\n(left with compensation)",
            )
            title += f"; residual RMS {r.rms_um:.2f} µm, max {r.max_abs_um:.2f} µm, range {r.range_um:.2f} µm"
        else:
            title += f"; no residual: {s.why_no_prediction or 'no finite prediction'}"
        shade(ax, False)
        ax.axhline(0.0, color="0.6", lw=0.5)
        ax.set_ylabel(f"{s.axis} / µm")
        ax.set_title(title, fontsize=9, loc="left")
        ax.grid(True, color="0.92", lw=0.6)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.axes[-1].set_xlabel(f"time since the log's first row (t_s = {tt.t0_s:.6g} s) / h")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()
