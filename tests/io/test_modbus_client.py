"""The one Modbus client: registers or a typed fault, never an exception. Shape checks against a
raw-socket peer (not pymodbus) that answers with the wrong shape, over TCP and over RTU on a
socat pty pair; the same client against a real pymodbus server for reads, writes and FC 23."""

from __future__ import annotations

import socket

import pytest

from compd.io.modbus_client import (
    BadReply,
    ExceptionReply,
    LinkFault,
    ModbusClient,
    NoConnection,
)
from tests.sources.rawmodbus import RawModbusServer, RawRtuPeer

TABLE = {0: 253, 1: 249, 2: 612, 3: 177}

# misbehaviours a real stack would not show, that pymodbus hands back as a normal reply
SHAPES = [
    ("extra", {}, "reply has 6 registers, asked 4"),
    ("fewer", {}, "reply has 3 registers, asked 4"),
    ("wrong_function", {}, "reply function 0x04, asked 0x03"),
    ("wrong_function", {"function": 0x10}, "reply function 0x10, asked 0x03"),
    ("bad_byte_count", {"byte_count_delta": -2}, "reply has 3 registers, asked 4"),  # pymodbus trusts the count
    ("trailing", {}, "frame length 15, byte count 8 for 4 registers"),
]


def _client(port: int, **kw) -> ModbusClient:  # noqa: ANN003
    return ModbusClient(transport="tcp", host="127.0.0.1", port=port, timeout_s=kw.pop("timeout_s", 0.2), **kw)


def test_tcp_read_returns_the_registers() -> None:
    with RawModbusServer(TABLE) as srv:
        c = _client(srv.port)
        try:
            assert c.read_registers(0, 4) == [253, 249, 612, 177]
            assert c.read_registers(1, 2, table="input") == [249, 612]
            assert c.connects == 1 and c.connected
        finally:
            c.close()
    assert not c.connected


@pytest.mark.parametrize(("mode", "opts", "reason"), SHAPES, ids=[f"{m}{o}" for m, o, _ in SHAPES])
def test_tcp_reply_of_the_wrong_shape_is_a_bad_reply(mode: str, opts: dict, reason: str) -> None:
    with RawModbusServer(TABLE) as srv:
        c = _client(srv.port)
        try:
            srv.set(mode, **opts)
            r = c.read_registers(0, 4)
            assert isinstance(r, BadReply), r
            assert reason in r.reason
            assert r.detail == f"malformed reply to registers 0+4: {r.reason}"
            assert c.connected  # the stream is in step: no reconnect needed
            srv.set("none")
            assert c.read_registers(0, 4) == [253, 249, 612, 177]
            assert c.connects == 1
        finally:
            c.close()


def test_tcp_exception_reply_is_typed_with_its_code() -> None:
    with RawModbusServer(TABLE) as srv:
        c = _client(srv.port)
        try:
            srv.set("exception", exception_code=2)
            r = c.read_registers(0, 4)
            assert isinstance(r, ExceptionReply) and r.code == 2
            assert not isinstance(r, LinkFault)
        finally:
            c.close()


@pytest.mark.parametrize("mode", ["silence", "wrong_tid", "wrong_unit", "truncated", "bad_byte_count"])
def test_tcp_no_usable_reply_is_a_link_fault_and_the_next_request_reconnects(mode: str) -> None:
    """pymodbus refuses these itself (a timeout, or an exception): the client closes the
    stream, which may still hold the late reply, and opens a new one for the next request."""
    with RawModbusServer(TABLE) as srv:
        c = _client(srv.port, timeout_s=0.1)
        try:
            assert c.read_registers(0, 4) == [253, 249, 612, 177]
            srv.set(mode)
            r = c.read_registers(0, 4)
            assert isinstance(r, LinkFault) and not isinstance(r, NoConnection), r
            assert not c.connected
            srv.set("none")
            assert c.read_registers(0, 4) == [253, 249, 612, 177]
            assert c.connects == 2
        finally:
            c.close()


def test_a_refused_connection_is_no_connection() -> None:
    with socket.socket() as s:  # a free port, closed again: connections are refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    c = _client(port)
    try:
        assert c.connect() is False
        assert c.last_error is not None and c.last_error.startswith("connect")
        r = c.read_registers(0, 1)
        assert isinstance(r, NoConnection) and isinstance(r, LinkFault)
        assert c.connects == 0
    finally:
        c.close()


def test_tcp_write_is_acknowledged_and_a_wrong_acknowledgement_refused() -> None:
    with RawModbusServer(dict(TABLE)) as srv:
        c = _client(srv.port)
        try:
            assert c.write_registers(10, [1, 0x12345]) is None  # values are 16-bit words
            assert srv.registers[10] == 1 and srv.registers[11] == 0x2345
            srv.set("wrong_echo")
            r = c.write_registers(10, [5, 6])
            assert isinstance(r, BadReply) and "acknowledges registers 10+4, wrote 10+2" in r.reason
            srv.set("wrong_function")
            r = c.write_registers(10, [5, 6])
            assert isinstance(r, BadReply) and "reply function 0x06, asked 0x10" in r.reason
            srv.set("exception", exception_code=3)
            r = c.write_registers(10, [5, 6])
            assert isinstance(r, ExceptionReply) and r.code == 3
            srv.set("silence")
            assert isinstance(c.write_registers(10, [5, 6]), LinkFault)
        finally:
            c.close()


