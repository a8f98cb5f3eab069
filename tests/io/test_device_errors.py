"""A device's error is logged with the OS's reason once per change, and its recovery once."""

from __future__ import annotations

import logging
import socket
import time
from typing import Any

import pytest

from compd.core.clock import WallClock
from compd.core.frame import Frame
from compd.io.worker import DeviceWork, IoWorker, LinkDown
from compd.sources.dcon import DconConfig, DconSource
from compd.sources.modbus import ModbusConfig, ModbusSource
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice

WAIT_S = 20.0  # generous: the machine may be busy
NAMES = ["T1", "T2"]


def _wait(predicate: Any, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.005)


def _records(caplog: pytest.LogCaptureFixture, event: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == event]


def _free_port() -> int:
    """A 127.0.0.1 port nothing listens on (bound, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start(source: Any) -> None:
    frame = Frame(source.signal_names())
    source.bind(frame)
    source.worker.start(clock=WallClock().now)


def test_a_serial_port_gone_after_start_up_logs_the_os_reason_once(tmp_path, caplog) -> None:
    port = tmp_path / "ttyUSB9"
    port.write_text("")  # there at start-up (the check passes) ...
    cfg = DconConfig.model_validate(
        {
            "kind": "dcon",
            "name": "adam",
            "serial_port": str(port),
            "address": 1,
            "channels": NAMES,
            "poll_period_s": 0.01,
        }
    )
    src = DconSource(cfg)
    src.reconnect_min_s, src.reconnect_max_s = 0.01, 0.02
    src.open(0.0)
    port.unlink()  # ... then unplugged
    caplog.set_level(logging.DEBUG, logger="compd.io")
    _start(src)
    try:
        _wait(lambda: src.worker.errors >= 5, "the worker did not retry")
    finally:
        src.close()
    errors = _records(caplog, "device_error")
    assert len(errors) == 1, [r.getMessage() for r in errors]
    msg = errors[0].getMessage()
    assert errors[0].levelno == logging.WARNING
    assert f"could not open port {port}" in msg and "No such file or directory" in msg
    assert msg.startswith("poll-adam: ")
    assert src.get_status()["last_error"] in msg  # status says the same


def test_a_modbus_rtu_source_on_a_missing_port_logs_the_os_reason_once(tmp_path, caplog) -> None:
    port = tmp_path / "ttyUSB9"
    cfg = ModbusConfig.model_validate(
        {
            "kind": "modbus",
            "name": "rtu",
            "transport": "rtu",
            "serial_port": str(port),
            "poll_period_s": 0.01,
            "reconnect_min_s": 0.01,
            "reconnect_max_s": 0.02,
            "channels": [{"name": n, "address": i} for i, n in enumerate(NAMES)],
        }
    )
    src = ModbusSource(cfg)
    caplog.set_level(logging.DEBUG, logger="compd.io")
    _start(src)
    try:
        _wait(lambda: src.worker.errors >= 5, "the worker did not retry")
    finally:
        src.close()
    errors = _records(caplog, "device_error")
    assert len(errors) == 1, [r.getMessage() for r in errors]
    assert f"could not open port {port}" in errors[0].getMessage()
    assert "No such file or directory" in errors[0].getMessage()


def test_modbus_tcp_to_a_closed_port_logs_connection_refused_once_then_its_recovery(caplog) -> None:
    port = _free_port()
    cfg = ModbusConfig.model_validate(
        {
            "kind": "modbus",
            "name": "pt100",
            "port": port,
            "timeout_s": 0.5,
            "poll_period_s": 0.01,
            "reconnect_min_s": 0.01,
            "reconnect_max_s": 0.02,
            "channels": [{"name": n, "address": i, "status_address": 10 + i} for i, n in enumerate(NAMES)],
        }
    )
    src = ModbusSource(cfg)
    src.worker.recovered_after_s = 0.0
    caplog.set_level(logging.DEBUG, logger="compd.io")
    srv = None
    _start(src)
    try:
        _wait(lambda: src.worker.errors >= 5, "the worker did not retry")
        errors = _records(caplog, "device_error")
        assert len(errors) == 1, [r.getMessage() for r in errors]  # not one per retry
        assert errors[0].getMessage() == f"poll-pt100: connect to 127.0.0.1:{port}: [Errno 111] Connection refused"
        assert not _records(caplog, "device_recovered")

        srv = ModbusServerThread(
            Pt100ModbusDevice(Pt100Transmitter(NAMES, [25.0, 26.0]), status_address=10), port=port
        ).start()
        _wait(lambda: _records(caplog, "device_recovered"), "no recovery logged")
        rounds = src.worker.rounds
        _wait(lambda: src.worker.rounds >= rounds + 3, "no polls after the recovery")
    finally:
        src.close()
        if srv is not None:
            srv.stop()
    recovered = _records(caplog, "device_recovered")
    assert len(recovered) == 1
    assert recovered[0].levelno == logging.INFO
    assert "recovered" in recovered[0].getMessage() and "Connection refused" in recovered[0].getMessage()
    assert len(_records(caplog, "device_error")) == 1


class Flapping(DeviceWork):
    """Fails every other round with one error, then with another, then goes well."""

    def __init__(self, script: list[str | None]) -> None:
        super().__init__()
        self.script = list(script)

    def round(self, request: Any) -> Any:
        step = self.script.pop(0) if self.script else None
        if step is not None:
            raise LinkDown(step)
        return None


def test_each_change_of_the_error_is_logged_and_a_flapping_one_only_once(caplog) -> None:
    work = Flapping(["timeout", None, "timeout", None, "timeout", "garbled", "garbled", None])
    w = IoWorker(
        work, name="dev", period_s=0.001, reconnect_min_s=0.001, reconnect_max_s=0.001, recovered_after_s=3600.0
    )  # no round is healthy for long enough here
    caplog.set_level(logging.DEBUG, logger="compd.io")
    w.start()
    try:
        _wait(lambda: not work.script and w.rounds >= 10, "the script did not run")
    finally:
        w.stop()
    assert [r.getMessage() for r in _records(caplog, "device_error")] == ["dev: timeout", "dev: garbled"]
    assert not _records(caplog, "device_recovered")
    assert w.reported_error == "garbled"


def test_a_sensor_gone_bad_names_its_sources_error_as_the_cause(caplog) -> None:
    from compd.cycle.publish import with_causes
    from compd.daemon.host import log_guard_event

    class Guard:
        events = [(1.0, "T_xi", "bad", "comms_lost"), (2.0, "T_amb", "bad", "out_of_range"), (3.0, "T_xi", "good", "")]

    class Src:
        name = "adam"

        def signal_names(self) -> list[str]:
            return ["T_xi", "T_amb"]

        def get_status(self) -> dict[str, Any]:
            return {"last_error": "open: could not open port /dev/ttyUSB9: [Errno 2] No such file or directory"}

    caplog.set_level(logging.DEBUG, logger="compd.service")
    events = with_causes(Guard.events, [Src()])
    for ev in events:
        log_guard_event(*ev)
    assert len(events) == 3
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == (
        "T_xi bad: comms_lost (source adam: open: could not open port /dev/ttyUSB9:"
        " [Errno 2] No such file or directory)"
    )
    assert caplog.records[0].cause.startswith("source adam: open: could not open port")
    assert lines[1] == "T_amb bad: out_of_range"  # not a device's fault: no cause
    assert lines[2] == "T_xi good: "


def test_a_sink_link_to_a_closed_port_logs_connection_refused_once(caplog) -> None:
    from compd.io.modbus_link import ModbusLink

    port = _free_port()
    link = ModbusLink("127.0.0.1", port, name="pmc", status_period_s=0.01, reconnect_min_s=0.01, reconnect_max_s=0.02)
    caplog.set_level(logging.DEBUG, logger="compd.io")
    link.start()
    try:
        link.submit(0, [1])
        _wait(lambda: link.errors >= 5, "the link did not retry")
    finally:
        link.stop()
    errors = _records(caplog, "device_error")
    assert [r.getMessage() for r in errors] == [
        f"modbus-link-pmc: connect to 127.0.0.1:{port}: [Errno 111] Connection refused"
    ]
    assert link.last_error == f"connect to 127.0.0.1:{port}: [Errno 111] Connection refused"
