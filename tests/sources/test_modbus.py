"""Modbus source against the hil_sim PT100 module over real Modbus TCP and RTU (socat pty)."""

from __future__ import annotations

import struct

import pytest

from compd.sources.modbus import ModbusConfig, ModbusSource, decode_registers, plan_reads
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from hil_sim.devices.ptypair import PtyPair
from tests.sources.helpers import Harness

TEMPS = [25.3, 24.9, -3.2, 100.0]
NAMES = ["T1", "T2", "T3", "T4"]


def test_decode_int16_scaled_and_codes():
    raw, v = decode_registers([253], "int16")
    assert (raw, v) == (253, 253.0)
    raw, v = decode_registers([0xFFE0], "int16")
    assert raw == 0xFFE0 and v == -32.0
    raw, v = decode_registers([0x8000], "int16")
    assert raw == 0x8000 and v == -32768.0


@pytest.mark.parametrize("byte_order", ["big", "little"])
@pytest.mark.parametrize("word_order", ["big", "little"])
def test_decode_float32_orders(byte_order, word_order):
    b = struct.pack(">f", 24.75)
    words = [b[0:2], b[2:4]]
    if byte_order == "little":
        words = [w[::-1] for w in words]
    if word_order == "little":
        words = words[::-1]
    regs = [int.from_bytes(w, "big") for w in words]
    assert decode_registers(regs, "float32", byte_order, word_order)[1] == 24.75


def test_decode_int32_word_order():
    v = -123456
    hi, lo = (v & 0xFFFFFFFF) >> 16, v & 0xFFFF
    assert decode_registers([hi, lo], "int32")[1] == v
    assert decode_registers([lo, hi], "int32", word_order="little") == ((hi << 16) | lo, v)


def test_plan_reads_merges_consecutive():
    assert plan_reads([(0, 1), (1, 1), (2, 1), (3, 1)]) == [(0, 4)]
    assert plan_reads([(0, 2), (2, 2), (10, 1)]) == [(0, 4), (10, 1)]
    assert plan_reads([(0, 1), (3, 1)], max_gap=2) == [(0, 4)]
    assert plan_reads([(0, 100), (100, 100)]) == [(0, 100), (100, 100)]


def _cfg(**kw):
    base = {
        "kind": "modbus",
        "name": "pt100",
        "timeout_s": 0.1,
        "poll_period_s": 0.01,
        "reconnect_min_s": 0.02,
        "reconnect_max_s": 0.1,
        "channels": [{"name": n, "address": i, "status_address": 10 + i} for i, n in enumerate(NAMES)],
    }
    base.update(kw)
    return ModbusConfig.model_validate(base)


def _device(**kw):
    tx = Pt100Transmitter(NAMES, TEMPS)
    return tx, Pt100ModbusDevice(tx, status_address=10, **kw)


def _check_faults(h: Harness, tx: Pt100Transmitter, srv: ModbusServerThread, slow_s: float = 0.3):
    """Values, module codes, then each wire fault and the recovery after it (`slow_s`: an
    answer later than the source's timeout)."""
    s = h.sample()
    for n, t in zip(NAMES, TEMPS, strict=True):
        assert s[n][1] == "GOOD"
        assert s[n][0] == pytest.approx(t, abs=1e-9)
    assert h.source.requests == [(0, 4), (10, 4)]  # consecutive registers: one request each

    tx.set_fault("T2", "burnout")
    tx.set("T3", 300.0)  # beyond the module's 250 °C range → over-range code
    s = h.sample()
    assert s["T2"][1] == "BURNOUT"
    assert s["T3"][1] == "OUT_OF_RANGE"
    assert s["T1"] == (pytest.approx(25.3), "GOOD")
    tx.set_fault("T2", "none")
    tx.set("T3", -3.2)

    for fault in ("exception", "no_answer", "garbage", "crc_error", "slow"):
        srv.faults.set(fault, slow_s=slow_s)
        s = h.sample(polls=2)
        assert {q for _, q in s.values()} == {"COMMS_LOST"}, fault
        srv.faults.set("none")
        s = h.sample(polls=3)
        assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS], f"after {fault}"


