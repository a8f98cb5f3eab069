"""The fixed-period loop: absolute schedule, lateness and misses, stage order, signals."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from compd.codec import decode
from compd.config import load_config
from compd.core.clock import Clock
from compd.daemon.app import App
from tests.service_helpers import wait_running

ROOT = Path(__file__).resolve().parents[2]

CONFIG = """\
loop:
  clock: {clock}
  period_s: {period}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario:
      segments: [{{duration_s: 36000, speed_rpm: 12000}}]
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}
guard:
  max_slew_um_per_s: {slew}
sink:
  kind: pci1756
"""


class ScriptedClock(Clock):
    """Simulated clock whose wake-ups are late by a scripted amount."""

    simulated = True

    def __init__(self, late_s: list[float], compute_s: float = 0.0) -> None:
        self.t = 0.0
        self.late = list(late_s)
        self.compute_s = compute_s
        self.deadlines: list[float] = []

    def now(self) -> float:
        return self.t

    def wait_until(self, deadline: float) -> None:
        self.deadlines.append(deadline)
        self.t = max(self.t, deadline) + (self.late.pop(0) if self.late else 0.0)


def make_app(tmp_path: Path, clock: str = "sim", period: float = 0.1, slew: float = 2.0) -> App:
    p = tmp_path / "c.yaml"
    p.write_text(CONFIG.format(clock=clock, period=period, slew=slew))
    return App(load_config(p))


def test_absolute_schedule_and_misses(tmp_path: Path) -> None:
    app = make_app(tmp_path)
    clock = ScriptedClock([0.0, 0.01, 0.06, 0.0, 0.25, 0.0, 0.0])
    app.loop.clock = clock
    app.open()
    stats = app.loop.run(max_cycles=7)
    app.close()
    # deadlines are start + k·period, never drifting with lateness
    assert clock.deadlines[:5] == [0.0, 0.1, 0.2, 0.30000000000000004, 0.4]
    # 0.06 s late is more than half a 0.1 s period: a miss; 0.25 s overran two deadlines
    assert stats.misses == 2
    assert stats.skipped == 2
    assert clock.deadlines[5] > 0.65
    assert stats.cycles == 7
    assert stats.lateness_us()["max"] == 250000.0


def test_stage_times_recorded(tmp_path: Path) -> None:
    app = make_app(tmp_path)
    app.open()
    stats = app.loop.run(max_cycles=50)
    app.close()
    stages = stats.stages()
    assert list(stages) == ["read", "model", "guard", "codec", "sink"]
    assert all(s["max_us"] > 0 for s in stages.values())
    assert stats.compute_us()["max"] > 0


def test_sim_run_compensates_and_ends_safe(tmp_path: Path) -> None:
    app = make_app(tmp_path, period=1.0)
    app.duration_s = 3 * 3600
    result = app.run()
    comp = result["compensation"]["z"]
    assert comp["rms_before_um"] > 10
    assert comp["reduction_pct"] > 70
    assert app.sink.card.read_do_word(0) == 0  # safe output after the run


def test_slew_limit_never_exceeded(tmp_path: Path) -> None:
    app = make_app(tmp_path, period=1.0, slew=0.01)
    steps: list[float] = []
    last = [0.0]

    def watch(loop, now):  # noqa: ANN001
        steps.append(abs(loop.guard.out_um[0] - last[0]))
        last[0] = loop.guard.out_um[0]

    app.loop.observers.append(watch)
    app.duration_s = 3600
    app.run()
    assert max(steps) <= 0.01 * 1.0 + 1e-12
    assert last[0] < 0  # it did move (toward minus the growth)


def test_sigterm_emits_safe_output_and_exits_0(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    status = tmp_path / "status.json"
    p.write_text(
        CONFIG.format(clock="wall", period=0.002, slew=1000.0) + f"status:\n  path: {status}\n  period_s: 0.05\n"
    )
    out = tmp_path / "summary.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "compd", "run", str(p), "--json", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        # signal once the loop has run (the status file says so), however slow the machine
        wait_running(status, proc, 60.0, after_cycles=100)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    summary = json.loads(out.read_text())
    assert summary["loop"]["cycles"] > 100
    assert summary["sink"]["word"] == "0x0000"
    assert summary["sink"]["writes"] > 100


def test_model_update_period_holds_output(tmp_path: Path) -> None:
    app = make_app(tmp_path, period=1.0)
    app.model.update_period_s = 60.0
    preds = []
    app.loop.observers.append(lambda loop, now: preds.append(float(loop.pred_um[0])))
    app.duration_s = 600
    app.run()
    changes = np.count_nonzero(np.diff(preds))
    assert 5 <= changes <= 10


@pytest.mark.slow
def test_word_walks_one_lsb_at_the_slew_pace(tmp_path: Path) -> None:
    """The audit's case through the whole loop: 10 ms cycles, slew 2 µm/s, dead-band 3 µm.
    The word on the card changes by one LSB at a time, no faster than lsb/slew, and stays
    within the dead-band of the guarded correction (it used to jump 3 → 6 LSB and hold −10
    for −11.22 µm)."""
    p = tmp_path / "c.yaml"
    p.write_text(CONFIG.format(clock="sim", period=0.01, slew=2.0) + "codec: {deadband_um: 3.0}\n")
    app = App(load_config(p))
    trace: list[tuple[float, int, float]] = []

    def watch(loop, now):  # noqa: ANN001
        x1 = decode(loop.sink.card.read_do_word(0))[0]  # what the card carries
        trace.append((now, x1.direction * x1.magnitude if x1.enable else 0, float(loop.guard.out_um[0])))

    app.loop.observers.append(watch)
    app.duration_s = 900.0
    app.run()
    steps = [(t, q - q0) for (t, q, _), (_, q0, _) in zip(trace[1:], trace, strict=False) if q != q0]
    assert len(steps) >= 5  # the spindle grew: the word did walk
    assert all(abs(d) == 1 for _, d in steps)
    for (t0, _), (t1, _) in zip(steps, steps[1:], strict=False):
        assert t1 - t0 >= 1.0 / 2.0 - 0.01 - 1e-9  # lsb/slew, less one cycle's carry
    assert max(abs(q - c) for _, q, c in trace) <= 3.0 + 2 * 2.0 * 0.01 + 1e-9
    word = app.sink.card.read_do_word(0)
    assert word == 0  # safe output after the run


def test_a_clock_jump_during_a_cycle_is_seen_and_licenses_no_slew(tmp_path: Path) -> None:
    """The clock jumps 60 s while a cycle works: the skip to the next deadline must not hide
    it, and the next cycle licenses one period of slew, not 60 s of it."""
    app = make_app(tmp_path, slew=2.0)
    clock = ScriptedClock([])
    app.loop.clock = clock
    dts: list[float] = []

    def jump_in_cycle_5(loop, now):  # noqa: ANN001
        dts.append(loop.guard.dt_s)
        if len(dts) == 5:
            clock.t += 60.0

    app.loop.observers.append(jump_in_cycle_5)
    app.open()
    stats = app.loop.run(max_cycles=10)
    app.close()
    jumps = [e for e in app.guard.events if e[1:3] == ("clock", "jump")]
    assert len(jumps) == 1 and "+60.0" in jumps[0][3], app.guard.events
    assert max(dts) == pytest.approx(0.1)
    assert stats.skipped > 500  # the loop went on from the new time