def test_tcp_read_write_in_one_request_is_shape_checked() -> None:
    with RawModbusServer(dict(TABLE)) as srv:
        c = _client(srv.port)
        try:
            assert c.read_write_registers(0, 3, 4, [7, 8]) == [253, 249, 612]
            assert srv.registers[4] == 7 and srv.registers[5] == 8
            srv.set("fewer")
            r = c.read_write_registers(0, 3, 4, [9, 9])
            assert isinstance(r, BadReply) and "reply has 2 registers, asked 3" in r.reason
            srv.set("wrong_function")
            r = c.read_write_registers(0, 3, 4, [9, 9])
            assert isinstance(r, BadReply) and "asked 0x17" in r.reason
        finally:
            c.close()


def _answered(c: ModbusClient) -> list[int] | object:
    """The table, read until the peer answers in step (a reply late on a busy machine is a
    LinkFault and the line is flushed: ask again)."""
    r: object = None
    for _ in range(20):
        r = c.read_registers(0, 4)
        if not isinstance(r, LinkFault):
            break
    return r


@pytest.mark.parametrize(
    ("mode", "opts", "reason"),
    [
        ("extra", {"extra": 10}, "reply has 14 registers, asked 4"),
        ("wrong_function", {}, "reply function 0x04, asked 0x03"),
        ("fewer", {}, "reply has 3 registers, asked 4"),
    ],
    ids=["extra", "wrong_function", "fewer"],
)
def test_rtu_reply_of_the_wrong_shape_is_a_bad_reply_and_the_line_recovers(
    tmp_path, mode: str, opts: dict, reason: str
) -> None:  # noqa: ANN001
    """The same over Modbus RTU: a raw peer on a socat pty answers with the wrong shape; the
    client flushes the line and the next request is answered in step."""
    from hil_sim.devices.ptypair import PtyPair

    a, b = tmp_path / "ttyPeer", tmp_path / "ttyCompd"
    with PtyPair(a, b), RawRtuPeer(TABLE, str(a)) as peer:
        c = ModbusClient(transport="rtu", serial_port=str(b), baudrate=115200, timeout_s=1.0)
        try:
            assert _answered(c) == [253, 249, 612, 177]
            peer.set(mode, **opts)
            r = c.read_registers(0, 4)
            assert isinstance(r, BadReply), r
            assert reason in r.reason
            peer.set("none")
            assert _answered(c) == [253, 249, 612, 177]
        finally:
            c.close()


def test_rtu_silence_is_a_link_fault_and_the_port_stays_open(tmp_path) -> None:  # noqa: ANN001
    from hil_sim.devices.ptypair import PtyPair

    a, b = tmp_path / "ttyPeer", tmp_path / "ttyCompd"
    with PtyPair(a, b), RawRtuPeer(TABLE, str(a)) as peer:
        c = ModbusClient(transport="rtu", serial_port=str(b), baudrate=115200, timeout_s=0.1)
        try:
            peer.set("silence")
            r = c.read_registers(0, 4)
            assert isinstance(r, LinkFault) and not isinstance(r, NoConnection)
            assert c.connected  # RTU: the input is flushed, the port stays open
            peer.set("none")
            assert _answered(c) == [253, 249, 612, 177]
            assert c.connects == 1
        finally:
            c.close()


def test_rtu_missing_port_is_no_connection(tmp_path) -> None:  # noqa: ANN001
    c = ModbusClient(transport="rtu", serial_port=str(tmp_path / "no-such-tty"), timeout_s=0.1)
    r = c.read_registers(0, 1)
    assert isinstance(r, NoConnection) and "no-such-tty" in r.detail
    c.close()


class _Registers:
    """A plain holding-register map for the pymodbus server."""

    register_count = 32

    def __init__(self) -> None:
        self.mem = [0] * self.register_count

    def read_registers(self, address: int, count: int) -> list[int] | None:
        return self.mem[address : address + count] if address + count <= self.register_count else None

    def write_registers(self, address: int, values: list[int]) -> bool:
        if address + len(values) > self.register_count:
            return False
        self.mem[address : address + len(values)] = values
        return True


def test_against_a_pymodbus_server_reads_writes_and_read_write_pass_the_checks() -> None:
    from hil_sim.devices.modbus_server import ModbusServerThread

    dev = _Registers()
    with ModbusServerThread(dev, port=0) as srv:
        c = _client(srv.port, timeout_s=1.0)
        try:
            assert c.write_registers(2, [11, 12, 13]) is None
            assert c.read_registers(0, 5) == [0, 0, 11, 12, 13]
            assert c.read_write_registers(2, 2, 20, [99]) == [11, 12]
            assert dev.mem[20] == 99
            r = c.read_registers(30, 4)  # beyond the map: the device refuses
            assert isinstance(r, ExceptionReply)
        finally:
            c.close()
