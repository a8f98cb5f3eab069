"""Matrix rows for faults on the wire and around the loop: servers killed or slow, bad replies,
RTU garbage and CRC errors, a closed pty, CAN silence, a clock jump, a full disk."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pytest

from hil_sim.devices.can_pt100 import CanChannel, CanPt100
from hil_sim.devices.dcon import DconModule
from hil_sim.devices.modbus_server import ModbusServerThread, WireFaults
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from hil_sim.devices.ptypair import PtyPair
from tests.faults.harness import (
    CLEAR_S,
    FAULT_S,
    SENSOR,
    WANT_UM,
    FaultRun,
    JumpClock,
    base_config,
    check,
    modbus_tcp_source,
    record,
)

COMMS = ("comms_lost", "stale")


def _tcp(tmp_path: Path, policy: str, mode: str, **kw) -> None:  # noqa: ANN003
    """A Modbus TCP module whose wire fault `mode` is switched on at FAULT_S, off at CLEAR_S."""
    tx = Pt100Transmitter([SENSOR], [24.0])
    faults = WireFaults()
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0, faults=faults) as server:
        run = FaultRun(tmp_path, base_config(modbus_tcp_source(server.port), policy))
        run.at(FAULT_S, "fault", lambda: faults.set(mode, **kw))
        run.at(CLEAR_S, "clear", lambda: faults.set("none"))
        return run.run(reasons=COMMS)


def test_slow_answers(tmp_path: Path) -> None:
    m = _tcp(tmp_path, "hold", "slow", slow_s=0.3)
    record("slow_answers", m, tmp_path)
    check(m, recovered=True)


def test_exception_replies(tmp_path: Path) -> None:
    m = _tcp(tmp_path, "hold", "exception")
    record("exception_replies", m, tmp_path)
    check(m, recovered=True)


def test_server_killed(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    server = ModbusServerThread(Pt100ModbusDevice(tx), port=0).start()
    try:
        run = FaultRun(tmp_path, base_config(modbus_tcp_source(server.port), "ramp_to_zero"))
        run.at(FAULT_S, "fault", server.stop)
        m = run.run(reasons=COMMS)
    finally:
        server.stop()
    record("server_killed", m, tmp_path)
    check(m, recovered=False)
    assert run.trace.out[-1] == 0.0


def test_server_restarted(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    dev = Pt100ModbusDevice(tx)
    servers = [ModbusServerThread(dev, port=0).start()]
    port = servers[0].port

    def restart() -> None:
        servers.append(ModbusServerThread(dev, port=port).start())

    try:
        run = FaultRun(tmp_path, base_config(modbus_tcp_source(port), "ramp_to_zero"))
        run.at(FAULT_S, "fault", servers[0].stop)
        run.at(CLEAR_S, "restart", restart)
        m = run.run(reasons=COMMS)
    finally:
        for s in servers:
            s.stop()
    record("server_restarted", m, tmp_path)
    check(m, recovered=True)
    assert abs(run.trace.out[-1] - WANT_UM) <= 0.5  # back at the model's correction


@pytest.mark.parametrize("mode", ["garbage", "crc_error"])
def test_rtu_wire_faults(tmp_path: Path, mode: str) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    faults = WireFaults()
    a, b = tmp_path / "ttyDev", tmp_path / "ttyCompd"
    with PtyPair(a, b), ModbusServerThread(Pt100ModbusDevice(tx), serial_port=str(a), faults=faults):
        src = modbus_tcp_source(1, transport="rtu", serial_port=str(b), baudrate=115200, poll_period_s=0.03)
        run = FaultRun(tmp_path, base_config(src, "hold"))
        run.at(FAULT_S, "fault", lambda: faults.set(mode))
        run.at(CLEAR_S, "clear", lambda: faults.set("none"))
        m = run.run(reasons=COMMS)
    row = "rtu_garbage" if mode == "garbage" else "rtu_crc_error"
    record(row, m, tmp_path)
    check(m, recovered=True)


def test_pty_closed(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    a, b = tmp_path / "ttyDev", tmp_path / "ttyCompd"
    pty = PtyPair(a, b).start()
    try:
        with DconModule(tx, str(a), baudrate=115200):
            src = {
                "kind": "dcon",
                "name": "dcon",
                "serial_port": str(b),
                "baudrate": 115200,
                "channels": [SENSOR],
                "poll_period_s": 0.03,
                "timeout_s": 0.1,
                "stale_after_s": 0.3,
            }
            run = FaultRun(tmp_path, base_config(src, "disable"))
            run.at(FAULT_S, "fault", pty.stop)
            m = run.run(reasons=COMMS)
    finally:
        pty.stop()
    record("pty_closed", m, tmp_path)
    check(m, recovered=False)


def test_can_silence(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    bus = f"faults-{time.monotonic_ns()}"
    with CanPt100(tx, [CanChannel(SENSOR, 0x181)], interface="virtual", channel=bus, period_s=0.02) as dev:
        src = {
            "kind": "can",
            "name": "can",
            "interface": "virtual",
            "channel": bus,
            "timeout_s": 0.2,
            "signals": [{"name": SENSOR, "id": 0x181}],
        }
        run = FaultRun(tmp_path, base_config(src, "hold"))
        run.at(FAULT_S, "fault", lambda: dev.set_fault("no_answer"))
        run.at(CLEAR_S, "clear", lambda: dev.set_fault("none"))
        m = run.run(reasons=COMMS)
    record("can_silence", m, tmp_path)
    check(m, recovered=True)


def test_clock_jump(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    clock = JumpClock()
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        # loop time runs 60 s ahead after the jump: the duration counts it
        run = FaultRun(
            tmp_path, base_config(modbus_tcp_source(server.port), "hold"), duration_s=60.0 + 10.0, clock=clock
        )
        run.at(FAULT_S, "fault", lambda: setattr(clock, "offset_s", 60.0))
        # right after the jump the last sample is 60 s old on the new clock: the axis holds
        # until the next poll, then recovers; the row ends when it has
        run.expect_recovery = True
        m = run.run(sensor="clock", kind="jump")
    record("clock_jump", m, tmp_path)
    check(m, fault=False, recovered=True)
    assert m.event is not None and m.logged


def test_disk_full(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        cfg = base_config(modbus_tcp_source(server.port), "hold")
        cfg["log"]["path"] = "/dev/full"  # every write fails with ENOSPC
        run = FaultRun(tmp_path, cfg)
        m = run.run()
    errors = [r for r in run.records if getattr(r, "event", None) == "log_error"]
    # one clear line, not one per row: one per writer, and a service process the supervisor restarted
    # (it stalled on a loaded machine: `service_restarted`) opens the log again with a writer of its own
    restarts = [r for r in run.records if getattr(r, "event", None) == "service_restarted"]
    assert len(errors) == 1 + len(restarts), [(r.ts, r.event, r.getMessage()) for r in errors + restarts]
    assert all(e.levelno == logging.ERROR for e in errors)
    m.event = f"log_error: {errors[0].reason}"
    m.logged = True
    m.time_to_safe_s = None
    record("disk_full", m, tmp_path)
    check(m, fault=False, recovered=True)
    assert m.samples_lost > 0  # the rows that could not be written are counted
    assert abs(run.trace.out[-1] - WANT_UM) <= 0.5  # compensation went on
    assert run.summary["log_error"] and "No space left" in run.summary["log_error"]


def test_modbus_malformed_reply(tmp_path: Path) -> None:
    """A raw-socket peer (not pymodbus): the sensor's request (register 0) is answered with
    ten extra registers reaching into the status request's (register 10), while that one
    gets exception replies, then with the wrong function code; cleared at CLEAR_S."""
    from tests.sources.rawmodbus import RawModbusServer

    mid = (FAULT_S + CLEAR_S) / 2
    with RawModbusServer({0: 240, 10: 0}) as peer:
        src = modbus_tcp_source(peer.port, channels=[{"name": SENSOR, "address": 0, "status_address": 10}])
        run = FaultRun(tmp_path, base_config(src, "hold"))

        def fault() -> None:
            peer.set("extra", address=0, extra=12)  # registers 1..12: 0x1234… in the status slot
            peer.set("exception", address=10)

        def refunction() -> None:
            peer.set("none")
            peer.set("wrong_function", address=0)

        run.at(FAULT_S, "fault", fault)
        run.at(mid, "wrong_function", refunction)
        run.at(CLEAR_S, "clear", lambda: peer.set("none"))
        m = run.run(reasons=("comms_lost",))
        source = run.app.sources[0]
        m.extra["malformed_replies"] = source.get_status()["malformed_replies"]
    record("modbus_malformed_reply", m, tmp_path)
    check(m, recovered=True)
    assert source.get_status()["malformed_replies"] > 0
