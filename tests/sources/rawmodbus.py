"""A raw-socket Modbus TCP peer for tests (no pymodbus): answers FC 3/4 from a register table,
writes it on FC 16 and FC 23 (write, then read), and misbehaves on request in ways a real stack
would not (wrong shapes, wrong ids, silence).

`RawModbusServer(registers)` listens on 127.0.0.1, port 0 (see `.port`; or the `port` given),
one thread per connection. `set(mode, address=None, **opts)` switches a misbehaviour on for every read, or
only for reads whose start register is `address` (several addresses can misbehave at once;
`set("none")` clears them all):

  none            correct replies
  extra           `extra` (2) more registers than asked; byte count and MBAP length agree
  fewer           `fewer` (1) fewer registers than asked; byte count and MBAP length agree
  wrong_function  the reply carries function `function` (default: 4 for 3, 3 for 4), same data
  wrong_tid       the reply's transaction id is off by one
  wrong_unit      the reply's unit id is off by one
  bad_byte_count  the PDU's byte count says `byte_count_delta` (+2) more than the data it carries
  trailing        byte count right for the registers asked, but `extra` (2) more registers follow
                  inside the frame (the MBAP length counts them)
  truncated       the MBAP length promises the whole reply; only half of it is sent
  exception       exception reply (function | 0x80, code `exception_code`)
  silence         no reply at all
  wrong_echo      FC 16: the acknowledgement names `extra` (2) more registers than written

FC 16 (write) honours none, wrong_function (default 6), wrong_tid, wrong_unit, exception,
silence and wrong_echo; FC 23 is answered like a read of its read range (after the write).

Each request is counted in `requests` (by start address in `requests_at`).
"""

from __future__ import annotations

import contextlib
import socket
import socketserver
import struct
import threading
from typing import Any

MODES = (
    "none",
    "extra",
    "fewer",
    "wrong_function",
    "wrong_tid",
    "wrong_unit",
    "bad_byte_count",
    "trailing",
    "truncated",
    "exception",
    "silence",
    "wrong_echo",
)


def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


class _Handler(socketserver.BaseRequestHandler):
    server: _TcpServer

    def handle(self) -> None:
        owner = self.server.owner
        sock: socket.socket = self.request
        owner._track(sock, True)
        try:
            while True:
                try:
                    head = _recv_exact(sock, 7)
                    if head is None:
                        return
                    tid, pid, length, unit = struct.unpack(">HHHB", head)
                    pdu = _recv_exact(sock, length - 1) if length > 1 else b""
                except OSError:
                    return
                if pdu is None or pid != 0:
                    return
                out = owner.answer(tid, unit, pdu)
                if out:
                    try:
                        sock.sendall(out)
                    except OSError:
                        return
        finally:
            owner._track(sock, False)


class _TcpServer(socketserver.ThreadingMixIn, socketserver.TCPServer):
    daemon_threads = False  # server_close joins the connection threads
    allow_reuse_address = True
    block_on_close = True

    def __init__(self, owner: RawModbusServer, port: int = 0) -> None:
        self.owner = owner
        super().__init__(("127.0.0.1", port), _Handler)


