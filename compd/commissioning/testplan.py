"""The thermal test of a machine (`compd testplan`): a plan designed for identification, its CSV and its G-code.

A plan is a table of rows: from its `t_s` until the next row's, the spindle turns at
`speed_rpm` and each named linear axis reciprocates over its stroke at `feed_<axis>_mm_min`
(0: it stands); `probe` 1 asks for a measurement of the thermal error at `t_s`. The last row
ends the plan. docs/testplan.md gives the design's rationale; in short:

* the primary spectrum: the spindle's speed levels spread evenly over [min, max] (or, on a
  machine without a spindle, each axis's feed levels); each level is held twice, once short
  and once long, the hold lengths spread geometrically from a quarter of the machine's time
  constant τ to three τ and given to the levels in a pseudo-random order, so that no level is
  always the long one;
* the holds follow each other in a pseudo-random order with steps up and down (never the same
  level twice in a row), a multi-level pseudo-random sequence rather than a staircase;
* cool-down pauses (everything stopped) of lengths from τ/4 to 2τ between holds, the longest
  one (which cools the machine by about 86 %) at the end;
* an idle stretch at the start: the cold machine at rest, the only thing that changes is the
  shop's air;
* with a spindle, the axes' feeds are assigned to the holds by their own shuffle (standing
  included), one axis at a time, so that no feed goes with one speed: their effects can be told
  apart;
* every change falls on the step grid (`step_min`, by default the probing interval), and a
  measurement is taken every `probe_every_min`: by default at every change too.

Everything is a pure function of the inputs: the same inputs and seed give the same plan.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from compd import version
from compd.core.errors import BadInput

LINEAR_AXES = "xyzuvw"  # axis letters the three controllers share for linear axes
FEED_COLUMN = re.compile(r"feed_([a-z][a-z0-9]*)_mm_min")
SHORTEST_TAU = 0.25  # the shortest hold, in time constants
LONGEST_TAU = 3.0  # the longest hold
PAUSE_TAU = (0.25, 2.0)  # the shortest and the longest cool-down pause: e^-2 = 14 % of the rise left
MIN_PASS_SCALE = 0.8  # a pass is at least this share of its nominal length (more hours: more passes)
MAX_STEPS = 200_000  # steps of the time grid in one plan (a fortnight in steps of 6 s)
ORDER_TRIES = 2000  # shuffles tried for an order that meets the constraints (then a fallback)
DWELL_MAX_S = 9999.999  # one FANUC G04 X (IS-C's range is 0.0001..9999.9999 s); Siemens split alike
PROBE_CALLS = {"linuxcnc": "o<probe> call", "fanuc": "M98 P9000", "siemens": "PROBE_Z"}
CONTROLLERS = tuple(PROBE_CALLS)
PROGRAM_SUFFIX = {"linuxcnc": ".ngc", "fanuc": ".nc", "siemens": ".mpf"}


@dataclass(frozen=True)
class Axis:
    """A linear axis the test moves: it reciprocates over `stroke_mm` (from where it stands, in
    the + direction and back) at feeds from `min_feed_mm_min` to `max_feed_mm_min`."""

    name: str
    stroke_mm: float
    max_feed_mm_min: float
    min_feed_mm_min: float

    def round_trip_s(self, feed_mm_min: float) -> float:
        """Seconds for one stroke out and back at `feed_mm_min` (at the programmed feed)."""
        return 2.0 * self.stroke_mm / feed_mm_min * 60.0


def parse_axis(text: str, flag: str = "--axis") -> Axis:
    """`NAME:STROKE_MM:MAX_FEED_MM_MIN[:MIN_FEED_MM_MIN]` → Axis (BadInput naming the flag)."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise BadInput(f"give NAME:STROKE_MM:MAX_FEED_MM_MIN[:MIN_FEED_MM_MIN], got {text!r}", path=flag)
    name = parts[0].strip().lower()
    if len(name) != 1 or name not in LINEAR_AXES:
        raise BadInput(
            f"the axis is one letter of {', '.join(LINEAR_AXES.upper())} (a linear axis), got {parts[0]!r}", path=flag
        )
    values = []
    for what, cell in zip(("stroke", "max feed", "min feed"), parts[1:], strict=False):
        try:
            v = float(cell)
        except ValueError:
            raise BadInput(f"{name}: the {what} is not a number: {cell!r}", path=flag) from None
        if not (math.isfinite(v) and v > 0):
            raise BadInput(f"{name}: the {what} must be > 0, got {cell!r}", path=flag)
        values.append(v)
    stroke, top = values[0], values[1]
    low = values[2] if len(values) == 3 else 0.1 * top
    if not low < top:
        raise BadInput(f"{name}: the min feed must be below the max feed ({low:g} >= {top:g})", path=flag)
    return Axis(name, stroke, top, low)


