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
    assert sink.sync(0.0)  # the NC's data read back before anything is written
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
            assert sink.resync(5.0, 0.0)  # the NC's data read back over Modbus
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


def test_in_process_the_nc_ramps_toward_k0_over_the_time_since_the_last_call():
    """A call 10 s after the last hands the NC the new K0 where its time stood, so the NC ramps
    over those 10 s (5 µm/s) and applies 12 µm by the call: not one call late."""
    sink = _sink(_Model(), velo_factor=1e-5, ipo_s=0.004)
    out = np.zeros(1)
    sink.write(0, np.array([0.0]), np.array([True]), True, 0.0)
    sink.settle(0.0)
    sink.write(0, np.array([12.0]), np.array([True]), False, 10.0)
    sink.settle(10.0)
    sink.applied_um(out)
    assert out[0] == pytest.approx(12.0, abs=1e-4)
    sink.commanded_um(out)
    assert out[0] == pytest.approx(12.0, abs=1e-4)
    # faster than the NC's ramp: 100 µm in 10 s at 5 µm/s gets 50 µm there, the rest later
    sink.write(0, np.array([112.0]), np.array([True]), False, 20.0)
    sink.settle(20.0)
    sink.applied_um(out)
    assert out[0] == pytest.approx(62.0, abs=0.05)


@pytest.mark.parametrize("model", [_Model(), _LinearModel()])
def test_write_rows_equals_writing_row_by_row(model):
    """`write_rows` (the rows where the NC sits on its target and no K0 is due skipped) gives
    the applied and commanded ΔK of write, settle and read at every row, each write with its
    row's linear terms."""
    from compd.sinks.base import Sink

    rng = np.random.default_rng(4)
    n = 3000
    t = np.cumsum(rng.choice([0.002, 0.5, 1.0, 10.0], n, p=[0.2, 0.3, 0.4, 0.1]))
    corr = np.cumsum(rng.choice([0.0, 0.0, 0.0, 0.05, -0.05, 0.3, 3.0, -2.0], (n, 1)), axis=0)
    en = rng.random((n, 1)) > 0.02
    words, changed = np.zeros(n, np.int64), np.zeros(n, bool)
    terms = [[(0.01 + 1e-4 * i, 100.0)] for i in range(n)] if model.linear_terms() else None
    ref, got = _sink(model, min_update_s=0.3), _sink(model, min_update_s=0.3)
    a1, c1, a2, c2 = (np.zeros((n, 1)) for _ in range(4))
    if terms is None:
        Sink.write_rows(ref, t, words, changed, corr, en, a1, c1)
    else:  # the reference writes with each row's terms as the model would give them
        for i in range(n):
            ref._row_terms = terms[i]
            Sink.write_rows(
                ref,
                t[i : i + 1],
                words[i : i + 1],
                changed[i : i + 1],
                corr[i : i + 1],
                en[i : i + 1],
                a1[i : i + 1],
                c1[i : i + 1],
            )
    got.write_rows(t, words, changed, corr, en, a2, c2, terms)
    np.testing.assert_array_equal(a2, a1)
    np.testing.assert_array_equal(c2, c1)
    assert (np.abs(a1 - c1) > 1e-3).any()  # the NC ramping behind its target in places
    ref.link.flush()
    got.link.flush()
    assert got.nc.mem == ref.nc.mem