class RawModbusServer:
    """Serves `registers` (address → value; missing addresses read 0) to FC 3 and FC 4."""

    def __init__(self, registers: dict[int, int] | list[int], *, unit_id: int = 1, port: int = 0) -> None:
        self.registers = dict(enumerate(registers)) if isinstance(registers, list) else dict(registers)
        self.unit_id = unit_id
        self.faults: dict[int | None, tuple[str, dict[str, Any]]] = {}  # start (None: any) → mode
        self.requests = 0
        self.requests_at: dict[int, int] = {}
        self._lock = threading.Lock()
        self._conns: set[socket.socket] = set()
        self._closing = False
        self._server: _TcpServer | None = None
        self._thread: threading.Thread | None = None
        self.port = port

    # ------------------------------------------------------------------ behaviour
    def set(self, mode: str, address: int | None = None, **opts: Any) -> None:
        """Misbehave as `mode` (for reads starting at `address`, or all reads)."""
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r} (known: {', '.join(MODES)})")
        with self._lock:
            if mode == "none" and address is None:
                self.faults.clear()
            elif mode == "none":
                self.faults.pop(address, None)
            else:
                self.faults[address] = (mode, dict(opts))

    def answer(self, tid: int, unit: int, pdu: bytes) -> bytes:
        """The bytes sent back for one request (b"" for none)."""
        if len(pdu) < 5:
            return b""
        fc, start, count = struct.unpack(">BHH", pdu[:5])
        written: tuple[int, list[int]] | None = None
        if fc == 16 and len(pdu) >= 6 + 2 * count:
            written = (start, list(struct.unpack(f">{count}H", pdu[6 : 6 + 2 * count])))
        elif fc == 23 and len(pdu) >= 10:
            w_start, w_count = struct.unpack(">HH", pdu[5:9])
            written = (w_start, list(struct.unpack(f">{w_count}H", pdu[10 : 10 + 2 * w_count])))
        with self._lock:
            self.requests += 1
            self.requests_at[start] = self.requests_at.get(start, 0) + 1
            mode, opts = self.faults.get(start) or self.faults.get(None) or ("none", {})
            if written is not None and mode not in ("exception", "silence"):
                for k, v in enumerate(written[1]):
                    self.registers[written[0] + k] = v
            values = [self.registers.get(a, 0) & 0xFFFF for a in range(start, start + count)]
        if fc == 16:
            return self._answer_write(tid, unit, start, count, mode, opts)
        if fc not in (3, 4, 23):
            return self._frame(tid, unit, bytes([fc | 0x80, 1]))
        if mode == "silence":
            return b""
        if mode == "exception":
            return self._frame(tid, unit, bytes([fc | 0x80, opts.get("exception_code", 4)]))
        if mode in ("extra", "trailing"):
            values += [0x1234 + k for k in range(opts.get("extra", 2))]
        elif mode == "fewer":
            values = values[: max(0, count - opts.get("fewer", 1))]
        data = b"".join(struct.pack(">H", v) for v in values)
        byte_count = len(data) & 0xFF
        if mode == "bad_byte_count":
            byte_count = (byte_count + opts.get("byte_count_delta", 2)) & 0xFF
        elif mode == "trailing":
            byte_count = 2 * count
        reply_fc = fc
        if mode == "wrong_function":
            reply_fc = opts.get("function", 4 if fc == 3 else 3)
        if mode == "wrong_tid":
            tid = (tid + 1) & 0xFFFF
        if mode == "wrong_unit":
            unit = (unit + 1) & 0xFF
        out = self._frame(tid, unit, bytes([reply_fc, byte_count]) + data)
        if mode == "truncated":
            out = out[: 7 + (len(out) - 7) // 2]
        return out

    def _answer_write(self, tid: int, unit: int, start: int, count: int, mode: str, opts: dict[str, Any]) -> bytes:
        if mode == "silence":
            return b""
        if mode == "exception":
            return self._frame(tid, unit, bytes([0x90, opts.get("exception_code", 4)]))
        reply_fc = opts.get("function", 6) if mode == "wrong_function" else 16
        if mode == "wrong_echo":
            count += opts.get("extra", 2)
        if mode == "wrong_tid":
            tid = (tid + 1) & 0xFFFF
        if mode == "wrong_unit":
            unit = (unit + 1) & 0xFF
        return self._frame(tid, unit, struct.pack(">BHH", reply_fc, start, count))

    @staticmethod
    def _frame(tid: int, unit: int, pdu: bytes) -> bytes:
        return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu

    # ------------------------------------------------------------------ lifecycle
    def _track(self, sock: socket.socket, add: bool) -> None:
        with self._lock:
            (self._conns.add if add else self._conns.discard)(sock)
            closing = add and self._closing
        if closing:  # accepted just before stop(): do not block in recv
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def start(self) -> RawModbusServer:
        self._closing = False
        self._server = _TcpServer(self, self.port)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, name="raw-modbus-server", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        self._server.shutdown()
        with self._lock:
            self._closing = True
            conns = list(self._conns)
        for s in conns:  # wake the connection threads blocked in recv
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
        self._server.server_close()  # joins the connection threads (block_on_close)
        if self._thread is not None:
            self._thread.join(5)
        self._server = None
        self._thread = None

    def __enter__(self) -> RawModbusServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def crc16(data: bytes) -> bytes:
    """Modbus RTU CRC (poly 0xA001, init 0xFFFF), low byte first."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


class RawRtuPeer(RawModbusServer):
    """The same table and misbehaviours as Modbus RTU on a serial port (a socat pty end):
    reads 8-byte requests, answers unit + PDU + CRC (a truncated reply has no CRC)."""

    def __init__(
        self, registers: dict[int, int] | list[int], serial_port: str, *, unit_id: int = 1, baudrate: int = 115200
    ) -> None:
        super().__init__(registers, unit_id=unit_id)
        self.serial_port = serial_port
        self.baudrate = baudrate
        self._stop = threading.Event()
        self._ser: Any = None

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                buf += self._ser.read(8 - len(buf))
            except OSError:
                return
            if len(buf) < 8:
                continue
            req, buf = buf, b""
            if crc16(req[:6]) != req[6:]:
                self._ser.reset_input_buffer()  # out of step: start again on a clean line
                continue
            frame = self.answer(0, req[0], req[1:6])
            if not frame:
                continue
            mode = (self.faults.get(int.from_bytes(req[2:4], "big")) or self.faults.get(None) or ("none",))[0]
            out = frame[6:] if mode == "truncated" else frame[6:] + crc16(frame[6:])
            try:
                self._ser.write(out)
            except OSError:
                return

    def start(self) -> RawRtuPeer:
        import serial

        self._stop.clear()
        self._ser = serial.Serial(self.serial_port, self.baudrate, timeout=0.05)
        self._thread = threading.Thread(target=self._serve, name="raw-rtu-peer", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        if self._ser is not None:
            self._ser.close()
            self._ser = None
