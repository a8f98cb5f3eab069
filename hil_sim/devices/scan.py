"""The software PLC's CNCs on wall time: the threads that run a served PMC's scans and an NC's IPO cycles."""

from __future__ import annotations

import time

from compd.plc.fanuc_pmc import FanucPmc
from compd.plc.siemens_nc import SiemensNc
from hil_sim.devices.worker import DeviceThread


class PmcScanThread(DeviceThread):
    """Runs a PMC's scans on wall time, on an absolute schedule (start + k·scan_s)."""

    thread_name = "pmc-scan"

    def __init__(self, pmc: FanucPmc) -> None:
        super().__init__()
        self.pmc = pmc

    def _run(self) -> None:
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set():
            self.pmc.scan()
            k += 1
            rest = t0 + k * self.pmc.scan_s - time.monotonic()
            if rest > 0:
                self._stop.wait(rest)
            elif rest < -self.pmc.scan_s:  # overran: skip what is past
                k += int(-rest / self.pmc.scan_s)


class NcIpoThread(DeviceThread):
    """Runs an NC's IPO cycles on wall time."""

    thread_name = "nc-ipo"

    def __init__(self, nc: SiemensNc) -> None:
        super().__init__()
        self.nc = nc
        self._t0 = 0.0

    def _open(self) -> None:
        self._t0 = time.monotonic()
        self.nc.start_at(0.0)

    def _run(self) -> None:
        while not self._stop.wait(self.nc.ipo_s):
            self.nc.advance_to(time.monotonic() - self._t0)
