"""PT100 modules over Modbus TCP or Modbus RTU (pymodbus), polled beside the cycle.

Each channel is a register (or a register pair) holding a scaled temperature:
value_c = raw · scale + offset_c, with the data type, byte order and word order of
the module. Raw codes that mean burn-out or out of range, and optional per-channel
status registers, become signal quality. Channels whose registers lie next to each
other are read in one request. A timeout, a garbled reply, a Modbus exception reply,
a reply of the wrong shape (another function code, more or fewer registers than asked,
a frame longer than its byte count: `compd.modbus_reply`) or a lost connection makes the
channels of that request COMMS_LOST; a reply fills only the registers its own request
asked for. The connection is re-established with exponential back-off and the daemon
never sees an exception.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.config import SourceConfig, Strict
from compd.frame import Quality
from compd.modbus_reply import HOLDING, INPUT, FrameTap, shape_error
from compd.sources.base import PolledSource, check_serial_port

log = logging.getLogger("compd.sources.modbus")

DataTypeT = Literal["int16", "uint16", "int32", "uint32", "float32"]
OrderT = Literal["big", "little"]
Code = Annotated[int, Field(ge=0, le=0xFFFFFFFF)]  # a raw register value (up to 32 bits)
_FORMATS = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}


def register_width(data_type: str) -> int:
    """Registers per value: 1 for 16-bit types, 2 for 32-bit."""
    return 2 if data_type.endswith("32") else 1


def decode_registers(
    words: list[int] | tuple[int, ...], data_type: str, byte_order: str = "big", word_order: str = "big"
) -> tuple[int, float]:
    """Registers → (raw code, number).

    The raw code is the registers as read, put in high-word-first order (what a
    manual's "0x7FFF" or "0x80000000" means); the number is the value they encode
    in `data_type` after undoing the module's byte and word order.
    """
    ws = list(words)
    if word_order == "little":
        ws = ws[::-1]
    raw = 0
    for w in ws:
        raw = (raw << 16) | (w & 0xFFFF)
    if byte_order == "little":
        ws = [((w & 0xFF) << 8) | ((w >> 8) & 0xFF) for w in ws]
    data = b"".join(w.to_bytes(2, "big") for w in ws)
    return raw, float(struct.unpack(">" + _FORMATS[data_type], data)[0])


def plan_reads(
    spans: list[tuple[int, int]], max_gap: int = 0, max_count: int = 125
) -> list[tuple[int, int]]:
    """Merge register spans (start, count) into as few requests as possible.

    Spans whose gap is at most `max_gap` registers are read together, as long as a
    request stays within `max_count` registers (Modbus allows 125 per read).
    """
    out: list[tuple[int, int]] = []
    for start, count in sorted(set(spans)):
        if out:
            s0, c0 = out[-1]
            end = max(s0 + c0, start + count)
            if start <= s0 + c0 + max_gap and end - s0 <= max_count:
                out[-1] = (s0, end - s0)
                continue
        out.append((start, count))
    return out


class ModbusChannel(Strict):
    """One temperature; unset options take the source's values."""

    name: str = Field(min_length=1, description="signal name")
    address: int = Field(ge=0, le=65535, description="first register (0-based, as on the wire)")
    data_type: DataTypeT | None = None
    scale: float | None = Field(None, ge=-1e6, le=1e6, description="°C per count; not 0")
    offset_c: float | None = Field(None, ge=-1000, le=1000)
    byte_order: OrderT | None = None
    word_order: OrderT | None = None
    burnout_codes: list[Code] | None = None
    out_of_range_codes: list[Code] | None = None
    status_address: int | None = Field(None, ge=0, le=65535, description="status register")


class ModbusConfig(SourceConfig):
    """A PT100 module on Modbus TCP (`host`, `port`) or RTU (`serial_port`)."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    serial_port: str | None = Field(None, description="RTU: the serial device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(9600, ge=300, le=4_000_000, description="RTU: bit/s")
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    device_id: int = Field(1, ge=0, le=247, description="unit id / slave address")
    function: Literal["holding", "input"] = Field("holding", description="register table")
    data_type: DataTypeT = "int16"
    scale: float = Field(0.1, ge=-1e6, le=1e6, description="°C per count (int16 × 0.1 °C: 0.1); not 0")
    offset_c: float = Field(0.0, ge=-1000, le=1000, description="added after scaling")
    byte_order: OrderT = "big"
    word_order: OrderT = "big"
    burnout_codes: list[Code] = Field(default_factory=lambda: [0x8000])
    out_of_range_codes: list[Code] = Field(default_factory=lambda: [0x7FFF, 0x8001])
    status_burnout_mask: int = Field(0x0001, ge=0, le=0xFFFF)
    status_out_of_range_mask: int = Field(0x0006, ge=0, le=0xFFFF)
    max_gap: int = Field(0, ge=0, le=100, description="unused registers a merged read may span")
    poll_period_s: float = Field(0.1, ge=0.001, le=60)
    timeout_s: float = Field(0.25, ge=0.001, le=30)
    stale_after_s: float | None = Field(
        None, gt=0, le=86400, description="older samples read as STALE; longer than poll_period_s"
    )
    reconnect_min_s: float = Field(0.1, ge=0.01, le=60)
    reconnect_max_s: float = Field(10.0, ge=0.01, le=3600, description="at least reconnect_min_s")
    channels: list[ModbusChannel] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> ModbusConfig:
        if self.transport == "rtu" and not self.serial_port:
            raise ValueError("transport rtu needs serial_port")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s is below reconnect_min_s")
        if self.stale_after_s is not None and not self.stale_after_s > self.poll_period_s:
            raise ValueError("stale_after_s must be longer than poll_period_s (else every sample is stale)")
        if 0 in {self.scale, *(c.scale for c in self.channels)}:
            raise ValueError("scale 0 would read every temperature as offset_c")
        names = [c.name for c in self.channels]
        if len(set(names)) != len(names):
            raise ValueError("a channel name is used twice")
        return self


@dataclass
class _Channel:
    name: str
    address: int
    width: int
    data_type: str
    scale: float
    offset_c: float
    byte_order: str
    word_order: str
    burnout: frozenset[int]
    out_of_range: frozenset[int]
    status_address: int | None


def _resolve(cfg: ModbusConfig) -> list[_Channel]:
    out = []
    for c in cfg.channels:
        dt = c.data_type or cfg.data_type
        out.append(
            _Channel(
                c.name,
                c.address,
                register_width(dt),
                dt,
                cfg.scale if c.scale is None else c.scale,
                cfg.offset_c if c.offset_c is None else c.offset_c,
                c.byte_order or cfg.byte_order,
                c.word_order or cfg.word_order,
                frozenset(cfg.burnout_codes if c.burnout_codes is None else c.burnout_codes),
                frozenset(cfg.out_of_range_codes if c.out_of_range_codes is None else c.out_of_range_codes),
                c.status_address,
            )
        )
    return out


class ModbusSource(PolledSource):
    """Polls a Modbus PT100 module on its own thread; `read` never blocks."""

    Config = ModbusConfig

    def __init__(self, cfg: ModbusConfig, base_dir: str = ".") -> None:
        self._channels = _resolve(cfg)
        super().__init__(cfg, base_dir)
        self.cfg: ModbusConfig = cfg
        self.poll_period_s = cfg.poll_period_s
        self.stale_after_s = cfg.stale_after_s
        spans = [(c.address, c.width) for c in self._channels]
        spans += [(c.status_address, 1) for c in self._channels if c.status_address is not None]
        self.requests = plan_reads(spans, cfg.max_gap)
        self._client: Any = None
        self._next_connect_s = 0.0
        self._backoff_s = cfg.reconnect_min_s
        self.connects = 0
        self.exception_replies = 0
        self.comm_errors = 0
        self.malformed_replies = 0
        self.last_error: str | None = None
        self._tap = FrameTap()
        self._bad_request: dict[tuple[int, int], str] = {}  # request → why its last reply was refused

    def signal_names(self) -> list[str]:
        return [c.name for c in self._channels]

    # ------------------------------------------------------------- connection
    def open(self, now_s: float) -> None:
        if self.cfg.transport == "rtu" and self.cfg.serial_port:
            check_serial_port(self.cfg.serial_port, self.config_path)

    def _make_client(self) -> Any:
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # faults are reported as quality
        cfg = self.cfg
        if cfg.transport == "tcp":
            return ModbusTcpClient(cfg.host, port=cfg.port, timeout=cfg.timeout_s, retries=0, trace_packet=self._tap)
        return ModbusSerialClient(
            cfg.serial_port,
            baudrate=cfg.baudrate,
            parity=cfg.parity,
            stopbits=cfg.stopbits,
            timeout=cfg.timeout_s,
            retries=0,
        )

    def _connect(self) -> bool:
        now = time.monotonic()
        if self._client is not None and self._client.connected:
            return True
        if now < self._next_connect_s:
            return False
        if self._client is None:
            self._client = self._make_client()
        try:
            ok = bool(self._client.connect())
        except Exception as e:  # pyserial/OS errors while opening
            ok = False
            self.last_error = f"connect: {e}"
        if ok:
            self.connects += 1
            self._backoff_s = self.cfg.reconnect_min_s
            return True
        self.last_error = self.last_error or "connect failed"
        self._next_connect_s = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.cfg.reconnect_max_s)
        return False

    def _drop(self) -> None:
        """After a comms error: TCP reconnects (the stream may hold a late reply);
        RTU discards whatever is in the input buffer."""
        c = self._client
        if c is None:
            return
        if self.cfg.transport == "tcp":
            c.close()
        else:
            sock = getattr(c, "socket", None)
            if sock is not None:
                try:
                    time.sleep(min(self.cfg.timeout_s, 0.05))
                    sock.reset_input_buffer()
                except Exception:
                    c.close()

    # ------------------------------------------------------------------- poll
    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        if not self._connect():
            quality[:] = Quality.COMMS_LOST
            return
        from pymodbus.exceptions import ModbusException

        cfg = self.cfg
        holding = cfg.function == "holding"
        read = self._client.read_holding_registers if holding else self._client.read_input_registers
        function_code = HOLDING if holding else INPUT
        regs: dict[int, int] = {}
        for start, count in self.requests:
            try:
                rr = read(start, count=count, device_id=cfg.device_id)
            except (ModbusException, OSError, ValueError) as e:
                self.comm_errors += 1
                self.last_error = f"{type(e).__name__}: {e}"
                self._drop()
                break
            if rr.isError():
                self.exception_replies += 1
                self.last_error = f"exception reply, code {getattr(rr, 'exception_code', '?')}"
                continue
            problem = shape_error(rr, function_code, count, cfg.device_id)
            if problem is None and cfg.transport == "tcp":
                problem = self._tap.tcp_error(getattr(rr, "transaction_id", 0), count)
            if problem is not None:
                self._malformed((start, count), problem)
                continue
            if self._bad_request.pop((start, count), None) is not None:
                log.info(
                    "%s: replies to registers %d+%d are well-formed again", self.name, start, count,
                    extra={"event": "modbus_reply_ok", "source": self.name, "request": f"{start}+{count}"},
                )
            regs.update(zip(range(start, start + count), rr.registers, strict=True))
        for i, ch in enumerate(self._channels):
            words = [regs.get(ch.address + k) for k in range(ch.width)]
            status = regs.get(ch.status_address) if ch.status_address is not None else 0
            if any(w is None for w in words) or status is None:
                quality[i] = Quality.COMMS_LOST
                continue
            raw, number = decode_registers(words, ch.data_type, ch.byte_order, ch.word_order)
            q = Quality.GOOD
            if status & cfg.status_burnout_mask or raw in ch.burnout:
                q = Quality.BURNOUT
            elif status & cfg.status_out_of_range_mask or raw in ch.out_of_range:
                q = Quality.OUT_OF_RANGE
            elif not math.isfinite(number):
                q = Quality.BURNOUT  # float modules report a broken sensor as NaN
            else:
                values[i] = number * ch.scale + ch.offset_c
            quality[i] = q

    def _malformed(self, request: tuple[int, int], problem: str) -> None:
        """A reply of the wrong shape: counted, logged once per request and reason, and on
        RTU the input buffer flushed (the frame may not have ended where pymodbus thought)."""
        self.malformed_replies += 1
        start, count = request
        self.last_error = f"malformed reply to registers {start}+{count}: {problem}"
        if self._bad_request.get(request) != problem:
            self._bad_request[request] = problem
            log.warning(
                "%s: %s", self.name, self.last_error,
                extra={"event": "modbus_bad_reply", "source": self.name, "request": f"{start}+{count}",
                       "reason": problem},
            )
        if self.cfg.transport == "rtu":
            self._drop()

    def close(self) -> None:
        super().close()
        if self._client is not None:
            self._client.close()
            self._client = None

    def get_status(self) -> dict[str, Any]:
        return {
            **super().get_status(),
            "transport": self.cfg.transport,
            "requests_per_poll": len(self.requests),
            "polls": self.polls,
            "connects": self.connects,
            "exception_replies": self.exception_replies,
            "comm_errors": self.comm_errors,
            "malformed_replies": self.malformed_replies,
            "last_error": self.last_error,
        }