def test_tcp_values_and_faults():
    tx, dev = _device()
    with (
        ModbusServerThread(dev, port=0) as srv,
        Harness(ModbusSource(_cfg(transport="tcp", port=srv.port))) as h,
    ):
        _check_faults(h, tx, srv)
        assert h.source.get_status()["exception_replies"] >= 1
        assert h.source.get_status()["comm_errors"] >= 3


def test_rtu_values_and_faults(tmp_path):
    tx, dev = _device()
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), ModbusServerThread(dev, serial_port=str(a)) as srv:
        # the server thread shares this process: a timeout that a busy machine cannot break
        cfg = _cfg(transport="rtu", serial_port=str(b), baudrate=115200, timeout_s=0.5)
        with Harness(ModbusSource(cfg)) as h:
            _check_faults(h, tx, srv, slow_s=1.5)


def test_float32_little_word_order_and_nan_burnout():
    tx = Pt100Transmitter(NAMES, TEMPS)
    dev = Pt100ModbusDevice(tx, data_type="float32", scale=1.0, word_order="little")
    chans = [{"name": n, "address": 2 * i} for i, n in enumerate(NAMES)]
    with ModbusServerThread(dev, port=0) as srv:
        cfg = _cfg(port=srv.port, data_type="float32", scale=1.0, word_order="little", channels=chans)
        with Harness(ModbusSource(cfg)) as h:
            s = h.sample()
            assert [s[n][0] for n in NAMES] == pytest.approx(TEMPS, abs=1e-5)
            assert h.source.requests == [(0, 8)]
            tx.set_fault("T4", "burnout")
            assert h.sample()["T4"][1] == "BURNOUT"


def test_slow_answer_within_timeout_reads_stale():
    tx, dev = _device()
    with ModbusServerThread(dev, port=0) as srv:
        cfg = _cfg(port=srv.port, timeout_s=1.0, stale_after_s=0.1)
        with Harness(ModbusSource(cfg)) as h:
            assert h.sample()["T1"] == (pytest.approx(25.3), "GOOD")
            srv.faults.set("slow", slow_s=0.25)
            s = h.sample(polls=2)
            assert s["T1"] == (pytest.approx(25.3), "STALE")  # the value arrives, but it is old


def test_reconnects_after_server_restart():
    tx, dev = _device()
    srv = ModbusServerThread(dev, port=0).start()
    port = srv.port
    try:
        with Harness(ModbusSource(_cfg(port=port))) as h:
            assert h.sample()["T1"][1] == "GOOD"
            srv.stop()
            assert h.sample(polls=3)["T1"][1] == "COMMS_LOST"
            srv = ModbusServerThread(dev, port=port).start()
            # back once a reconnect (its back-off up to reconnect_max_s) went through: a condition, not 4 polls
            assert h.sample_good()["T1"] == (pytest.approx(25.3), "GOOD")
            assert h.source.get_status()["connects"] >= 2
    finally:
        srv.stop()


def test_config_requires_serial_port_for_rtu():
    with pytest.raises(ValueError, match="serial_port"):
        ModbusConfig.model_validate(
            {"kind": "modbus", "name": "x", "transport": "rtu", "channels": [{"name": "a", "address": 0}]}
        )


def test_bit_channel_reads_one_register_bit_without_fault_codes():
    """A PMC signal (Y5.2, Y5.15) as 0/1: 0x8004 is a burn-out code for a temperature, not for a bit."""
    from compd.plc.fanuc_pmc import FanucPmc

    pmc = FanucPmc()
    pmc.write_registers(105, [0x8004])
    channels = [
        {"name": "inh", "address": 105, "bit": 2},
        {"name": "b15", "address": 105, "bit": 15},
        {"name": "b0", "address": 105, "bit": 0},
    ]
    with (
        ModbusServerThread(pmc, port=0) as srv,
        Harness(ModbusSource(_cfg(port=srv.port, channels=channels))) as h,
    ):
        s = h.sample()
        assert s == {"inh": (1.0, "GOOD"), "b15": (1.0, "GOOD"), "b0": (0.0, "GOOD")}
        pmc.write_registers(105, [0])
        s = h.sample(polls=2)
        assert s["inh"] == (0.0, "GOOD")
