"""An independent Modbus implementation (mbpoll, libmodbus) reads our devices over TCP and RTU."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from compd.plc.fanuc_pmc import FanucPmc
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from hil_sim.devices.ptypair import PtyPair

MBPOLL = shutil.which("mbpoll")
# `make test` installs mbpoll (make sysdeps); this skip only fires when run by hand without it.
pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll binary absent (make sysdeps installs it)")


def mbpoll(*args: str) -> dict[int, int]:
    """Run mbpoll once; {1-based register: signed value} from its output."""
    out = subprocess.run([MBPOLL, *args], capture_output=True, text=True, timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr
    return {int(a): int(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", out.stdout, re.M)}


def _tx():
    tx = Pt100Transmitter(["T1", "T2", "T3", "T4"], [25.3, 24.9, -3.2, 100.0])
    tx.set_fault("T2", "burnout")
    return tx


def test_mbpoll_reads_transmitter_over_tcp():
    with ModbusServerThread(Pt100ModbusDevice(_tx()), port=0) as srv:
        regs = mbpoll("-m", "tcp", "-p", str(srv.port), "-a", "1", "-r", "1", "-c", "4", "-1", "127.0.0.1")
    # int16 × 0.1 °C (mbpoll prints the raw 16 bits unsigned): −3.2 °C = 0xFFE0, burn-out 0x8000
    assert regs == {1: 253, 2: 0x8000, 3: 0xFFE0, 4: 1000}


def test_mbpoll_reads_transmitter_over_rtu(tmp_path):
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), ModbusServerThread(Pt100ModbusDevice(_tx()), serial_port=str(a)):
        regs = mbpoll("-m", "rtu", "-b", "115200", "-P", "none", "-a", "1", "-r", "1", "-c", "4", "-1", str(b))
    assert regs == {1: 253, 2: 0x8000, 3: 0xFFE0, 4: 1000}


def _pmc_with_shift() -> FanucPmc:
    pmc = FanucPmc()
    pmc.write_registers(0, [0x43, 0xC5, 1])  # word 0xC543 with the strobe up
    pmc.advance_to(0.02)
    assert pmc.applied_um() == [5.0, -3.0]
    return pmc


def test_mbpoll_reads_and_writes_pmc_over_tcp():
    pmc = _pmc_with_shift()
    with ModbusServerThread(pmc, port=0) as srv:
        # status block at 400 (mbpoll -r is 1-based): scans lo, hi, alarm, reset, applied 1, 2
        regs = mbpoll("-m", "tcp", "-p", str(srv.port), "-a", "1", "-r", "401", "-c", "6", "-1", "127.0.0.1")
        assert regs[405] == 5 and regs[406] == 0xFFFD and regs[403] == 0
        assert regs[401] | (regs[402] << 16) == pmc.scans
        # write the shift command of axis 1 (R2 = register 202) with mbpoll, let the PMC scan
        mbpoll("-m", "tcp", "-p", str(srv.port), "-a", "1", "-r", "203", "-1", "127.0.0.1", "9")
        pmc.advance_to(0.05)
        assert pmc.applied_um() == [9.0, -3.0]


def test_mbpoll_reads_pmc_over_rtu(tmp_path):
    pmc = _pmc_with_shift()
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), ModbusServerThread(pmc, serial_port=str(a)):
        regs = mbpoll("-m", "rtu", "-b", "115200", "-P", "none", "-a", "1", "-r", "201", "-c", "4", "-1", str(b))
    assert regs == {201: 0xC543, 202: 1, 203: 5, 204: 0xFFFD}
