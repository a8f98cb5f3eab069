"""The machine holds compensation off: an inhibit signal, and per axis a referenced signal (the `inhibit` section).

Every cycle, before the guard, each axis gets a hold reason from the frame: `INHIBITED`
when the global or the axis's inhibit signal is on (or not good: comms lost, stale),
`WAITING` when the axis has a referenced signal that is off (or not good), else `NONE`.
The guard ramps a held axis's correction to zero at its slew limit and back once
released (compd.cycle.guard). The signals are ordinary frame signals: a Modbus register bit
(`bit` of a modbus source's channel), a CAN bit, any source's value; not 0 is on.
"""

from __future__ import annotations

import numpy as np

from compd.core.config import InhibitConfig
from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality

NONE, INHIBITED, WAITING = 0, 1, 2
HOLD_NAMES = {NONE: None, INHIBITED: "inhibited", WAITING: "waiting for reference"}
GOOD = int(Quality.GOOD)


class Inhibit:
    """Per-axis hold reasons from the frame; `evaluate` allocates nothing."""

    def __init__(self, cfg: InhibitConfig, axes: list[str], frame: Frame) -> None:
        self.cfg = cfg

        def index(name: str | None, path: tuple[str | int, ...]) -> int:
            if name is None:
                return -1
            if name not in frame.index:
                raise BadInput(f"{name!r} is not a signal of any source", path=path)
            return frame.index[name]

        glob = index(cfg.signal, ("inhibit", "signal"))
        self._inhibit: list[list[int]] = []  # per axis: the inhibit signals' frame indices
        self._referenced: list[int] = []  # per axis: the referenced signal's index, -1 for none
        for axis in axes:
            ax = cfg.axes.get(axis)
            own = index(ax.signal, ("inhibit", "axes", axis, "signal")) if ax else -1
            self._inhibit.append([i for i in (glob, own) if i >= 0])
            self._referenced.append(index(ax.referenced, ("inhibit", "axes", axis, "referenced")) if ax else -1)
        self._stale_s = float(cfg.stale_after_s)
        self._invert = bool(cfg.invert)

    def _good(self, frame: Frame, i: int, now_s: float) -> bool:
        return int(frame.quality[i]) == GOOD and now_s - float(frame.stamp_s[i]) <= self._stale_s

    def evaluate(self, frame: Frame, now_s: float, hold: np.ndarray) -> None:
        """Write each axis's hold reason (NONE, INHIBITED, WAITING) into `hold`."""
        for a, signals in enumerate(self._inhibit):
            h = NONE
            r = self._referenced[a]
            if r >= 0 and not (self._good(frame, r, now_s) and frame.values[r] != 0):
                h = WAITING
            for i in signals:
                if not self._good(frame, i, now_s) or (frame.values[i] != 0) != self._invert:
                    h = INHIBITED
                    break
            hold[a] = h
