"""Lockstep closed loop: the same seed gives the same residual log, byte for byte, on an idle
machine and beside two CPU-bound processes (the plant waits for compd, never for wall time)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig import closedloop as cl

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

# 2 plant-hours of the spindle's unseen day: 9000 rpm jobs, the PMC's shift moves
# within the first hour (word mode: latch on the strobe, step limit, on plant time)
HOURS, SPEEDUP = 2.0, 7200.0


def _burners(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def test_lockstep_residual_log_is_byte_identical_idle_and_beside_cpu_hogs(tmp_path):
    model = cl.prepare_model("spindle", "xi_spindle", tmp_path)
    idle = cl.closed_loop("spindle", model, tmp_path / "idle", speedup=SPEEDUP, duration_s=HOURS * 3600)
    hogs = _burners(2)
    try:
        busy = cl.closed_loop("spindle", model, tmp_path / "busy", speedup=SPEEDUP, duration_s=HOURS * 3600)
    finally:
        for p in hogs:
            p.kill()
        for p in hogs:
            p.wait()
    print(f"idle {idle['wall_s']:.1f} s wall, beside two CPU hogs {busy['wall_s']:.1f} s")
    a = Path(idle["residual_log"]).read_bytes()
    b = Path(busy["residual_log"]).read_bytes()
    assert a == b
    # and the run did something: the PMC applied a shift that cut the error
    applied = np.loadtxt(idle["residual_log"], delimiter=",", skiprows=1)[:, 3]
    assert np.count_nonzero(applied) > 100
    assert idle["axes"]["z"]["reduction_pct"] > 50.0
    assert idle["sink"]["updates"] == busy["sink"]["updates"] > 5
