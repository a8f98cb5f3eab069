"""How time passes for the device a sink writes to: its own clock (over the network) or the loop's (in process).

A sink tells its `DeviceTime` the loop's time at every call (`set`) and lets device
time pass with `wait` (e.g. two PMC scans between two steps of the shift); the device's
time never runs backwards (after a wait it may be ahead of the loop's for a while). A device
elsewhere keeps its own clock, so waiting is sleeping; a device of the software PLC in
this process runs on the loop's time, so waiting moves that time on at once — a
replay of a day never sleeps.

`catch_up` says which: a device on the loop's time is where the sink's last call (or wait)
left it, so a call at loop time t after dt may act in that dt as the device's rates allow
(several PMC steps, a K0 the NC ramps to over dt), the device running its scans between.
A replay's row stands for many of the daemon's cycles; a device on its own clock is
written once per call, as the live daemon's cycle never waits.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod


class DeviceTime(ABC):
    """The device's time as the sink knows it, s."""

    # True: the device runs on the loop's time (waiting costs nothing), and a call may do
    # what the time since the device's last call allows
    catch_up: bool = False

    def __init__(self) -> None:
        self.now_s = -math.inf  # until the sink opens

    def set(self, now_s: float) -> None:
        """The loop's time of the sink's current call (an earlier one than a wait reached is ignored)."""
        self.now_s = max(self.now_s, now_s)

    @abstractmethod
    def wait(self, dt_s: float) -> None:
        """Let `dt_s` of the device's time pass."""


class WallTime(DeviceTime):
    """A device on its own clock (a PLC over Modbus): waiting sleeps."""

    def wait(self, dt_s: float) -> None:
        time.sleep(dt_s)
        self.now_s += dt_s


class LoopTime(DeviceTime):
    """A device that runs on the loop's time (the software PLC in process): waiting moves it on at once."""

    catch_up = True

    def wait(self, dt_s: float) -> None:
        self.now_s += dt_s