@dataclass
class Plan:
    """The rows of a test plan: from `t_s[i]` to `t_s[i + 1]` the spindle turns at `speed_rpm[i]`
    and each axis of `feeds_mm_min` reciprocates at its feed (0: stands); `probe[i]` asks for a
    measurement at `t_s[i]`. The last row ends the plan (its values hold no time).

    `strokes_mm` (designed plans) says over what each axis reciprocates; `info` what the design
    chose (for the summary and the program's header)."""

    t_s: np.ndarray
    speed_rpm: np.ndarray
    feeds_mm_min: dict[str, np.ndarray]
    probe: np.ndarray
    strokes_mm: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.size)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def columns(self) -> list[str]:
        return ["t_s", "speed_rpm", *(f"feed_{a}_mm_min" for a in self.feeds_mm_min), "probe"]

    def state(self, i: int) -> tuple[float, tuple[float, ...]]:
        """(speed, feeds in axis order) of row i: what holds from its t_s."""
        return float(self.speed_rpm[i]), tuple(float(f[i]) for f in self.feeds_mm_min.values())

    def holds(self) -> list[tuple[float, float, float, dict[str, float]]]:
        """(t_s, duration_s, speed_rpm, {axis: feed}) of each stretch of rows with the same values
        (the last row, which ends the plan, not counted)."""
        out: list[tuple[float, float, float, dict[str, float]]] = []
        prev = None
        for i in range(len(self) - 1):
            s = self.state(i)
            dur = float(self.t_s[i + 1] - self.t_s[i])
            if s == prev:
                t0, d, v, f = out[-1]
                out[-1] = (t0, d + dur, v, f)
            else:
                out.append((float(self.t_s[i]), dur, s[0], dict(zip(self.feeds_mm_min, s[1], strict=True))))
            prev = s
        return out

    def probe_times_s(self) -> np.ndarray:
        return self.t_s[self.probe.astype(bool)]

    def write_csv(self, path: str | Path) -> None:
        """The plan as CSV: header, then one row per change or measurement (whole numbers where
        the values are whole)."""
        cols = [self.t_s, self.speed_rpm, *self.feeds_mm_min.values(), self.probe.astype(float)]
        with open(path, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(self.columns) + "\n")
            for i in range(len(self)):
                fh.write(",".join(_num(float(c[i]), 3) for c in cols) + "\n")


def _num(x: float, decimals: int) -> str:
    """`x` with at most `decimals` decimals and no trailing zeros (600, 13.714, -800)."""
    text = f"{x:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


