"""PT100 modules (and PLC signal bits) over Modbus TCP or Modbus RTU (pymodbus), polled beside the cycle.

Each channel is a register (or a register pair) holding a scaled temperature:
value_c = raw · scale + offset_c, with the data type, byte order and word order of
the module. Raw codes that mean burn-out or out of range, and optional per-channel
status registers, become signal quality. Channels whose registers lie next to each
other are read in one request. A timeout, a garbled reply, a Modbus exception reply,
a reply of the wrong shape (another function code, more or fewer registers than asked,
a frame longer than its byte count: `compd.io.modbus_client`) or a lost connection makes
the channels of that request COMMS_LOST; a reply fills only the registers its own request
asked for. The source's I/O worker re-establishes the connection with exponential
back-off and the daemon never sees an exception. A channel with `bit`, or any channel
of a source that reads coils or discrete inputs (`function`), is a signal bit (0 or 1:
a CNC's inhibit, an axis referenced), with no scale and no fault codes.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import SourceConfig, Strict
from compd.core.frame import Quality
from compd.io.mailbox import Snapshot
from compd.io.modbus_client import (
    BadReply,
    ExceptionReply,
    LinkFault,
    ModbusClient,
    ModbusFault,
    NoConnection,
    OverModbus,
)
from compd.io.worker import LinkDown, stall_after
from compd.sources.base import PolledSource, Poller, check_serial_port

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


def plan_reads(spans: list[tuple[int, int]], max_gap: int = 0, max_count: int = 125) -> list[tuple[int, int]]:
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
    bit: int | None = Field(
        None,
        ge=0,
        le=31,
        description="read one bit of the register as 0 or 1 (a PMC or PLC signal: inhibit, referenced);"
        " no scale, offset or fault codes",
    )


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
    function: Literal["holding", "input", "coils", "discrete"] = Field(
        "holding",
        description="register table; coils or discrete (inputs): every channel is one bit at its address,"
        " read as 0 or 1 (a PLC signal: inhibit, referenced)",
    )
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
        one_bit = register_width(self.data_type) == 1 and not any(
            c.bit is not None or c.status_address is not None or (c.data_type or "").endswith("32")
            for c in self.channels
        )
        if self.function in ("coils", "discrete") and not one_bit:
            raise ValueError(
                f"function {self.function}: a channel is one bit (no bit, status_address or 32-bit data_type)"
            )
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
    bit: int | None = None


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
                c.bit,
            )
        )
    return out


class ModbusSource(PolledSource):
    """A Modbus PT100 module, polled by its I/O worker; `read` never blocks."""

    Config = ModbusConfig

    def __init__(self, cfg: ModbusConfig, base_dir: str = ".") -> None:
        self.stall_after_s = stall_after(cfg.timeout_s)
        self._channels = _resolve(cfg)
        super().__init__(cfg, base_dir)
        self.cfg: ModbusConfig = cfg
        self.poll_period_s = cfg.poll_period_s
        self.stale_after_s = cfg.stale_after_s
        self.reconnect_min_s, self.reconnect_max_s = cfg.reconnect_min_s, cfg.reconnect_max_s
        spans = [(c.address, c.width) for c in self._channels]
        spans += [(c.status_address, 1) for c in self._channels if c.status_address is not None]
        self.requests = plan_reads(spans, cfg.max_gap)

    def signal_names(self) -> list[str]:
        return [c.name for c in self._channels]

    def open(self, now_s: float) -> None:
        if self.cfg.transport == "rtu" and self.cfg.serial_port:
            check_serial_port(self.cfg.serial_port, self.config_path)

    def make_poller(self, snapshot: Snapshot) -> ModbusPoller:
        return ModbusPoller(self.cfg, self._channels, self.requests, snapshot, self.name)

    def get_status(self) -> dict[str, Any]:
        io = self.io_status()
        return {
            **super().get_status(),
            "transport": self.cfg.transport,
            "requests_per_poll": len(self.requests),
            "polls": self.polls,
            "connects": io["client_connects"],
            "exception_replies": io["exception_replies"],
            "comm_errors": io["comm_errors"],
            "malformed_replies": io["malformed_replies"],
            "last_error": io["last_error"],
        }


class ModbusPoller(OverModbus, Poller):
    """The device half of a Modbus source: the planned requests, read through the Modbus
    client, decoded into temperatures and qualities (runs on the worker's thread)."""

    client: ModbusClient

    def __init__(
        self,
        cfg: ModbusConfig,
        channels: list[_Channel],
        requests: list[tuple[int, int]],
        snapshot: Snapshot,
        name: str,
    ) -> None:
        super().__init__(len(channels), snapshot)
        self.cfg = cfg
        self.name = name
        self._channels = channels
        self.requests = requests
        self.client = ModbusClient(
            transport=cfg.transport,
            host=cfg.host,
            port=cfg.port,
            serial_port=cfg.serial_port,
            baudrate=cfg.baudrate,
            parity=cfg.parity,
            stopbits=cfg.stopbits,
            device_id=cfg.device_id,
            timeout_s=cfg.timeout_s,
        )
        self.exception_replies = 0
        self.comm_errors = 0
        self.malformed_replies = 0
        self._bad_request: dict[tuple[int, int], str] = {}  # request → why its last reply was refused

    def counters(self) -> dict[str, Any]:
        return {
            **super().counters(),
            "exception_replies": self.exception_replies,
            "comm_errors": self.comm_errors,
            "malformed_replies": self.malformed_replies,
            "client_connects": self.client.connects,
        }

    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        cfg = self.cfg
        regs: dict[int, int] = {}
        unreachable: NoConnection | None = None
        bit_table = cfg.function in ("coils", "discrete")
        for start, count in self.requests:
            if cfg.function == "coils" or cfg.function == "discrete":
                r = self.client.read_bits(start, count, table=cfg.function)
            else:
                r = self.client.read_registers(start, count, table=cfg.function)
            if isinstance(r, NoConnection):
                self.last_error = r.detail
                unreachable = r
                break
            if isinstance(r, LinkFault):  # TCP: closed, the next request reconnects; RTU: flushed
                self.comm_errors += 1
                self.last_error = r.detail
                break
            if isinstance(r, ExceptionReply):
                self.exception_replies += 1
                self.last_error = r.detail
                continue
            if isinstance(r, BadReply):
                self._malformed((start, count), r)
                continue
            assert not isinstance(r, ModbusFault)
            if self._bad_request.pop((start, count), None) is not None:
                log.info(
                    "%s: replies to registers %d+%d are well-formed again",
                    self.name,
                    start,
                    count,
                    extra={"event": "modbus_reply_ok", "source": self.name, "request": f"{start}+{count}"},
                )
            regs.update(zip(range(start, start + count), r, strict=True))
        for i, ch in enumerate(self._channels):
            words = [regs[a] for a in range(ch.address, ch.address + ch.width) if a in regs]
            status = regs.get(ch.status_address) if ch.status_address is not None else 0
            if len(words) < ch.width or status is None:
                quality[i] = Quality.COMMS_LOST
                continue
            raw, number = decode_registers(words, ch.data_type, ch.byte_order, ch.word_order)
            if ch.bit is not None or bit_table:  # a signal bit: no fault codes in a control register
                values[i] = float((raw >> (ch.bit or 0)) & 1)
                quality[i] = Quality.GOOD
                continue
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
        if unreachable is not None:  # the worker reconnects with back-off
            raise LinkDown(unreachable.detail)

    def _malformed(self, request: tuple[int, int], fault: BadReply) -> None:
        """A reply of the wrong shape: counted, logged once per request and reason (the
        client has flushed an RTU line already)."""
        self.malformed_replies += 1
        start, count = request
        self.last_error = fault.detail
        if self._bad_request.get(request) != fault.reason:
            self._bad_request[request] = fault.reason
            log.warning(
                "%s: %s",
                self.name,
                self.last_error,
                extra={
                    "event": "modbus_bad_reply",
                    "source": self.name,
                    "request": f"{start}+{count}",
                    "reason": fault.reason,
                },
            )
