"""Duty-cycle scenarios: piecewise-constant speed/feed segments and the ambient over time.

A scenario file is YAML:

    machine: lathe            # plant name (hil_sim.plants.PLANTS)
    params: {...}             # optional plant parameters
    seed: 3
    ambient: {start_c: 20, drift_c_per_h: 0.05, daily_amplitude_c: 1.0, points: [[0, 0], [6, 0.5]]}
    segments:
      - {duration_s: 3600, speed_rpm: 2000}
      - repeat: 4             # a group repeated
        segments:
          - {duration_s: 900, feed_mm_min: 6000, stroke_mm: [0, 600]}
          - {duration_s: 300, pos_mm: 300}
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

SCENARIOS = Path(__file__).resolve().parent / "scenarios"  # the machines' days (package data)


@dataclass
class Segment:
    """What the machine does for `duration_s` seconds.

    `speed_rpm` spindle speed; `feed_mm_min` feed of the linear axes, reciprocating
    over `stroke_mm` = [low, high] (the plant's default stroke if None); with no feed
    the axes stand at `pos_mm` (where they were if None). `load` scales the spindle
    power and the axis force (1 = nominal); `axis_load` scales one axis more
    ({x2: 1.3}). `coolant` switches the spindle coolant.
    """

    duration_s: float
    speed_rpm: float = 0.0
    feed_mm_min: float = 0.0
    load: float = 1.0
    stroke_mm: tuple[float, float] | None = None
    pos_mm: float | None = None
    coolant: bool = False
    axis_load: dict[str, float] = field(default_factory=dict)

    def load_of(self, axis: str) -> float:
        return self.load * self.axis_load.get(axis, 1.0)


HVAC_SHAPES = ("sine", "square", "triangle")


@dataclass
class Ambient:
    """Ambient temperature: start value, linear drift, a daily sine, piecewise-linear offsets
    and the HVAC's cycle.

    `points` are [hour, offset °C] pairs interpolated linearly (held flat outside). The HVAC
    term (off at `hvac_amplitude_c` 0, the default) swings ± `hvac_amplitude_c` with period
    `hvac_period_s`: `sine`, `square` (the supply air switched on and off) or `triangle` (the
    room's ramp between an on/off controller's switching points), starting at `hvac_phase_s`.
    """

    start_c: float = 20.0
    drift_c_per_h: float = 0.0
    daily_amplitude_c: float = 0.0
    daily_phase_h: float = 0.0
    points: list[tuple[float, float]] = field(default_factory=list)
    hvac_amplitude_c: float = 0.0
    hvac_period_s: float = 1800.0
    hvac_phase_s: float = 0.0
    hvac_shape: str = "sine"

    def __post_init__(self) -> None:
        pts = [tuple(map(float, p)) for p in self.points]
        for p in pts:
            if len(p) != 2:
                raise ValueError("ambient.points are [hour, offset_c] pairs")
        self.points = sorted(pts)  # type: ignore[arg-type]
        self._ph = [p[0] * 3600.0 for p in self.points]
        self._pc = [p[1] for p in self.points]
        if self.hvac_shape not in HVAC_SHAPES:
            raise ValueError(f"ambient.hvac_shape: one of {', '.join(HVAC_SHAPES)}, got {self.hvac_shape!r}")
        if not self.hvac_period_s > 0:
            raise ValueError("ambient.hvac_period_s: must be > 0")

    def at(self, t_s: float) -> float:
        v = (
            self.start_c
            + self.drift_c_per_h * t_s / 3600.0
            + self.daily_amplitude_c * math.sin(2 * math.pi * (t_s / 3600.0 - self.daily_phase_h) / 24.0)
        )
        if self._ph:
            v += _interp(t_s, self._ph, self._pc)
        if self.hvac_amplitude_c:  # skipped when off: today's files stay bit for bit
            v += self.hvac_amplitude_c * self._hvac_unit(t_s)
        return v

    def _hvac_unit(self, t_s: float) -> float:
        """The HVAC cycle at `t_s` on a unit amplitude (−1 … 1)."""
        frac = ((t_s - self.hvac_phase_s) / self.hvac_period_s) % 1.0
        if self.hvac_shape == "sine":
            return math.sin(2 * math.pi * frac)
        if self.hvac_shape == "square":
            return 1.0 if frac < 0.5 else -1.0
        return 4.0 * abs(frac - 0.5) - 1.0

    def to_dict(self) -> dict[str, Any]:
        """The mapping `Scenario.from_dict` reads back (keys at their defaults left out)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "points":
                if v:
                    out["points"] = [[float(h), float(c)] for h, c in v]
            elif v != f.default:
                out[f.name] = v if isinstance(v, str) else float(v)
        return out


def _interp(x: float, xs: list[float], ys: list[float]) -> float:
    """Linear interpolation in sorted `xs`, held flat outside (scalar, no numpy overhead)."""
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    k = bisect.bisect_right(xs, x) - 1
    if xs[k + 1] == xs[k]:
        return ys[k + 1]
    return ys[k] + (ys[k + 1] - ys[k]) * (x - xs[k]) / (xs[k + 1] - xs[k])


@dataclass
class Scenario:
    """What the machine does over time (and, from a file, which machine and its params)."""

    segments: list[Segment]
    ambient: Ambient = field(default_factory=Ambient)
    seed: int = 0
    machine: str | None = None
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._ends = list(np.cumsum([s.duration_s for s in self.segments]))

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))

    def index_at(self, t_s: float) -> int:
        """Index of the segment running at `t_s` (the last one after the end)."""
        i = bisect.bisect_right(self._ends, t_s)
        return min(i, len(self.segments) - 1)

    def segment_at(self, t_s: float) -> Segment:
        if not self.segments:
            return Segment(0.0)
        return self.segments[self.index_at(t_s)]

    def boundaries(self) -> np.ndarray:
        return np.cumsum([0.0] + [s.duration_s for s in self.segments])

    def to_dict(self) -> dict[str, Any]:
        """The mapping `from_dict` reads back: a scenario file's content (segment keys at
        their defaults left out)."""
        out: dict[str, Any] = {}
        if self.machine is not None:
            out["machine"] = self.machine
        if self.params:
            out["params"] = dict(self.params)
        out["seed"] = int(self.seed)
        out["ambient"] = self.ambient.to_dict()
        out["segments"] = [segment_dict(s) for s in self.segments]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Scenario:
        """Build from a mapping; errors are ValueError naming the key path."""
        if not isinstance(data, dict):
            raise ValueError("a scenario is a mapping")
        known = {"segments", "ambient", "seed", "machine", "params"}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown key {sorted(unknown)[0]!r} (known: {', '.join(sorted(known))})")
        segs = _segments(data.get("segments"), "segments")
        if not segs:
            raise ValueError("segments: a scenario needs at least one segment")
        amb_data = data.get("ambient") or {}
        if not isinstance(amb_data, dict):
            raise ValueError("ambient: must be a mapping")
        amb_known = {f.name for f in fields(Ambient)}
        for k, v in amb_data.items():
            if k not in amb_known:
                raise ValueError(f"ambient.{k}: unknown key (known: {', '.join(sorted(amb_known))})")
            if k == "hvac_shape":
                if v not in HVAC_SHAPES:
                    raise ValueError(f"ambient.hvac_shape: one of {', '.join(HVAC_SHAPES)}, got {v!r}")
            elif k != "points":
                _number(v, f"ambient.{k}")
        amb = Ambient(**amb_data)
        machine = data.get("machine")
        if machine is not None and not isinstance(machine, str):
            raise ValueError("machine: must be a plant name")
        params = data.get("params") or {}
        if not isinstance(params, dict):
            raise ValueError("params: must be a mapping")
        seed = data.get("seed", 0)
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise ValueError("seed: must be an integer")
        return cls(segs, amb, seed, machine, dict(params))

    @classmethod
    def load(cls, file: str | Path) -> Scenario:
        """Read a scenario YAML; errors are ValueError starting with the file name."""
        from compd.core.config import load_yaml
        from compd.core.errors import BadInput

        try:  # compd's reader: bounded size, nesting and alias expansion
            data = load_yaml(file).data
        except BadInput as e:
            if not e.message.startswith("YAML"):
                raise ValueError(str(e)) from None
            where = f":{e.line}" if e.line is not None else ""
            raise ValueError(f"{file}{where}: not valid YAML: {e.message.split(': ', 1)[-1]}") from None
        try:
            return cls.from_dict(data)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{file}: {e}") from None


