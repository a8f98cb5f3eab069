"""Small configs for the service tests (the sim spindle, a replay log with a sensor fault) and a
wait for a daemon's status file."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np

SIM = """
loop: {{clock: sim, period_s: {period_s}, speedup: {speedup}}}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {{seed: 3, segments: [{{duration_s: {duration_s}, speed_rpm: 10000}}]}}
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
sink: {{kind: pci1756}}
{extra}
"""


def sim_config(
    tmp_path: Path, extra: str = "", *, duration_s: float = 1800, period_s: float = 1.0, speedup: float = 0
) -> Path:
    path = tmp_path / "sim.yaml"
    path.write_text(
        SIM.format(extra=extra, duration_s=duration_s, period_s=period_s, speedup=speedup),
        encoding="utf-8",
    )
    return path


def fault_config(tmp_path: Path, extra: str = "") -> Path:
    """A replay of a warming ξ sensor that reads 900 °C between t = 200 s and 300 s."""
    t = np.arange(0.0, 1000.0, 10.0)
    temp = 20.0 + 0.01 * t
    temp[(t >= 200) & (t < 300)] = 900.0
    rows = ["t_s,T_xi,err_z_um"] + [f"{a:g},{b:g},{2.2 * (b - 20):g}" for a, b in zip(t, temp, strict=True)]
    (tmp_path / "fault.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    path = tmp_path / "fault.yaml"
    path.write_text(
        f"""
loop: {{clock: sim, period_s: 1.0}}
sources: [{{kind: replay, name: log, path: fault.csv}}]
model: {{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}}}
guard:
  recovery_s: 20
  stale_after_s: 60
  signals: {{T_xi: {{min: 0, max: 80}}}}
sink: {{kind: pci1756}}
{extra}
""",
        encoding="utf-8",
    )
    return path


def wait_running(status_file: Path, proc: subprocess.Popen, timeout_s: float = 120, *, after_cycles: int = 0) -> dict:
    """The daemon's status once it says running with more than `after_cycles` cycles; the
    process must stay alive meanwhile."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        try:
            data = json.loads(status_file.read_text())
            if data["state"] == "running" and data["loop"]["cycles"] > after_cycles:
                return data
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    raise AssertionError(f"the daemon never reported running in {status_file}")
