"""A sample of named signals, each with a value, a quality and a time stamp.

The frame is allocated once at start-up; sources write into it by index and the
model reads from it by index, so the cycle allocates nothing.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable

import numpy as np

from compd.core.errors import BadInput


class Quality(enum.IntEnum):
    """Signal quality, worst last. Anything but GOOD makes a model input bad."""

    GOOD = 0
    STALE = 1
    OUT_OF_RANGE = 2
    BURNOUT = 3
    COMMS_LOST = 4
    NO_DATA = 5
    IMPLAUSIBLE = 6
    FROZEN = 7  # unchanged for guard.signals.<name>.frozen_after_s while the others moved


QUALITY_NAMES = {q.value: q.name.lower() for q in Quality}


class Frame:
    """Named signals in preallocated arrays: `values`, `quality`, `stamp_s`.

    `stamp_s[i]` is the loop-clock time at which signal i was sampled at its
    source; its age at time t is `t - stamp_s[i]`.
    """

    def __init__(self, names: Iterable[str]) -> None:
        self.names: list[str] = []
        self.index: dict[str, int] = {}
        for name in names:
            self.add(name)
        self.values = np.full(len(self.names), np.nan)
        self.quality = np.full(len(self.names), Quality.NO_DATA, dtype=np.uint8)
        self.stamp_s = np.full(len(self.names), -np.inf)

    def add(self, name: str) -> int:
        """Register a signal name before the arrays are sized (init only)."""
        if name in self.index:
            raise BadInput(f"signal {name!r} is published twice")
        self.index[name] = len(self.names)
        self.names.append(name)
        return self.index[name]

    def __len__(self) -> int:
        return len(self.names)

    def indices(self, names: Iterable[str], *, what: str = "input") -> np.ndarray:
        """Indices of `names`; an unknown name is a wiring error listing the known ones."""
        out = []
        for name in names:
            if name not in self.index:
                known = ", ".join(self.names) or "none"
                raise BadInput(f"{what} {name!r} is not a signal of any source (signals: {known})")
            out.append(self.index[name])
        return np.asarray(out, dtype=np.intp)

    def set(self, i: int, value: float, quality: int, stamp_s: float) -> None:
        """Write one signal."""
        self.values[i] = value
        self.quality[i] = quality
        self.stamp_s[i] = stamp_s

    def snapshot(self, now_s: float) -> dict[str, dict[str, float | str]]:
        """A plain dict of every signal (status, tests); not for the hot path."""
        return {
            name: {
                "value": float(self.values[i]),
                "quality": QUALITY_NAMES.get(int(self.quality[i]), "?"),
                "age_s": float(now_s - self.stamp_s[i]),
            }
            for i, name in enumerate(self.names)
        }