def plan_segments(plan: Any, axis: str | None = None, stroke_mm: tuple[float, float] | None = None) -> list[Segment]:
    """The segments of a `compd testplan` plan (compd.commissioning.testplan.Plan): one per row but
    the last (which ends the plan), at the row's speed; the linear axes reciprocate over `stroke_mm`
    (the plant's own stroke when None) at the feed of the plan's axis `axis` (its only feed column
    when None; 0: they stand). ValueError names what does not fit."""
    feeds = plan.feeds_mm_min
    if axis is None and len(feeds) > 1:
        raise ValueError(
            f"the plan has feeds for the axes {', '.join(feeds)}: say which one the plant's linear axes follow"
        )
    if axis is not None and axis not in feeds:
        raise ValueError(
            f"the plan has no feed_{axis}_mm_min (its feed columns: "
            f"{', '.join(f'feed_{a}_mm_min' for a in feeds) or 'none'})"
        )
    feed = feeds[axis if axis is not None else next(iter(feeds))] if feeds else None
    out = []
    for i in range(len(plan.t_s) - 1):
        f = 0.0 if feed is None else float(feed[i])
        out.append(
            Segment(
                float(plan.t_s[i + 1] - plan.t_s[i]),
                speed_rpm=float(plan.speed_rpm[i]),
                feed_mm_min=f,
                stroke_mm=stroke_mm if f > 0 else None,
            )
        )
    return out


