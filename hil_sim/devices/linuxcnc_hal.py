"""The plant's side of a real controller: LinuxCNC's spindle speed and applied external offsets, read from HAL.

For the closed loop on LinuxCNC the plant does not follow a scenario's speeds: LinuxCNC runs the
test program, and the plant turns at `spindle.0.speed-out`. What LinuxCNC applies on each axis
(`axis.L.eoffset`, machine units: mm) is the correction that reaches the tool, read here from
HAL, never from compd. A HAL component of hil_sim's (`hilsim`, float inputs `speed` and
`L.eoffset`) is netted to those pins' signals; `hil_sim serve` makes it (`kind: linuxcnc_hal`)
and a plant names it as its `cnc` and `speed_from`. LinuxCNC's shutdown ends the process that
made it: stop `hil_sim serve` first.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

from compd.io import hal_modules
from compd.io.hal_agent import linuxcnc_runs, net_input


class LinuxcncHal:
    """hil_sim's HAL component: the spindle's speed and each axis's applied offset."""

    def __init__(
        self, axes: Sequence[str] = ("z",), component: str = "hilsim", speed_pin: str = "spindle.0.speed-out"
    ) -> None:
        self.axes = list(axes)
        self.component = component
        self.speed_pin = speed_pin
        self._comp: Any = None

    def start(self) -> LinuxcncHal:
        why = linuxcnc_runs()
        if why is not None:
            raise RuntimeError(why)
        hal, _ = hal_modules.load()
        c = hal.component(self.component)
        c.newpin("speed", hal.HAL_FLOAT, hal.HAL_IN)
        for a in self.axes:
            c.newpin(f"{a}.eoffset", hal.HAL_FLOAT, hal.HAL_IN)
        c.ready()
        self._comp = c
        for ours, theirs in [("speed", self.speed_pin), *((f"{a}.eoffset", f"axis.{a}.eoffset") for a in self.axes)]:
            why = net_input(hal, f"{self.component}.{ours}", theirs, f"{self.component}-{ours.replace('.', '-')}")
            if why is not None:
                raise RuntimeError(why)
        return self

    def speed_rpm(self) -> float:
        return float(self._comp["speed"]) if self._comp is not None else 0.0

    def applied_mm(self) -> list[float]:
        """Each axis's applied external offset (mm), in `axes` order."""
        if self._comp is None:
            return [0.0] * len(self.axes)
        return [float(self._comp[f"{a}.eoffset"]) for a in self.axes]

    def stop(self) -> None:
        if self._comp is not None:
            with contextlib.suppress(Exception):  # gone with LinuxCNC
                self._comp.exit()
            self._comp = None

    def where(self) -> str:
        return f"HAL component {self.component} (speed from {self.speed_pin}, offsets of {', '.join(self.axes)})"
