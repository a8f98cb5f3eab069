"""The plant clocks over Modbus TCP against a pymodbus server: the following clock reads the plant
time on its I/O worker, gives up a wait when the plant stalls and fails when it is gone; the
lockstep clock runs the plant to each deadline and polls each source once, at that time, through
the source's own worker (which polls nothing unasked)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from compd.core.frame import Frame
from compd.sources.modbus import ModbusConfig, ModbusSource
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.plant_clock import LockstepPlantClock, PlantClock

WAIT_S = 20.0


class PlantTime:
    """A plant clock device's registers: time (ms, high word first), state; a write of
    registers 4–5 (lockstep) runs the plant to that time."""

    register_count = 8

    def __init__(self, t_ms: int = 0) -> None:
        self.mem = [0] * self.register_count
        self.mem[2] = 1
        self.set_ms(t_ms)
        self.run_tos: list[int] = []

    def set_ms(self, t_ms: int) -> None:
        self.mem[0], self.mem[1] = (t_ms >> 16) & 0xFFFF, t_ms & 0xFFFF

    def read_registers(self, address: int, count: int) -> list[int] | None:
        return self.mem[address : address + count] if address + count <= self.register_count else None

    def write_registers(self, address: int, values: list[int]) -> bool:
        if address != 4 or len(values) != 2:
            return False
        t_ms = (values[0] << 16) | values[1]
        self.run_tos.append(t_ms)
        self.set_ms(t_ms)
        return True


class Temps:
    """A PT100 module's registers: int16 × 0.1 °C."""

    register_count = 4

    def __init__(self) -> None:
        self.mem = [215, 230, 0, 0]

    def read_registers(self, address: int, count: int) -> list[int] | None:
        return self.mem[address : address + count] if address + count <= self.register_count else None

    def write_registers(self, address: int, values: list[int]) -> bool:
        return False


def _until(pred, timeout_s: float = WAIT_S) -> bool:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_plant_clock_follows_the_plant_time() -> None:
    plant = PlantTime(1500)
    with ModbusServerThread(plant, port=0) as srv:
        clock = PlantClock("127.0.0.1", srv.port, poll_period_s=0.002, stall_s=0.2, lost_s=0.5)
        clock.start()
        try:
            assert clock.now() == 1.5
            plant.set_ms(2500)
            assert _until(lambda: clock.now() == 2.5)
            clock.wait_until(2.0)  # reached already: returns at once
            clock.wait_until(100.0)  # the plant stands still: the wait gives up after stall_s
            assert clock.now() == 2.5
            assert clock.reads > 0
        finally:
            clock.stop()
        assert clock.now() == 2.5


def test_plant_clock_fails_when_the_plant_is_gone() -> None:
    plant = PlantTime(1000)
    srv = ModbusServerThread(plant, port=0).start()
    clock = PlantClock("127.0.0.1", srv.port, poll_period_s=0.002, stall_s=60.0, lost_s=0.3, timeout_s=0.1)
    try:
        clock.start()
        srv.stop()
        with pytest.raises(RuntimeError, match="no answer"):
            clock.wait_until(100.0)
        assert clock.errors > 0
    finally:
        clock.stop()
        srv.stop()


def test_plant_clock_start_without_a_plant_is_an_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    clock = PlantClock("127.0.0.1", port, timeout_s=0.05)
    with pytest.raises(RuntimeError, match="no answer"):
        clock.start()
    clock.stop()


class _Sink:
    def __init__(self) -> None:
        self.flushes = 0

    def await_held(self, timeout_s: float) -> bool:
        return True  # what the device holds is known (the lockstep clock asks before every release)

    def flush(self, timeout_s: float) -> bool:
        self.flushes += 1
        return True


def test_lockstep_clock_runs_the_plant_to_each_deadline_and_polls_each_source_once_there() -> None:
    plant, temps = PlantTime(0), Temps()
    cfg = ModbusConfig.model_validate(
        {
            "kind": "modbus",
            "name": "pt",
            "port": 1,
            "poll_period_s": 0.001,
            "timeout_s": 1.0,
            "channels": [{"name": "T1", "address": 0}, {"name": "T2", "address": 1}],
        }
    )
    with ModbusServerThread(plant, port=0) as psrv, ModbusServerThread(temps, port=0) as tsrv:
        source = ModbusSource(cfg.model_copy(update={"port": tsrv.port}))
        frame = Frame(source.signal_names())
        source.bind(frame)
        clock = LockstepPlantClock("127.0.0.1", psrv.port)
        clock.start()
        sink = _Sink()
        try:
            source.open(clock.now())
            source.start_polling(clock)  # adopted: its worker polls only when the clock asks
            clock.bind(sink, [source])
            assert clock.now() == 0.0 and source.polls == 0
            for k in (1, 2, 3):
                clock.wait_until(0.5 * k)
                assert clock.now() == 0.5 * k
                assert source.polls == k  # exactly one poll per release, none of its own
                source.read(frame, clock.now())
                assert frame.values.tolist() == pytest.approx([21.5 + (k - 1), 23.0])  # read at this release
                assert np.all(frame.stamp_s == 0.5 * k)  # stamped with the plant time
                temps.mem[0] += 10
            assert plant.run_tos == [500, 1000, 1500]
            assert sink.flushes == 3 and clock.releases == 3 and not clock.finished
        finally:
            source.close()
            clock.stop()
