"""The closed loop on a real controller (rig/linuxcnc_loop.py): LinuxCNC runs compd's thermal test, hil_sim's spindle
turns at LinuxCNC's spindle speed, compd compensates through LinuxCNC's external offsets, the error at the tool is
the plant's growth plus the offset LinuxCNC applied (read from HAL by the plant, not from compd).

The short run (make test): an 8 h test from `compd testplan`, its dwells divided by the plant's speedup (480: a
minute of wall time). The offset follows compd's correction within 1 µm (the reads in which the correction held
still), the error at the tool is cut, SIGTERM leaves 0. The 24 h test beside the in-process loop is in make accept
(scripts/accept_linuxcnc.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rig import linuxcnc_loop
from tests.linuxcnc.sim import Sim, require

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)


def test_linuxcnc_runs_compd_s_thermal_test_and_compd_compensates_the_plant_through_its_offsets(tmp_path: Path):
    require()
    with Sim() as sim:
        out = linuxcnc_loop.run(sim, tmp_path, hours=8, speedup=480.0, timeout_s=600.0)
    z = out["z"]
    print(
        f"\nLinuxCNC's offset - compd's correction: {out['follow_reads']} steady reads, largest"
        f" {out['follow_max_um']:.3f} um; z RMS {z['rms_before_um']:.2f} -> {z['rms_after_um']:.2f} um"
        f" ({z['reduction_pct']:.1f} %)"
    )
    assert out["follow_reads"] > 20 and out["follow_max_um"] <= 1.0, out
    assert out["compd_exit"] == 0 and abs(out["eoffset_after_um"]) < 0.15, out
    assert z["rms_before_um"] > 3.0 and z["rms_after_um"] < 0.5 * z["rms_before_um"], out
