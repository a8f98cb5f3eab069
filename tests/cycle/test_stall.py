"""A stall and a clock step are different events: `loop_stall` when the loop did not run (the
clock moved as far as elapsed time did), `clock_jump` when the loop clock itself stepped. Both
keep the output from stepping for the gap."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from compd.config import load_config
from compd.core.clock import Clock
from compd.core.frame import Quality
from compd.cycle.guard import Guard
from compd.daemon.app import App
from compd.daemon.host import log_guard_event
from tests.cycle.test_guard import make, run
from tests.cycle.test_loop import CONFIG, ScriptedClock

PERIOD_S = 0.1  # the loop's threshold: max(20 periods, 0.5 s) = 2 s


class ElapsedClock(Clock):
    """A scripted clock whose time follows elapsed time, as the wall clock's does (`rate` loop
    seconds per elapsed second: 1, or a plant's speed-up). `stall_s` makes a wake-up late with
    elapsed time moving as far (the process did not run); `offset_s` moves the clock alone
    (a step). The loop reads elapsed time from `elapsed_s`."""

    simulated = False

    def __init__(self, rate: float = 1.0) -> None:
        self.rate = rate
        self.e = 0.0  # elapsed time, s
        self.offset_s = 0.0
        self.stall_s = 0.0  # added to the next wake-up, then cleared

    def now(self) -> float:
        return self.rate * self.e + self.offset_s

    def elapsed_s(self) -> float:
        return self.e

    def wait_until(self, deadline_s: float) -> None:
        self.e = max(self.e, (deadline_s - self.offset_s) / self.rate) + self.stall_s
        self.stall_s = 0.0


def _app(tmp_path: Path, clock: Clock) -> App:
    p = tmp_path / "c.yaml"
    p.write_text(CONFIG.format(clock="sim", period=PERIOD_S, slew=2.0))
    app = App(load_config(p))
    app.loop.clock = clock
    return app


def _run(app: App, cycles: int, at_cycle: int, act: Any) -> list[float]:
    """Run `cycles` cycles; `act(clock)` inside cycle `at_cycle`. The guard's dt of each cycle."""
    dts: list[float] = []

    def watch(loop: Any, now: float) -> None:
        dts.append(loop.guard.dt_s)
        if len(dts) == at_cycle:
            act(loop.clock)

    app.loop.observers.append(watch)
    app.open()
    try:
        app.loop.run(max_cycles=cycles)
    finally:
        app.close()
    return dts


def _events(app: App, event: str) -> list[tuple[float, str, str, str]]:
    return [e for e in app.guard.events if e[2] == event]


def test_a_late_wake_up_on_a_clock_that_did_not_step_is_a_stall(tmp_path: Path) -> None:
    app = _app(tmp_path, ElapsedClock())
    dts = _run(app, 12, 5, lambda c: setattr(c, "stall_s", 3.0))  # the next wake-up 3 s late
    stalls = _events(app, "stall")
    assert [(s, r) for _, s, _, r in stalls] == [("loop", "woke 3.000 s late")], app.guard.events
    assert _events(app, "jump") == []
    assert app.guard.faults.get("stall:loop") == 1
    assert max(dts) == pytest.approx(PERIOD_S)  # the output never stepped for the gap


def test_a_stall_during_a_cycles_work_is_a_stall(tmp_path: Path) -> None:
    """The process stops while a cycle works: the next wake-up is on time for a deadline after
    the skip, but 3 s after the cycle before; elapsed time moved as far."""
    app = _app(tmp_path, ElapsedClock())
    dts = _run(app, 12, 5, lambda c: setattr(c, "e", c.e + 3.0))
    stalls = _events(app, "stall")
    assert len(stalls) == 1 and stalls[0][3].endswith("s since the last cycle"), app.guard.events
    assert _events(app, "jump") == []
    assert max(dts) == pytest.approx(PERIOD_S)


