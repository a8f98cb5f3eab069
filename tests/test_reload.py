"""SIGHUP: a bad config is rejected and the old one keeps running; a good one takes over without a step."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from compd.log import read_log

CONFIG = """\
loop: {{clock: sim, period_s: 1.0, speedup: 600}}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {{segments: [{{duration_s: 86400, speed_rpm: 12000}}]}}
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}
guard: {{max_slew_um_per_s: {slew}}}
sink: {{kind: pci1756}}
log: {{path: run.csv, period_s: 1.0, flush_s: 0.2}}
"""


def wait_for(pred, timeout_s: float = 20.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.05)


def test_sighup_reload(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(slew=0.05))
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            time.sleep(2.0)
            cfg.write_text(CONFIG.format(slew=0.05).replace("max_slew_um_per_s", "max_slew"))
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "reload rejected" in err_path.read_text())
            assert proc.poll() is None  # still running on the old config
            time.sleep(1.0)
            cfg.write_text(CONFIG.format(slew=0.02))
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "reloaded" in err_path.read_text())
            time.sleep(1.5)
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = err_path.read_text()
    assert proc.returncode == 0, text
    assert "guard.max_slew" in text and ":12:" in text
    log = read_log(tmp_path / "run.csv", allow_nan=True)
    t = log.col("t_s")
    corr = log.col("corr_z_um")
    assert t[-1] > 2000  # simulated seconds
    dt = np.diff(t)
    steps = np.abs(np.diff(corr))
    ok = dt > 0
    # never faster than the larger of the two slew limits, across both reloads
    assert (steps[ok] <= 0.05 * dt[ok] + 1e-9).all()
    assert corr.min() < -10  # it was compensating a warm spindle throughout
