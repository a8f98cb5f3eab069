"""siemens sink: K0 (and tanβ, P0) into the NC emulator, whose IPO cycle caps the change (MD32760)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from compd.plc.siemens_nc import SiemensNc
from compd.sinks.siemens import SiemensConfig, SiemensSink, regs_f32
from hil_sim.devices.modbus_server import ModbusServerThread


class _Model:
    outputs = ["z"]

    def linear_terms(self):
        return None  # not position dependent (Model's default)


class _LinearModel:
    outputs = ["z"]

    def linear_terms(self):
        return [(0.01, 100.0)]  # error slope 0.01 µm/mm about P0 = 100 mm


def _sink(model, **kw):
    sink = SiemensSink(SiemensConfig(kind="siemens", **kw))
    sink.bind(["z"], 1.0)
    sink.bind_model(model)
    sink.open(0.0)
    return sink


def test_k0_ramps_at_the_md32760_rate():
    sink = _sink(_Model(), velo_factor=1e-5, ipo_s=0.004)
    nc = sink.nc
    cap_um = 1e-5 * 30000 / 60 * 0.004 * 1000  # MD32760 × v_max × IPO, in µm
    assert nc.cap_mm(0) * 1000 == pytest.approx(cap_um)
    out = np.zeros(1)
    sink.write(0, np.array([12.0]), np.array([True]), True, 0.0)
    sink.settle(1.0)
    sink.applied_um(out)
    # IPO cycles after the write in (0, 1] s: 250 (± one for float accumulation of the IPO clock)
    assert out[0] == pytest.approx(cap_um * 250, abs=cap_um * 1.01)
    sink.settle(5.0)
    sink.applied_um(out)
    assert out[0] == pytest.approx(12.0, abs=1e-4)
    assert nc.mem[6] == 1  # MD32750: position independent only


def test_position_dependent_terms():
    sink = _sink(_LinearModel())
    nc = sink.nc
    assert nc.mem[6] == 3
    nc.set_position(0, 300.0)
    sink.write(0, np.array([12.0]), np.array([True]), True, 0.0)
    sink.settle(10.0)
    # ΔK = K0 + tanβ (P − P0) = 12 µm − 0.01 µm/mm × 200 mm
    assert nc.applied_mm()[0] * 1000 == pytest.approx(10.0, abs=1e-3)


def test_over_modbus_tcp():
    nc = SiemensNc(2)
    with ModbusServerThread(nc, port=0) as srv:
        sink = SiemensSink(SiemensConfig(kind="siemens", host="127.0.0.1", port=srv.port, axes={"z": 1}))
        sink.bind(["z"], 1.0)
        sink.bind_model(_Model())
        sink.open(0.0)
        try:
            sink.write(0, np.array([-7.5]), np.array([True]), True, time.monotonic())
            sink.settle(0.0)
            c = ModbusTcpClient("127.0.0.1", port=srv.port, timeout=1, retries=0)
            try:
                rr = c.read_holding_registers(16, count=8, device_id=1)
            finally:
                c.close()
            assert regs_f32(rr.registers[0], rr.registers[1]) * 1000 == pytest.approx(-7.5, abs=1e-4)
            assert rr.registers[6] == 1
        finally:
            sink.close()
