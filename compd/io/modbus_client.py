"""The one Modbus client (TCP or RTU, pymodbus): register and bit reads, register writes, every reply shape-checked.

`ModbusClient` is the only place in compd that builds a pymodbus client. Each call
sends one request, waits for its reply (up to `timeout_s`) and returns either the
data or a `ModbusFault`, never raises:

  LinkFault       no reply, a garbled or truncated frame, a lost connection. Afterwards a
                  TCP client is closed (its stream may still hold a late reply: the next
                  request reconnects); an RTU client has its input buffer flushed.
  NoConnection    (a LinkFault) the request was not sent: the connection could not be
                  opened — the device is unreachable, a worker backs off.
  ExceptionReply  the device answered with a Modbus exception (`code`).
  BadReply        a reply of the wrong shape (`reason`): see below. On RTU the input
                  buffer is flushed (the frame may not have ended where pymodbus thought).

Shape checks. pymodbus 3.16's sync client matches a reply to its request by
transaction id and unit id (a mismatch is skipped, and the request times out), and
rejects a byte count longer than the frame; but it hands back whatever function code
and register count the peer sent: a 0x04 reply to a 0x03 request, six registers for
four asked, or a byte count shorter than the frame all arrive as a normal response.
So every reply is checked here before a register of it is used: its unit, its
function code, its register count (a write's echoed address and quantity) and, on
TCP, the frame itself (MBAP length and byte count, through pymodbus's `trace_packet`
hook), since pymodbus reads as many registers as the byte count says and ignores the
rest of the frame.

A client is used from one thread at a time (its I/O worker's): every call blocks.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from compd.io.worker import LinkDown

HOLDING = 0x03
INPUT = 0x04
WRITE_MULTIPLE = 0x10
READ_WRITE = 0x17  # function 23: write, then read, in one request

COILS = 0x01
DISCRETE = 0x02
TableT = Literal["holding", "input"]
BitTableT = Literal["coils", "discrete"]


@dataclass(frozen=True)
class ModbusFault:
    """Why a request gave no data; `detail` is the message for `last_error`."""

    detail: str


@dataclass(frozen=True)
class LinkFault(ModbusFault):
    """No usable reply at all: timeout, garbled or truncated frame, lost connection."""


@dataclass(frozen=True)
class NoConnection(LinkFault):
    """The request was not sent: no connection could be made (the device is unreachable)."""


@dataclass(frozen=True)
class ExceptionReply(ModbusFault):
    """The device answered with a Modbus exception."""

    code: int = 0


@dataclass(frozen=True)
class BadReply(ModbusFault):
    """A reply that does not answer the request asked (`reason` says how)."""

    reason: str = ""


def shape_error(rr: Any, function_code: int, count: int, device_id: int | None = None) -> str | None:
    """Why `rr` is not a reply to a read of `count` registers with `function_code` from
    `device_id` (None: it is). Call it on non-exception replies."""
    problem = _unit_and_function(rr, function_code, device_id)
    if problem is not None:
        return problem
    regs = getattr(rr, "registers", None)
    if regs is None or len(regs) != count:
        return f"reply has {0 if regs is None else len(regs)} registers, asked {count}"
    return None


def write_shape_error(rr: Any, address: int, count: int, device_id: int | None = None) -> str | None:
    """Why `rr` is not the acknowledgement of a write of `count` registers at `address`
    (function 16 echoes both); None: it is."""
    problem = _unit_and_function(rr, WRITE_MULTIPLE, device_id)
    if problem is not None:
        return problem
    echo = (getattr(rr, "address", None), getattr(rr, "count", None))
    if echo != (address, count):
        return f"reply acknowledges registers {echo[0]}+{echo[1]}, wrote {address}+{count}"
    return None


def _unit_and_function(rr: Any, function_code: int, device_id: int | None) -> str | None:
    dev = getattr(rr, "dev_id", None)
    if device_id is not None and isinstance(dev, int) and dev != device_id:
        return f"reply from unit {dev}, asked unit {device_id}"
    fc = getattr(rr, "function_code", None)
    if fc != function_code:
        return f"reply function 0x{fc:02X}, asked 0x{function_code:02X}" if isinstance(fc, int) else "no function code"
    return None


class FrameTap:
    """pymodbus's `trace_packet` hook: keeps the bytes last received, so the reply's MBAP
    length and byte count can be checked. Modbus TCP only."""

    def __init__(self) -> None:
        self.last = b""

    def __call__(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self.last = data
        return data

    def tcp_error(self, transaction_id: int, count: int | None, *, bits: bool = False) -> str | None:
        """Why the received frame with `transaction_id` is not a reply carrying exactly
        `count` registers (`bits`: coils or discrete inputs, 8 to a byte), or (count None) a
        write's acknowledgement of 4 bytes; None: it is, or it is not in the buffer."""
        n_bytes = 0 if count is None else ((count + 7) // 8 if bits else 2 * count)
        buf = self.last
        while len(buf) >= 8:
            length = int.from_bytes(buf[4:6], "big")
            if int.from_bytes(buf[0:2], "big") == transaction_id:
                if buf[7] & 0x80:
                    return None  # an exception reply: the caller has it already
                if count is None:
                    return None if length == 6 else f"frame length {length} for a write acknowledgement"
                if len(buf) < 9 or length != 3 + n_bytes or buf[8] != n_bytes:
                    byte_count = buf[8] if len(buf) >= 9 else "none"
                    return (
                        f"frame length {length}, byte count {byte_count} for {count} {'bits' if bits else 'registers'}"
                    )
                return None
            buf = buf[6 + length :]
        return None


class ModbusClient:
    """One Modbus connection, TCP (`host`, `port`) or RTU (`serial_port`): see the module."""

    def __init__(
        self,
        *,
        transport: Literal["tcp", "rtu"] = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str | None = None,
        baudrate: int = 9600,
        parity: str = "N",
        stopbits: int = 1,
        device_id: int = 1,
        timeout_s: float = 0.25,
    ) -> None:
        if transport == "rtu" and not serial_port:
            raise ValueError("an RTU client needs serial_port")
        self.transport = transport
        self.host, self.port, self.serial_port = host, port, serial_port
        self.baudrate, self.parity, self.stopbits = baudrate, parity, stopbits
        self.device_id = device_id
        self.timeout_s = timeout_s
        self.last_error: str | None = None
        self.connects = 0  # connections opened
        self._tap = FrameTap()
        self._client: Any = None  # the pymodbus client, built on the first connect

    @classmethod
    def tcp(cls, host: str, port: int, *, device_id: int = 1, timeout_s: float = 0.25) -> ModbusClient:
        """A Modbus TCP client."""
        return cls(transport="tcp", host=host, port=port, device_id=device_id, timeout_s=timeout_s)

    def where(self) -> str:
        """host:port, or the serial device."""
        return f"{self.host}:{self.port}" if self.transport == "tcp" else str(self.serial_port)

    # ------------------------------------------------------------- connection
    def _build(self) -> Any:
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # faults are reported, not logged twice
        tcp_client, serial_client = _client_classes()
        if self.transport == "tcp":
            return tcp_client(self.host, port=self.port, timeout=self.timeout_s, retries=0, trace_packet=self._tap)
        return serial_client(
            self.serial_port or "",
            baudrate=self.baudrate,
            parity=self.parity,
            stopbits=self.stopbits,
            timeout=self.timeout_s,
            retries=0,
        )

    @property
    def connected(self) -> bool:
        return self._client is not None and bool(self._client.connected)

    def connect(self) -> bool:
        """Open the connection (a no-op when open); False, with `last_error`, when it fails."""
        if self._client is None:
            self._client = self._build()
        if self._client.connected:
            return True
        self._client.connect_error = None
        try:
            ok = bool(self._client.connect())
        except Exception as e:  # pyserial/OS errors while opening
            self.last_error = f"connect: {e}"
            return False
        if ok:
            self.connects += 1
        elif self.transport == "tcp":
            why = self._client.connect_error or "no connection"
            self.last_error = f"connect to {self.where()}: {why}"
        else:  # pyserial's text names the port
            self.last_error = f"connect: {self._client.connect_error or f'cannot open {self.where()}'}"
        return ok

    def close(self) -> None:
        if self._client is not None:
            self._client.close()

    def release(self) -> None:
        """For good (the link's worker stops): the connection closed."""
        self.close()

    def _after_link_fault(self) -> None:
        """TCP: close (the stream may hold a late reply); RTU: discard the input buffer."""
        c = self._client
        if c is None:
            return
        if self.transport == "tcp":
            c.close()
            return
        sock = getattr(c, "socket", None)
        if sock is None:
            return
        try:
            time.sleep(min(self.timeout_s, 0.05))  # let the rest of a late frame arrive
            sock.reset_input_buffer()
        except Exception:
            c.close()

    def _call(self, request: Any) -> Any:
        """Run `request(pymodbus_client)`; the reply, or a LinkFault."""
        if not self.connected and not self.connect():
            return NoConnection(self.last_error or "not connected")
        try:
            return request(self._client)
        except Exception as e:  # ModbusException, OSError, pyserial's, a decoder's: no usable reply
            self._after_link_fault()
            return LinkFault(f"{type(e).__name__}: {e}")

    def _checked(self, rr: Any, function_code: int, count: int, what: str) -> list[int] | ModbusFault:
        """The registers of a read reply `rr`, or why not."""
        if isinstance(rr, ModbusFault):
            return rr
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            return ExceptionReply(f"exception reply, code {code}", code if isinstance(code, int) else 0)
        problem = shape_error(rr, function_code, count, self.device_id)
        if problem is None and self.transport == "tcp":
            problem = self._tap.tcp_error(getattr(rr, "transaction_id", 0), count)
        if problem is not None:
            return self._bad(f"malformed reply to {what}: {problem}", problem)
        return list(rr.registers)

    def _bad(self, detail: str, reason: str) -> BadReply:
        if self.transport == "rtu":
            self._after_link_fault()
        return BadReply(detail, reason)

    # ------------------------------------------------------------- requests
    def read_registers(self, address: int, count: int, *, table: TableT = "holding") -> list[int] | ModbusFault:
        """Read `count` holding (function 3) or input (function 4) registers from `address`."""
        if table == "holding":
            fc = HOLDING
            rr = self._call(lambda c: c.read_holding_registers(address, count=count, device_id=self.device_id))
        else:
            fc = INPUT
            rr = self._call(lambda c: c.read_input_registers(address, count=count, device_id=self.device_id))
        return self._checked(rr, fc, count, f"registers {address}+{count}")

    def read_bits(self, address: int, count: int, *, table: BitTableT = "coils") -> list[int] | ModbusFault:
        """Read `count` coils (function 1) or discrete inputs (function 2) from `address`, as 0 or 1."""
        if table == "coils":
            fc = COILS
            rr = self._call(lambda c: c.read_coils(address, count=count, device_id=self.device_id))
        else:
            fc = DISCRETE
            rr = self._call(lambda c: c.read_discrete_inputs(address, count=count, device_id=self.device_id))
        if isinstance(rr, ModbusFault):
            return rr
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            return ExceptionReply(f"exception reply, code {code}", code if isinstance(code, int) else 0)
        problem = _unit_and_function(rr, fc, self.device_id)
        bits = getattr(rr, "bits", None)
        if problem is None and (bits is None or len(bits) < count):
            problem = f"reply has {0 if bits is None else len(bits)} bits, asked {count}"
        if problem is None and self.transport == "tcp":
            problem = self._tap.tcp_error(getattr(rr, "transaction_id", 0), count, bits=True)
        if problem is not None:
            return self._bad(f"malformed reply to {table} {address}+{count}: {problem}", problem)
        assert bits is not None  # no problem: the reply had its bits
        return [1 if b else 0 for b in bits[:count]]

    def write_registers(self, address: int, values: Sequence[int]) -> None | ModbusFault:
        """Write holding registers from `address` (function 16); None once acknowledged."""
        words = [v & 0xFFFF for v in values]
        rr = self._call(lambda c: c.write_registers(address, words, device_id=self.device_id))
        if isinstance(rr, ModbusFault):
            return rr
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            return ExceptionReply(f"write exception reply, code {code}", code if isinstance(code, int) else 0)
        problem = write_shape_error(rr, address, len(words), self.device_id)
        if problem is None and self.transport == "tcp":
            problem = self._tap.tcp_error(getattr(rr, "transaction_id", 0), None)
        if problem is not None:
            return self._bad(f"malformed reply to the write of registers {address}+{len(words)}: {problem}", problem)
        return None

    def read_write_registers(
        self, read_address: int, read_count: int, write_address: int, values: Sequence[int]
    ) -> list[int] | ModbusFault:
        """Write `values` at `write_address`, then read `read_count` registers from
        `read_address`, in one request (function 23)."""
        words = [v & 0xFFFF for v in values]
        rr = self._call(
            lambda c: c.readwrite_registers(
                read_address=read_address,
                read_count=read_count,
                write_address=write_address,
                values=words,
                device_id=self.device_id,
            )
        )
        return self._checked(rr, READ_WRITE, read_count, f"read/write of registers {read_address}+{read_count}")


_CLASSES: tuple[type, type] | None = None


def _client_classes() -> tuple[type, type]:
    """pymodbus's TCP and serial clients, whose failed `connect` keeps the OS's reason in
    `connect_error` (pymodbus only logs it): "[Errno 111] Connection refused", "could not
    open port /dev/ttyUSB9: [Errno 2] No such file or directory: '/dev/ttyUSB9'". The
    connects are pymodbus 3.16's own, with the exception kept."""
    global _CLASSES
    if _CLASSES is not None:
        return _CLASSES
    import socket

    import serial
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

    class KeepsReason:
        """pymodbus's `connect`, with the exception kept: `_open` makes the socket."""

        socket: Any
        connect_error: str | None = None

        def _open(self) -> Any:
            raise NotImplementedError

        def connect(self) -> bool:
            if self.socket:
                return True
            try:
                self.socket = self._open()
            except Exception as e:  # OSError, and pyserial's termios and other errors besides its own
                self.connect_error = str(e) or type(e).__name__
                self.close()  # type: ignore[attr-defined]
            return self.socket is not None

    class TcpClient(KeepsReason, ModbusTcpClient):
        def _open(self) -> Any:
            p = self.comm_params
            return socket.create_connection(
                (p.host, p.port), timeout=p.timeout_connect, source_address=p.source_address
            )

    class SerialClient(KeepsReason, ModbusSerialClient):
        def _open(self) -> Any:
            p = self.comm_params
            port = serial.serial_for_url(
                p.host,
                timeout=p.timeout_connect,
                write_timeout=p.timeout_connect,
                bytesize=p.bytesize,
                stopbits=p.stopbits,
                baudrate=p.baudrate,
                parity=p.parity,
                exclusive=True,
            )
            port.inter_byte_timeout = self.inter_byte_timeout
            return port

    _CLASSES = (TcpClient, SerialClient)
    return _CLASSES


class Connectable(Protocol):
    """What OverModbus connects and closes: a `ModbusClient`, or a device that behaves as one
    (compd.io.modbus_link.RegisterDevice)."""

    last_error: str | None

    def connect(self) -> bool: ...
    def close(self) -> None: ...


class OverModbus:
    """The connect and disconnect of a device work (compd.io.worker.DeviceWork) whose device
    is reached through `self.client`; mixed in before the work's base class (which names the
    client's own type)."""

    client: Connectable

    def connect(self) -> None:
        if not self.client.connect():
            raise LinkDown(self.client.last_error or "connect failed")

    def disconnect(self) -> None:
        self.client.close()
