"""The sinks' Modbus link against a raw-socket peer (not pymodbus): a read-back of the wrong
shape is a link error, never the device's status or applied value."""

from __future__ import annotations

import socket
import time

import pytest

from compd.io.modbus_link import ModbusLink
from tests.sources.rawmodbus import RawModbusServer

TABLE = [7, 0, 0, 0, 0xFFFB, 3, 0, 0]  # scan lo/hi, alarm, reset, applied 1 (−5), applied 2, alarm counts


def _until(pred, timeout_s: float = 10.0) -> bool:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.mark.parametrize(
    ("mode", "opts"),
    [("extra", {}), ("fewer", {}), ("wrong_function", {}), ("wrong_function", {"function": 0x06}), ("trailing", {})],
)
def test_malformed_read_back_is_a_link_error(mode: str, opts: dict) -> None:
    with RawModbusServer(TABLE) as srv:
        srv.set(mode, **opts)
        link = ModbusLink("127.0.0.1", srv.port, status=(0, 8), status_period_s=0.01, name="t")
        link.start()
        try:
            assert _until(lambda: link.bad_replies >= 3)
            assert link.status is None  # never taken as the device's status
            assert link.read_now(0, 8) is None
            st = link.get_status()
            assert st["bad_replies"] >= 3 and st["last_error"].startswith("malformed reply to registers 0+8")
            srv.set("none")
            assert _until(lambda: link.status is not None)
            assert link.status == TABLE
            assert link.read_now(4, 2) == [0xFFFB, 3]
        finally:
            link.stop()


def _refused_port() -> int:
    with socket.socket() as s:  # a free port, closed again: connections are refused
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_writes_wait_while_the_device_is_down_and_go_out_when_it_answers() -> None:
    port = _refused_port()
    link = ModbusLink("127.0.0.1", port, timeout_s=0.1, reconnect_min_s=0.02, reconnect_max_s=0.1, name="t")
    assert link.state == "closed"
    link.start()
    try:
        link.submit(10, [1, 2])
        assert _until(lambda: link.state == "down" and link.errors >= 2)
        assert link.pending() and link.flush(0.01) is False
        assert link.read_now(10, 2) is None  # down: no blocking read
        assert link.get_status()["last_error"].startswith("connect")
        link.submit(10, [3, 4])  # replaces the unsent write
        with RawModbusServer({}, port=port) as srv:
            assert link.flush(10.0) is True
            assert not link.pending() and link.state == "up"
            assert [srv.registers[10], srv.registers[11]] == [3, 4]
            assert link.writes == 1  # the first values were never sent
            assert link.read_now(10, 2) == [3, 4]
            link.submit(20, [0x1_0009])
            assert link.drain(10.0) is True and srv.registers[20] == 9
            assert link.write_hist.count == 2 and link.latency_hist.count == 2
            link.stop()
            assert link.state == "closed"
    finally:
        link.stop()


def test_a_write_lost_on_the_way_is_sent_again_unless_replaced() -> None:
    with RawModbusServer({}) as srv:
        link = ModbusLink("127.0.0.1", srv.port, timeout_s=0.1, reconnect_min_s=0.02, reconnect_max_s=0.05, name="t")
        link.start()
        try:
            srv.set("silence")
            link.submit(5, [1])
            assert _until(lambda: link.state == "down")
            assert link.pending() and 5 not in srv.registers
            srv.set("none")
            assert link.flush(10.0) is True
            assert srv.registers[5] == 1 and link.writes == 1
            srv.set("wrong_echo")  # acknowledged, but not this write: counted, not sent again
            link.submit(5, [2])
            assert link.flush(10.0) is True
            assert link.bad_replies == 1 and link.writes == 1
            assert "acknowledges registers 5+3, wrote 5+1" in link.last_error
        finally:
            link.stop()
