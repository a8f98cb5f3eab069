"""The hal source against a real (headless) LinuxCNC: the spindle speed a program commands, read through
compd's input component (`compd.in.speed_rpm`, netted by compd to spindle.0.speed-out)."""

from __future__ import annotations

import numpy as np
import pytest

from compd.core.frame import Quality
from compd.io.mailbox import Snapshot
from compd.io.worker import LinkDown
from compd.sources.hal import HalConfig, HalPoller
from tests.linuxcnc.sim import Sim, require, wait_for


def _poller() -> HalPoller:
    cfg = HalConfig(
        kind="hal", name="cnc", signals=[{"name": "speed_rpm", "pin": "spindle.0.speed-out"}, {"name": "T_spare"}]
    )
    return HalPoller(cfg, Snapshot(2))


def test_the_spindle_speed_of_a_running_program_reads_through_compd_in():
    require()
    with Sim() as sim:
        poller = _poller()
        try:
            with pytest.raises(LinkDown, match=r"compd\.in\.T_spare"):  # a signal nobody writes: never GOOD
                poller.connect()
            sim.halcmd("net", "spare", "motion.analog-out-00", "compd.in.T_spare")  # the HAL file's net
            poller.connect()
            values, quality = np.full(2, np.nan), np.zeros(2, dtype=np.uint8)
            program = sim.folder / "spin.ngc"
            program.write_text("G21 G90\nS3000 M3\nG4 P5\nM5\nM2\n")
            sim.run_program(program)

            def speed() -> bool:
                poller.poll(values, quality)
                return bool(
                    quality[0] == Quality.GOOD
                    and values[0] == pytest.approx(3000.0)
                    and quality[1] == Quality.GOOD
                    and values[1] == 0.0
                )

            wait_for(speed, "compd.in.speed_rpm at 3000 rpm")
            assert "compd.in" in sim.halcmd("show", "comp")
        finally:
            poller.close()
        assert "compd.in" not in sim.halcmd("show", "comp")
