"""pci1756 sink with `device: modbus`: its DO bytes reach a PMC in another process's X inputs."""

from __future__ import annotations

import time

import numpy as np

from compd.codec import encode
from compd.plc.fanuc_pmc import FanucPmc
from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.scan import PmcScanThread


def test_do_bytes_drive_pmc_over_modbus_tcp():
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            cfg = Pci1756Config(kind="pci1756", device="modbus", port=srv.port, heartbeat_bit=24, strobe_bit=16)
            sink = Pci1756Sink(cfg)
            sink.bind(["x1", "x2"], 1.0)
            sink.open(0.0)
            assert sink.resync(5.0, 0.0)  # the X registers read back before anything is written
            z, en = np.zeros(2), np.ones(2, dtype=bool)
            try:
                for k, word in enumerate([encode(3, -2), encode(8, -6)]):
                    sink.write(word, z, en, True, 0.1 * k)
                    sink.card.link.flush()
                    time.sleep(0.05)  # several 8 ms scans
                    assert pmc.read_registers(0, 4)[:2] == [word & 0xFF, word >> 8]
                assert pmc.applied_um() == [8.0, -6.0]
                sink.safe()
                sink.card.link.flush()
                time.sleep(0.05)
                assert pmc.applied_um() == [0.0, 0.0]
            finally:
                sink.close()
    finally:
        scan.stop()