_SEG_KEYS = {f.name for f in fields(Segment)}


def segment_dict(seg: Segment) -> dict[str, Any]:
    """One segment as a scenario file writes it (keys at their defaults left out)."""
    out: dict[str, Any] = {"duration_s": float(seg.duration_s)}
    for f in fields(Segment):
        v = getattr(seg, f.name)
        if f.name == "duration_s" or v is None or (f.name == "axis_load" and not v):
            continue
        if f.name == "coolant":
            if v:
                out["coolant"] = True
        elif f.name == "stroke_mm":
            out["stroke_mm"] = [float(v[0]), float(v[1])]
        elif f.name == "axis_load":
            out["axis_load"] = {str(a): float(x) for a, x in v.items()}
        elif v != f.default:
            out[f.name] = float(v)
    return out


def _number(v: Any, path: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{path}: must be a finite number, got {v!r}")
    return float(v)


def _segments(items: Any, path: str) -> list[Segment]:
    if not isinstance(items, list):
        raise ValueError(f"{path}: must be a list of segments")
    out: list[Segment] = []
    for k, item in enumerate(items):
        p = f"{path}[{k}]"
        if not isinstance(item, dict):
            raise ValueError(f"{p}: a segment is a mapping")
        if "repeat" in item:
            extra = set(item) - {"repeat", "segments"}
            if extra:
                raise ValueError(f"{p}.{sorted(extra)[0]}: a repeat group has only repeat and segments")
            n = item["repeat"]
            if not isinstance(n, int) or isinstance(n, bool) or n < 1:
                raise ValueError(f"{p}.repeat: must be an integer >= 1")
            group = _segments(item.get("segments"), f"{p}.segments")
            out += [Segment(**{**g.__dict__, "axis_load": dict(g.axis_load)}) for _ in range(n) for g in group]
            continue
        for key in item:
            if key not in _SEG_KEYS:
                raise ValueError(f"{p}.{key}: unknown key (known: {', '.join(sorted(_SEG_KEYS))})")
        if "duration_s" not in item:
            raise ValueError(f"{p}.duration_s: missing")
        kw: dict[str, Any] = {}
        for key in ("duration_s", "speed_rpm", "feed_mm_min", "load"):
            if key in item:
                kw[key] = _number(item[key], f"{p}.{key}")
        if not kw["duration_s"] > 0:
            raise ValueError(f"{p}.duration_s: must be > 0")
        for key in ("speed_rpm", "feed_mm_min", "load"):
            if kw.get(key, 0.0) < 0:
                raise ValueError(f"{p}.{key}: must be >= 0")
        if item.get("pos_mm") is not None:
            kw["pos_mm"] = _number(item["pos_mm"], f"{p}.pos_mm")
        if item.get("stroke_mm") is not None:
            s = item["stroke_mm"]
            if not isinstance(s, list) or len(s) != 2:
                raise ValueError(f"{p}.stroke_mm: must be [low, high]")
            lo, hi = (_number(v, f"{p}.stroke_mm") for v in s)
            if not hi > lo:
                raise ValueError(f"{p}.stroke_mm: high must be > low")
            kw["stroke_mm"] = (lo, hi)
        if "coolant" in item:
            if not isinstance(item["coolant"], bool):
                raise ValueError(f"{p}.coolant: must be true or false")
            kw["coolant"] = item["coolant"]
        if item.get("axis_load") is not None:
            al = item["axis_load"]
            if not isinstance(al, dict):
                raise ValueError(f"{p}.axis_load: must be a mapping axis: factor")
            kw["axis_load"] = {str(a): _number(v, f"{p}.axis_load.{a}") for a, v in al.items()}
        out.append(Segment(**kw))
    return out
