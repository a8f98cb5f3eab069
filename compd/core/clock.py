"""Clocks injected into the loop: wall time (sleep then spin) or simulated time.

Other clocks (a simulated plant's) plug in through the `compd.clocks` entry points.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Protocol


class DrivenSink(Protocol):
    """What a clock that drives the I/O between cycles asks of the sink (compd.sinks.base.Sink):
    that its device's held output is known and its writes acknowledged, each within `timeout_s`."""

    def await_held(self, timeout_s: float) -> bool: ...
    def flush(self, timeout_s: float) -> bool: ...


class DrivenSource(Protocol):
    """What such a clock asks of a polled source it adopted (compd.sources.base.PolledSource): one
    poll at the loop time `stamp`, True once done."""

    name: str

    def poll_now(self, stamp: float) -> bool: ...


class Clock(ABC):
    """What the loop needs of a clock: the time now (s), a wait until a deadline, and
    `start`/`stop` around a run (a clock read from elsewhere connects there).

    `simulated` is True when the clock's time is not wall time (the loop then keeps
    the interpreter's thread switch interval as it is, and no real-time option applies).
    """

    simulated: bool = False
    # whether `now` reads the same time in a forked child (an I/O worker's process)
    fork_safe: bool = False
    # `wait_until` spins through this much before a deadline (the loop keeps it free)
    spin_margin_s: float = 0.0
    # a reload whose clock is configured as before keeps this clock, running (a plant's clock:
    # its connection and its time go on); others are built anew
    kept_across_reload: bool = False

    @abstractmethod
    def now(self) -> float:
        """Loop time, s."""

    def bind(self, sink: DrivenSink, sources: Sequence[object]) -> None:
        """The pipeline's sink and sources, for a clock that drives their I/O between cycles
        (a lockstep plant clock: it polls those of them it adopted); others ignore them."""

    def adopt_poller(self, source: DrivenSource) -> bool:
        """A polled source asks whether the clock drives its polls (a lockstep plant clock
        polls every source once per cycle at the plant time). False: its I/O worker polls at
        its own pace."""
        return False

    @abstractmethod
    def wait_until(self, deadline_s: float) -> None:
        """Return at (or as soon as possible after) loop time `deadline_s`."""

    def elapsed_s(self) -> float:
        """Elapsed time (s, monotonic, any origin) beside the loop clock: the loop tells a
        stall (the clock moved as elapsed time did) from a step of the clock by it."""
        return time.monotonic()

    def start(self) -> None:
        """Called once before the loop opens anything (a clock read from elsewhere connects)."""

    def stop(self) -> None:
        """Release what `start` took; called after the loop closed."""


class WallClock(Clock):
    """Monotonic wall time. `wait_until` sleeps until `spin_margin_s` before the
    deadline, then spins, which cuts lateness from ~0.1 ms to a few µs."""

    simulated = False
    fork_safe = True

    def __init__(self, spin_margin_s: float = 0.0002) -> None:
        self.spin_margin_s = spin_margin_s

    def now(self) -> float:
        return time.monotonic()

    def wait_until(self, deadline_s: float) -> None:
        rest = deadline_s - time.monotonic() - self.spin_margin_s
        if rest > 0:
            time.sleep(rest)
        while time.monotonic() < deadline_s:
            pass


class SimClock(Clock):
    """Simulated time: `wait_until` jumps to the deadline at once.

    With `speedup` > 0 the clock also paces itself against wall time, so that
    `speedup` simulated seconds pass per wall second (the demo uses that).
    """

    simulated = True

    def __init__(self, start_s: float = 0.0, speedup: float = 0.0) -> None:
        self.t_s = float(start_s)
        self.speedup = speedup
        self._wall0 = time.monotonic()
        self._sim0 = self.t_s

    def now(self) -> float:
        return self.t_s

    def wait_until(self, deadline_s: float) -> None:
        if deadline_s > self.t_s:
            self.t_s = deadline_s
        if self.speedup > 0:
            wall_due = self._wall0 + (self.t_s - self._sim0) / self.speedup
            rest = wall_due - time.monotonic()
            if rest > 0:
                time.sleep(rest)

    def set(self, t_s: float) -> None:
        """Jump (replay: to the next row's time)."""
        self.t_s = t_s
