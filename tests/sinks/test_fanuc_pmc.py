"""fanuc_pmc sink: splits large changes under the PMC's step limit, in process and over Modbus TCP."""

from __future__ import annotations

import time

import numpy as np
import pytest

from compd.codec import encode
from compd.plc.fanuc_pmc import FanucPmc
from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink, step_toward
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.scan import PmcScanThread

Z = np.zeros(2)
EN = np.ones(2, dtype=bool)


def test_step_toward():
    assert step_toward([0, 0], [12, -3], 5) == [5, -3]
    assert step_toward([5, -3], [12, -3], 5) == [10, -3]


@pytest.mark.parametrize("mode", ["word", "shift"])
def test_in_process_walks_to_target_without_alarm(mode):
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode=mode, max_step_um=5, step_limit_um=10))
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    word = encode(30, -20)
    applied = []
    out = np.zeros(2)
    for k in range(200):  # 2 ms cycles, simulated
        t = k * 0.002
        sink.write(word, Z, EN, k == 0, t)
        sink.settle(t)
        sink.applied_um(out)
        applied.append(out.copy())
    a = np.array(applied)
    assert a[-1].tolist() == [30.0, -20.0]
    assert np.max(np.abs(np.diff(a, axis=0))) <= 5.0
    assert sink.get_status()["alarm"] == 0
    sink.safe()
    sink.applied_um(out)
    assert out.tolist() == [0.0, 0.0]
    assert sink.get_status()["alarm"] == 0


def test_config_rejects_step_above_in_process_limit():
    with pytest.raises(ValueError, match="step_limit_um"):
        FanucPmcConfig(kind="fanuc_pmc", max_step_um=20, step_limit_um=10)


def _run_remote(sink: FanucPmcSink, word: int, seconds: float) -> None:
    t0 = time.monotonic()
    first = True
    while time.monotonic() - t0 < seconds:
        sink.write(word, Z, EN, first, time.monotonic())
        first = False
        time.sleep(0.002)


def test_over_modbus_tcp_against_scanning_pmc():
    pmc = FanucPmc(step_limit_um=10)
    scan = PmcScanThread(pmc).start()
    try:
        with ModbusServerThread(pmc, port=0) as srv:
            cfg = FanucPmcConfig(kind="fanuc_pmc", host="127.0.0.1", port=srv.port, max_step_um=5)
            sink = FanucPmcSink(cfg)
            sink.bind(["x1", "x2"], 1.0)
            sink.open(time.monotonic())
            try:
                _run_remote(sink, encode(25, -12), 0.6)
                sink.settle(0.0)
                time.sleep(0.05)
                assert pmc.applied_um() == [25.0, -12.0]
                assert pmc.alarms() == 0
                out = np.zeros(2)
                sink.applied_um(out)  # from the status the link reads back
                assert out.tolist() == [25.0, -12.0]
                sink.safe()
                time.sleep(0.05)
                assert pmc.applied_um() == [0.0, 0.0] and pmc.alarms() == 0
            finally:
                sink.close()
    finally:
        scan.stop()


def test_without_splitting_the_pmc_alarms():
    """The reason for max_step_um: one 25 µm jump trips the PMC's 10 µm limit."""
    pmc = FanucPmc(step_limit_um=10)
    sink = FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", max_step_um=63, step_limit_um=63), pmc=pmc)
    sink.bind(["x1", "x2"], 1.0)
    sink.open(0.0)
    pmc.write_registers(300, [10])  # D0: the machine's real limit
    sink.write(encode(25, 0), Z, EN, True, 0.05)
    sink.settle(0.05)
    assert pmc.alarms() == 0b01 and pmc.applied_um() == [0.0, 0.0]