# ======================================================================================
# the design
def design(
    max_rpm: float,
    hours: float,
    *,
    min_rpm: float | None = None,
    probe_every_min: float = 10.0,
    step_min: float | None = None,
    time_constant_min: float = 60.0,
    levels: int = 7,
    feed_levels: int = 4,
    axes: Sequence[Axis] = (),
    idle_hours: float = 1.0,
    seed: int = 0,
) -> Plan:
    """The thermal test for a machine turning up to `max_rpm` (0: no spindle, the axes' feeds are
    the spectrum), `hours` long at most. BadInput names the option (its command-line flag) of a
    value that cannot make a plan. See the module's docstring for what is designed and why."""
    _check_inputs(
        max_rpm,
        hours,
        min_rpm,
        probe_every_min,
        step_min,
        time_constant_min,
        levels,
        feed_levels,
        axes,
        idle_hours,
        seed,
    )
    step_s = _whole_s(step_min if step_min is not None else probe_every_min, "--step-min")
    probe_s = _whole_s(probe_every_min, "--probe-every-min")
    if probe_s % step_s:
        raise BadInput(
            f"the probing interval ({probe_every_min:g} min) must be a whole number of steps ({step_s / 60:g} min)",
            path="--probe-every-min",
        )
    spindle = max_rpm > 0
    low_rpm = 0.0 if not spindle else (0.1 * max_rpm if min_rpm is None else float(min_rpm))
    for ax in axes:
        trip = ax.round_trip_s(ax.min_feed_mm_min)
        if trip > step_s:
            raise BadInput(
                f"{ax.name}: one stroke out and back over {ax.stroke_mm:g} mm at its lowest feed"
                f" ({ax.min_feed_mm_min:g} mm/min) takes {trip:.0f} s, longer than a step ({step_s:.0f} s):"
                " raise the min feed, shorten the stroke or lengthen --step-min",
                path="--axis",
            )
    # the states of the primary spectrum: (speed, {axis: feed})
    speeds = _levels(low_rpm, float(max_rpm), levels, "--levels", "rpm") if spindle else []
    feeds = {
        ax.name: _levels(ax.min_feed_mm_min, ax.max_feed_mm_min, feed_levels, "--feed-levels", "mm/min") for ax in axes
    }
    if spindle:
        primary = [(v, {}) for v in speeds]
        secondary: list[dict[str, float]] = [{}] + [{a: f} for a, fs in feeds.items() for f in fs]
    else:
        primary = [(0.0, {a: f}) for a, fs in feeds.items() for f in fs]
        secondary = [{}]
    m = len(primary)
    n_pauses = max(2, math.ceil(m / 2))
    hold_tau = np.geomspace(SHORTEST_TAU, LONGEST_TAU, 2 * m)
    pause_tau = np.geomspace(PAUSE_TAU[0], PAUSE_TAU[1], n_pauses)
    pass_min = time_constant_min * float(hold_tau.sum() + pause_tau.sum())
    # the time grid: the idle stretch, then passes of holds and pauses filling the rest
    idle_steps = int(round(idle_hours * 3600.0 / step_s))
    total_steps = int(math.floor(hours * 3600.0 / step_s + 1e-9))
    if total_steps > MAX_STEPS:
        raise BadInput(
            f"{hours:g} h in steps of {step_s:g} s are {total_steps} steps, more than {MAX_STEPS}:"
            " give a longer --step-min",
            path="--hours",
        )
    budget = total_steps - idle_steps
    per_pass = 2 * m + n_pauses
    if budget < per_pass:
        need_h = (idle_steps + per_pass) * step_s / 3600.0
        raise BadInput(
            f"{hours:g} h is too short for one pass over the {m} levels: it needs at least {need_h:.2f} h"
            f" ({idle_steps * step_s / 3600.0:g} h idle, then {2 * m} holds and {n_pauses} pauses of at least"
            f" one {step_s / 60:g} min step); give more hours, or fewer --levels, a shorter --step-min or"
            " --idle-hours",
            path="--hours",
        )
    passes = max(1, min(budget // per_pass, int(budget * step_s / 60.0 / (MIN_PASS_SCALE * pass_min))))
    if len(secondary) > 2 * m:
        raise BadInput(
            f"{len(secondary) - 1} axis feeds and standing do not fit into the {2 * m} holds of a pass:"
            " give fewer --feed-levels or more --levels",
            path="--feed-levels",
        )
    rng = np.random.default_rng([int(seed), 40])
    segments: list[tuple[str, float, float, dict[str, float]]] = []  # (kind, τ units, speed, feeds)
    last = None
    for _ in range(passes):
        order = _order(rng, m, last)
        last = order[-1][0]
        short = rng.permutation(hold_tau[:m])  # each level's short hold and its long one
        long = rng.permutation(hold_tau[m:])
        q = len(secondary)  # each feed (and standing) once, the other holds drawn, all shuffled
        extra = [int(e) for e in rng.permutation(np.concatenate([np.arange(q), rng.integers(0, q, 2 * m - q)]))]
        gaps = set(int(g) for g in rng.choice(np.arange(1, 2 * m), size=n_pauses - 1, replace=False))
        pauses = list(rng.permutation(pause_tau[:-1]))
        for k, (state, is_long) in enumerate(order):
            if k in gaps:
                segments.append(("pause", float(pauses.pop()), 0.0, {}))
            speed, own = primary[state]
            tau = float(long[state] if is_long else short[state])
            segments.append(("hold", tau, speed, {**own, **secondary[extra[k]]}))
        segments.append(("pause", float(pause_tau[-1]), 0.0, {}))
    # minutes → whole steps summing to the budget exactly (each at least one step)
    scale = budget * step_s / 60.0 / (passes * pass_min)
    steps = _apportion(np.array([s[1] for s in segments]) * time_constant_min * scale * 60.0 / step_s, budget)
    plan = _rows(segments, steps, idle_steps, step_s, probe_s, [ax.name for ax in axes])
    plan.strokes_mm = {ax.name: ax.stroke_mm for ax in axes}
    holds = [d * step_s for (kind, *_), d in zip(segments, steps, strict=True) if kind == "hold"]
    pauses_s = [d * step_s for (kind, *_), d in zip(segments, steps, strict=True) if kind == "pause"]
    plan.info = {
        "spindle": spindle,
        "speeds_rpm": speeds,
        "feeds_mm_min": feeds,
        "levels": m,
        "passes": passes,
        "holds_s": holds,
        "pauses_s": pauses_s,
        "idle_s": idle_steps * step_s,
        "step_s": step_s,
        "probe_every_s": probe_s,
        "probes": int(plan.probe.sum()),
        "time_constant_min": float(time_constant_min),
        "seed": int(seed),
        "hours": float(hours),
    }
    return plan


def _check_inputs(
    max_rpm: float,
    hours: float,
    min_rpm: float | None,
    probe_every_min: float,
    step_min: float | None,
    time_constant_min: float,
    levels: int,
    feed_levels: int,
    axes: Sequence[Axis],
    idle_hours: float,
    seed: int,
) -> None:
    def finite(v: float, flag: str, low: float = 0.0, strict: bool = True) -> None:
        ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        if not ok or (v <= low if strict else v < low):
            raise BadInput(f"must be a finite number {'>' if strict else '>='} {low:g}, got {v!r}", path=flag)

    finite(max_rpm, "--max-rpm", strict=False)
    finite(hours, "--hours")
    finite(probe_every_min, "--probe-every-min")
    if step_min is not None:
        finite(step_min, "--step-min")
    finite(time_constant_min, "--time-constant-min")
    finite(idle_hours, "--idle-hours", strict=False)
    if max_rpm == 0 and not axes:
        raise BadInput("0 means no spindle: then give the axes the test moves (--axis)", path="--max-rpm")
    if max_rpm > 0 and min_rpm is not None:
        finite(min_rpm, "--min-rpm")
        if not min_rpm < max_rpm:
            raise BadInput(f"must be below --max-rpm ({min_rpm:g} >= {max_rpm:g})", path="--min-rpm")
    for flag, n in (("--levels", levels), ("--feed-levels", feed_levels)):
        if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= 50:
            raise BadInput(f"a whole number from 2 to 50, got {n!r}", path=flag)
    names = [ax.name for ax in axes]
    if len(set(names)) != len(names):
        raise BadInput(f"axis {next(a for a in names if names.count(a) > 1)} given twice", path="--axis")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise BadInput(f"a whole number >= 0, got {seed!r}", path="--seed")


def _whole_s(minutes: float, flag: str) -> int:
    """A time step in whole seconds (the plan's times are whole seconds)."""
    s = minutes * 60.0
    if abs(s - round(s)) > 1e-6 or round(s) < 1:
        raise BadInput(f"must be a whole number of seconds (e.g. 0.5 = 30 s), got {minutes:g} min", path=flag)
    return int(round(s))


def _levels(low: float, high: float, n: int, flag: str, unit: str) -> list[float]:
    """`n` levels evenly over [low, high], in whole units, within [low, high]."""
    vals = [float(v) for v in np.round(np.linspace(low, high, n))]
    vals[0], vals[-1] = float(math.ceil(low)), float(math.floor(high))
    if len(set(vals)) != n or any(b <= a for a, b in zip(vals, vals[1:], strict=False)):
        raise BadInput(
            f"{n} levels from {low:g} to {high:g} {unit} are not {n} different whole numbers:"
            " give fewer levels or a wider range",
            path=flag,
        )
    return vals


def _order(rng: np.random.Generator, m: int, before: int | None) -> list[tuple[int, bool]]:
    """A pseudo-random order of the 2m holds (level index, long?): never the same level twice in a
    row (nor as the previous pass ended), steps up and down each at least a quarter of the steps."""
    items = [(k, False) for k in range(m)] + [(k, True) for k in range(m)]
    for _ in range(ORDER_TRIES):
        cand = [items[int(i)] for i in rng.permutation(2 * m)]
        if _good_order([c[0] for c in cand], before):
            return cand
    # a fallback that always meets them: the levels interleaved low/high, twice
    zig = [k for pair in zip(range(m), range(m - 1, -1, -1), strict=True) for k in pair][:m]
    seq = [(k, False) for k in zig] + [(k, True) for k in zig]
    return seq if seq[0][0] != before else seq[::-1]


def _good_order(levels: list[int], before: int | None) -> bool:
    seq = ([before] if before is not None else []) + levels
    steps = np.diff(seq)
    if np.any(steps == 0):
        return False
    need = max(1, (len(levels) - 1) // 4)
    return int(np.sum(steps > 0)) >= need and int(np.sum(steps < 0)) >= need


def _apportion(x: np.ndarray, total: int) -> np.ndarray:
    """Whole numbers ≥ 1 near `x` summing to `total` (largest remainders; total ≥ len(x))."""
    out = np.maximum(1, np.floor(x)).astype(int)
    frac = x - np.floor(x)
    while out.sum() < total:
        k = int(np.argmax(frac))
        out[k] += 1
        frac[k] -= 1.0
    while out.sum() > total:
        over = np.where(out > 1, out - x, -np.inf)
        out[int(np.argmax(over))] -= 1
    return out


def _rows(
    segments: list[tuple[str, float, float, dict[str, float]]],
    steps: np.ndarray,
    idle_steps: int,
    step_s: int,
    probe_s: int,
    axes: list[str],
) -> Plan:
    """The plan's rows: one at each change and at each measurement, the last ending the plan."""
    states = [(0.0, {})] * idle_steps + [
        (speed, feeds) for (_, _, speed, feeds), n in zip(segments, steps, strict=True) for _ in range(int(n))
    ]
    t, v, f, p = [], [], {a: [] for a in axes}, []
    prev = None
    for k, (speed, feeds) in enumerate(states):
        key = (speed, tuple(feeds.get(a, 0.0) for a in axes))
        probe = (k * step_s) % probe_s == 0
        if key != prev or probe:
            t.append(k * step_s)
            v.append(speed)
            for a in axes:
                f[a].append(feeds.get(a, 0.0))
            p.append(probe)
        prev = key
    t.append(len(states) * step_s)
    v.append(0.0)
    for a in axes:
        f[a].append(0.0)
    p.append((len(states) * step_s) % probe_s == 0)
    return Plan(np.array(t, float), np.array(v, float), {a: np.array(f[a], float) for a in axes}, np.array(p, bool))


def summary_lines(plan: Plan) -> list[str]:
    """What the design made, a few lines for the user."""
    i = plan.info
    lines = []
    if i["spindle"]:
        s = i["speeds_rpm"]
        lines.append(f"{len(s)} speeds {_num(s[0], 0)}..{_num(s[-1], 0)} rpm")
    for a, fs in i["feeds_mm_min"].items():
        lines.append(f"axis {a}: {len(fs)} feeds {_num(fs[0], 0)}..{_num(fs[-1], 0)} mm/min")
    holds, pauses = i["holds_s"], i["pauses_s"]
    lines.append(
        f"{len(holds)} holds {min(holds) / 60:g}..{max(holds) / 60:g} min, {len(pauses)} cool-down pauses"
        f" {min(pauses) / 60:g}..{max(pauses) / 60:g} min, idle {i['idle_s'] / 60:g} min"
        + (f", {i['passes']} passes" if i["passes"] > 1 else "")
    )
    lines.append(f"{i['probes']} measurements every {i['probe_every_s'] / 60:g} min; {plan.duration_s / 3600.0:.2f} h")
    return lines


def warnings(plan: Plan) -> list[str]:
    """What makes this plan weaker than it could be."""
    i = plan.info
    tau_s = i["time_constant_min"] * 60.0
    out = []
    if max(i["holds_s"]) < tau_s:
        out.append(
            f"the longest hold ({max(i['holds_s']) / 60:g} min) is shorter than the time constant"
            f" ({i['time_constant_min']:g} min): no level gets near its steady state; give more --hours"
        )
    if min(i["holds_s"]) > tau_s:
        out.append(
            f"the shortest hold ({min(i['holds_s']) / 60:g} min) is longer than the time constant"
            f" ({i['time_constant_min']:g} min): the plan shows little of the fast response"
        )
    return out


# ======================================================================================
# reading a plan
def read_plan(file: str | Path) -> Plan:
    """A plan CSV (as `compd testplan` writes it): `t_s` and `speed_rpm`, optional
    `feed_<axis>_mm_min` and `probe` (0/1); other columns are ignored. BadInput names the file,
    line and column of what is wrong."""
    file = str(file)
    try:
        fh = open(file, newline="", encoding="utf-8")  # noqa: SIM115
    except OSError as e:
        raise BadInput(f"cannot read the plan: {e.strerror or e}", file=file) from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise BadInput("the plan is empty (no header row)", file=file) from None
        except (csv.Error, UnicodeDecodeError) as e:
            raise BadInput(f"not a CSV file: {e}", file=file, line=1) from None
        for need in ("t_s", "speed_rpm"):
            if need not in header:
                raise BadInput(f"no column {need!r} (columns: {', '.join(header)})", file=file, line=1)
        if len(set(header)) != len(header):
            raise BadInput("column named twice", file=file, line=1, path=next(h for h in header if header.count(h) > 1))
        for h in header:
            if h.startswith("feed_") and not FEED_COLUMN.fullmatch(h):
                raise BadInput("a feed column is feed_<axis>_mm_min", file=file, line=1, path=h)
        used = [
            "t_s",
            "speed_rpm",
            *(h for h in header if FEED_COLUMN.fullmatch(h)),
            *(["probe"] if "probe" in header else []),
        ]
        idx = [header.index(c) for c in used]
        rows: list[list[float]] = []
        try:
            for lineno, row in enumerate(reader, start=2):
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue
                if len(row) != len(header):
                    raise BadInput(f"row has {len(row)} cells, the header has {len(header)}", file=file, line=lineno)
                values = []
                for name, j in zip(used, idx, strict=True):
                    cell = row[j].strip()
                    try:
                        x = float(cell)
                    except ValueError:
                        raise BadInput(f"not a number: {cell[:40]!r}", file=file, line=lineno, path=name) from None
                    if not math.isfinite(x):
                        raise BadInput(f"not a finite number: {cell!r}", file=file, line=lineno, path=name)
                    if name != "t_s" and x < 0:
                        raise BadInput(f"must be >= 0, got {cell}", file=file, line=lineno, path=name)
                    if name == "probe" and x not in (0.0, 1.0):
                        raise BadInput(f"0 or 1, got {cell}", file=file, line=lineno, path=name)
                    values.append(x)
                if rows and not values[0] > rows[-1][0]:
                    raise BadInput(
                        f"t_s must increase from row to row ({_num(values[0], 6)} after {_num(rows[-1][0], 6)})",
                        file=file,
                        line=lineno,
                        path="t_s",
                    )
                rows.append(values)
        except csv.Error as e:
            raise BadInput(f"CSV: {e}", file=file, line=reader.line_num) from None
        except UnicodeDecodeError:
            raise BadInput("not a UTF-8 text file", file=file) from None
    if len(rows) < 2:
        raise BadInput("a plan has at least two rows (the last one ends it)", file=file)
    data = np.array(rows, float)
    feeds = {FEED_COLUMN.fullmatch(c)[1]: data[:, k] for k, c in enumerate(used) if FEED_COLUMN.fullmatch(c)}
    probe = data[:, used.index("probe")].astype(bool) if "probe" in used else np.zeros(len(rows), bool)
    return Plan(data[:, 0], data[:, 1], feeds, probe, info={"file": file})


# ======================================================================================
# the programs
@dataclass
class Step:
    """What the program does for one row of the plan: measure, set the spindle, reciprocate the
    moving axes `trips` times (each axis out and back in turn), then dwell the rest."""

    t_s: float
    probe: bool
    speed_rpm: float | None  # the new speed (0: stop), None when it does not change
    moves: list[tuple[str, float, float]]  # (axis, stroke_mm, feed_mm_min)
    trips: int
    rest_s: float


def steps(plan: Plan) -> Iterator[Step]:
    """The plan's rows as program steps; a hold whose round trip does not fit its row dwells."""
    speed = 0.0
    for i in range(len(plan) - 1):
        dur = float(plan.t_s[i + 1] - plan.t_s[i])
        v = float(plan.speed_rpm[i])
        moves = [(a, plan.strokes_mm[a], float(f[i])) for a, f in plan.feeds_mm_min.items() if f[i] > 0]
        trip = sum(2.0 * s / f * 60.0 for _, s, f in moves)
        trips = int(math.floor(dur / trip + 1e-9)) if moves else 0
        yield Step(float(plan.t_s[i]), bool(plan.probe[i]), v if v != speed else None, moves, trips, dur - trips * trip)
        speed = v


def _dwells(rest_s: float, limit_s: float | None) -> list[float]:
    """`rest_s` rounded to ms, in pieces of at most `limit_s`."""
    ms = int(round(rest_s * 1000.0))
    if ms <= 0:
        return []
    if limit_s is None:
        return [ms / 1000.0]
    cap = int(limit_s * 1000.0)
    return [min(cap, ms - k) / 1000.0 for k in range(0, ms, cap)]


def _header_lines(plan: Plan, controller: str, probe_call: str, source: str) -> list[str]:
    i = plan.info
    lines = [
        f"compd {version()} testplan: the thermal test for {controller}, from {source}",
        *(summary_lines(plan) if "holds_s" in i else []),
        f"measuring call: {probe_call} (a placeholder for your own probing routine)",
    ]
    if plan.strokes_mm:
        lines.append(
            "axes: start each at the low end of its stroke: it moves + and back, "
            + ", ".join(f"{a.upper()} {_num(s, 3)} mm" for a, s in plan.strokes_mm.items())
        )
    return lines


def _comment_text(text: str) -> str:
    """Text safe inside a G-code comment: no parentheses, no line breaks."""
    return " ".join(text.replace("(", "[").replace(")", "]").split())


def _fanuc_comment(text: str) -> str:
    """A FANUC comment's text: upper case, and only characters every ISO-code control takes."""
    return " ".join(re.sub(r"[^A-Z0-9 .,+\-=/#*\[\]]", " ", _comment_text(text).replace(":", " -").upper()).split())


def linuxcnc(plan: Plan, probe_call: str, source: str) -> str:
    """The plan as a LinuxCNC (RS274NGC) program: G4 P<s> dwells, `o<n> repeat` loops."""
    out = [f"({_comment_text(h)})" for h in _header_lines(plan, "LinuxCNC", probe_call, source)]
    out += ["G21 G90 G94 G17", "M5"]
    loop = 100
    for st in steps(plan):
        out.append(f"(t = {_num(st.t_s, 3)} s)")
        if st.probe:
            out.append(probe_call)
        if st.speed_rpm is not None:
            out.append(f"S{_num(st.speed_rpm, 0)} M3" if st.speed_rpm > 0 else "M5")
        if st.trips:
            out.append(f"o{loop} repeat [{st.trips}]")
            for a, stroke, feed in st.moves:
                out += [f"G91 G1 {a.upper()}{_num(stroke, 3)} F{_num(feed, 3)}", f"G1 {a.upper()}-{_num(stroke, 3)}"]
            out += [f"o{loop} endrepeat", "G90"]
            loop += 1
        out += [f"G4 P{_num(d, 3)}" for d in _dwells(st.rest_s, None)]
    out.append(f"(t = {_num(float(plan.t_s[-1]), 3)} s: the end)")
    if plan.probe[-1]:
        out.append(probe_call)
    out += ["M5", "M2"]
    return "\n".join(out) + "\n"


def _fanuc_dec(x: float) -> str:
    """A FANUC value with its decimal point always written (X800. not X800, which reads as 0.8 mm)."""
    text = _num(x, 3)
    return text if "." in text else text + "."


def fanuc(plan: Plan, probe_call: str, source: str) -> str:
    """The plan as a FANUC program: G04 X<s> dwells (≤ 9999.999 s each), WHILE loops (custom macro)."""
    out = ["%", "O2303 (COMPD THERMAL TEST)"]
    out += [f"({_fanuc_comment(h)})" for h in _header_lines(plan, "FANUC", probe_call, source)]
    out += ["G21 G90 G94 G17", "M05"]
    for st in steps(plan):
        out.append(f"(T = {_num(st.t_s, 3)} S)")
        if st.probe:
            out.append(probe_call)
        if st.speed_rpm is not None:
            out.append(f"S{_num(st.speed_rpm, 0)} M03" if st.speed_rpm > 0 else "M05")
        if st.trips:
            out += ["#1=0", f"WHILE [#1 LT {st.trips}] DO1"]
            for a, stroke, feed in st.moves:
                out += [
                    f"G91 G01 {a.upper()}{_fanuc_dec(stroke)} F{_fanuc_dec(feed)}",
                    f"{a.upper()}-{_fanuc_dec(stroke)}",
                ]
            out += ["#1=#1+1", "END1", "G90"]
        out += [f"G04 X{_fanuc_dec(d)}" for d in _dwells(st.rest_s, DWELL_MAX_S)]
    out.append(f"(T = {_num(float(plan.t_s[-1]), 3)} S: THE END)")
    if plan.probe[-1]:
        out.append(probe_call)
    out += ["M05", "M30", "%"]
    return "\n".join(out) + "\n"


def siemens(plan: Plan, probe_call: str, source: str) -> str:
    """The plan as a SINUMERIK program: G4 F<s> dwells (≤ 9999.999 s each), WHILE loops on R90."""
    out = [f"; {' '.join(h.split())}" for h in _header_lines(plan, "SINUMERIK", probe_call, source)]
    out += ["G71 G90 G94 G17", "M5"]
    for st in steps(plan):
        out.append(f"; t = {_num(st.t_s, 3)} s")
        if st.probe:
            out.append(probe_call)
        if st.speed_rpm is not None:
            out.append(f"S{_num(st.speed_rpm, 0)} M3" if st.speed_rpm > 0 else "M5")
        if st.trips:
            out += ["R90=0", f"WHILE R90<{st.trips}"]
            for a, stroke, feed in st.moves:
                out += [f"G91 G1 {a.upper()}{_num(stroke, 3)} F{_num(feed, 3)}", f"{a.upper()}-{_num(stroke, 3)}"]
            out += ["R90=R90+1", "ENDWHILE", "G90"]
        out += [f"G4 F{_num(d, 3)}" for d in _dwells(st.rest_s, DWELL_MAX_S)]
    out.append(f"; t = {_num(float(plan.t_s[-1]), 3)} s: the end")
    if plan.probe[-1]:
        out.append(probe_call)
    out += ["M5", "M30"]
    return "\n".join(out) + "\n"


PROGRAMS = {"linuxcnc": linuxcnc, "fanuc": fanuc, "siemens": siemens}


def check_probe_call(text: str, controller: str) -> str:
    """The user's measuring call as one program line (BadInput otherwise)."""
    text = text.strip()
    if not text or "\n" in text or "\r" in text or not text.isprintable() or len(text) > 200:
        raise BadInput(
            f"one line of up to 200 printable characters, e.g. {PROBE_CALLS[controller]!r}", path="--probe-call"
        )
    if controller == "fanuc" and text != text.upper():
        raise BadInput(f"a FANUC program is upper case: {text.upper()!r}", path="--probe-call")
    return text
