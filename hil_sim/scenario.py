"""Duty-cycle scenarios: piecewise-constant speed/feed segments and the ambient over time."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml


@dataclass
class Segment:
    duration_s: float
    speed_rpm: float = 0.0
    feed_mm_min: float = 0.0
    load: float = 1.0


@dataclass
class Ambient:
    """Ambient temperature: start value, linear drift and a daily sine."""

    start_c: float = 20.0
    drift_c_per_h: float = 0.0
    daily_amplitude_c: float = 0.0
    daily_phase_h: float = 0.0

    def at(self, t_s: float) -> float:
        return (
            self.start_c
            + self.drift_c_per_h * t_s / 3600.0
            + self.daily_amplitude_c
            * math.sin(2 * math.pi * (t_s / 3600.0 - self.daily_phase_h) / 24.0)
        )


@dataclass
class Scenario:
    """What the machine does over time."""

    segments: list[Segment]
    ambient: Ambient = field(default_factory=Ambient)
    seed: int = 0

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))

    def segment_at(self, t_s: float) -> Segment:
        acc = 0.0
        for seg in self.segments:
            acc += seg.duration_s
            if t_s < acc:
                return seg
        return self.segments[-1] if self.segments else Segment(0.0)

    def boundaries(self) -> np.ndarray:
        return np.cumsum([0.0] + [s.duration_s for s in self.segments])

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Scenario:
        segs = [Segment(**s) for s in data.get("segments", [])]
        if not segs:
            raise ValueError("a scenario needs at least one segment")
        for s in segs:
            if not s.duration_s > 0:
                raise ValueError("segment duration_s must be > 0")
        amb = Ambient(**(data.get("ambient") or {}))
        return cls(segs, amb, int(data.get("seed", 0)))

    @classmethod
    def load(cls, file: str | Path) -> Scenario:
        data = yaml.safe_load(Path(file).read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError(f"{file}: a scenario is a mapping")
        data.pop("machine", None)
        data.pop("params", None)
        return cls.from_dict(data)