def test_a_step_of_the_clock_is_a_clock_jump_not_a_stall(tmp_path: Path) -> None:
    """The clock moves 60 s ahead while elapsed time moves one period: it stepped."""
    app = _app(tmp_path, ElapsedClock())
    dts = _run(app, 12, 5, lambda c: setattr(c, "offset_s", c.offset_s + 60.0))
    jumps = _events(app, "jump")
    assert len(jumps) == 1 and jumps[0][1] == "clock" and "+60.0" in jumps[0][3], app.guard.events
    assert _events(app, "stall") == []
    assert max(dts) == pytest.approx(PERIOD_S)


def test_on_a_plants_clock_a_stall_is_scaled_by_its_rate(tmp_path: Path) -> None:
    """A plant at 100× wall time: 0.05 s without running is 5 s of plant time late, a stall
    (the clock's rate, measured so far, explains it); a 60 s step is still a jump."""
    app = _app(tmp_path, ElapsedClock(rate=100.0))
    _run(app, 400, 300, lambda c: setattr(c, "stall_s", 0.05))  # 300 cycles: 0.3 s of elapsed time
    stalls = _events(app, "stall")
    assert len(stalls) == 1 and stalls[0][3].startswith("woke 5.0"), app.guard.events
    assert _events(app, "jump") == []
    app = _app(tmp_path, ElapsedClock(rate=100.0))
    _run(app, 400, 300, lambda c: setattr(c, "offset_s", c.offset_s + 60.0))
    assert len(_events(app, "jump")) == 1 and _events(app, "stall") == [], app.guard.events


def test_on_a_simulated_clock_a_gap_is_a_clock_jump(tmp_path: Path) -> None:
    """A simulated clock's time does not elapse by itself: a late wake-up is the clock set ahead."""
    app = _app(tmp_path, ScriptedClock([0.0] * 5 + [3.0]))
    _run(app, 12, 0, lambda c: None)
    jumps = _events(app, "jump")
    assert len(jumps) == 1 and _events(app, "stall") == [], app.guard.events


def test_clock_stepped() -> None:
    jump_s = 0.5
    assert not Guard.clock_stepped(0.812, 0.812, 1.0, False, jump_s)  # wall clock: woke late, a stall
    assert Guard.clock_stepped(60.01, 0.01, 1.0, False, jump_s)  # moved 60 s in 10 ms: a step
    assert Guard.clock_stepped(-3.0, 0.002, 1.0, False, jump_s)  # time went backwards
    assert Guard.clock_stepped(0.812, 0.812, 1.0, True, jump_s)  # simulated: any gap is a step
    assert not Guard.clock_stepped(10.0, 0.1, 100.0, False, jump_s)  # a plant at 100×: a 0.1 s stall
    assert Guard.clock_stepped(70.0, 0.1, 100.0, False, jump_s)  # ... and a 60 s step on it


def test_guard_stall_never_licenses_a_step() -> None:
    g, f = make()
    run(g, f, [0.0] * 5)
    f.set(0, 25.0, Quality.GOOD, 5.3)
    g.stall(5.3, 0.1, 0.812, 0.9)
    ok = g.check_inputs(f, 5.3)
    g.update(np.array([50.0]), ok, 5.3)
    assert abs(g.out_um[0]) <= 10.0 * 0.1 + 1e-12  # one period's slew (10 µm/s), not 0.9 s of it
    assert g.events[-1] == (5.3, "loop", "stall", "woke 0.812 s late")
    assert g.faults == {"stall:loop": 1}


def test_the_service_logs_loop_stall_and_clock_jump(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="compd.service"):
        log_guard_event(12.5, "loop", "stall", "woke 0.812 s late")
        log_guard_event(20.0, "clock", "jump", "+60.010 s since the last cycle")
    stall, jump = caplog.records
    assert (stall.event, stall.loop, stall.levelno) == ("loop_stall", "loop", logging.WARNING)
    assert (jump.event, jump.clock, jump.levelno) == ("clock_jump", "clock", logging.WARNING)
