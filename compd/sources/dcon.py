"""PT100 modules speaking DCON ASCII (ADAM-4015 style) over a serial line (pyserial), polled.

`#AA\\r` asks module AA (hex) for all channels; it answers `>+025.30+024.90…\\r` in
engineering units (°C). With `checksum: true` both carry the sum of their bytes mod
256 as two hex digits before the CR. The module signals out of range and burn-out
with fixed texts in place of a value (`out_of_range_codes`, `burnout_codes`: the
defaults are the ADAM-4000 engineering-unit codes +9999 / -0000 and -9999.9; set
them to your module's manual). The reply must have exactly one field per entry of
`channels` (list every channel of the module, null for those not used): a reply with more
or fewer values is not this module's answer to `#AA`. No reply within `timeout_s`, a
garbled or wrong-length reply, a bad checksum, a reply that does not start with `>`, or
`?AA`/`!AA` (command rejected, or an answer to another command; AA must be our address)
make every channel of the module COMMS_LOST, counted in `comm_errors` with `last_error`.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import SourceConfig
from compd.core.frame import Quality
from compd.io.mailbox import Snapshot
from compd.io.worker import LinkDown, stall_after
from compd.sources.base import PolledSource, Poller, check_serial_port

_FIELD = re.compile(rb"[+-][0-9.]+")


def dcon_checksum(data: bytes) -> bytes:
    """Two upper-case hex digits: the sum of the bytes mod 256."""
    return f"{sum(data) & 0xFF:02X}".encode()


def parse_reply(reply: bytes, address: int, use_checksum: bool, fields: int | None = None) -> list[bytes]:
    """The value fields of a `>…` reply to `#AA` (exactly `fields` of them, if given);
    ValueError names what is wrong with it."""
    if not reply.endswith(b"\r"):
        raise ValueError("no reply (timeout)" if not reply else "reply not terminated by CR")
    body = reply[:-1]
    if use_checksum:
        if len(body) < 3 or dcon_checksum(body[:-2]) != body[-2:].upper():
            raise ValueError("checksum error")
        body = body[:-2]
    if body[:1] in (b"?", b"!"):  # `?AA` rejected, `!AA…` answers another command
        text = body.decode("ascii", "replace")
        if body[1:3].upper() != f"{address:02X}".encode():
            raise ValueError(f"reply from another address ({text}), asked {address:02X}")
        raise ValueError(f"command rejected ({text})" if body[:1] == b"?" else f"reply to another command ({text})")
    if not body.startswith(b">"):
        raise ValueError("reply does not start with '>'")
    found = _FIELD.findall(body[1:])
    if b"".join(found) != body[1:]:
        raise ValueError("garbled reply")
    if fields is not None and len(found) != fields:
        raise ValueError(f"{len(found)} values, {fields} channels configured")
    return found


class DconConfig(SourceConfig):
    """One DCON module on a serial port; `channels` name its values in reply order."""

    serial_port: str = Field(description="serial device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(9600, ge=300, le=4_000_000, description="bit/s")
    address: int = Field(1, ge=0, le=255, description="module address (AA, hex on the wire)")
    checksum: bool = False
    channels: list[str | None] = Field(
        min_length=1, description="one entry per channel of the module, in reply order: its signal, or null"
    )
    out_of_range_codes: list[str] = Field(default_factory=lambda: ["+9999", "-0000"])
    burnout_codes: list[str] = Field(default_factory=lambda: ["-9999.9"])
    poll_period_s: float = Field(0.2, ge=0.001, le=60)
    timeout_s: float = Field(0.3, ge=0.001, le=30)
    stale_after_s: float | None = Field(None, gt=0, le=86400, description="longer than poll_period_s")

    @model_validator(mode="after")
    def _check(self) -> DconConfig:
        if self.stale_after_s is not None and not self.stale_after_s > self.poll_period_s:
            raise ValueError("stale_after_s must be longer than poll_period_s (else every sample is stale)")
        names = [c for c in self.channels if c]
        if not names:
            raise ValueError("name at least one channel")
        if len(set(names)) != len(names):
            raise ValueError("a channel name is used twice")
        return self


class DconSource(PolledSource):
    """A DCON module, polled (`#AA`) by its I/O worker; `read` never blocks."""

    Config = DconConfig
    # a port that cannot be opened is tried again every second
    reconnect_min_s = 1.0
    reconnect_max_s = 1.0

    def __init__(self, cfg: DconConfig, base_dir: str = ".") -> None:
        self.stall_after_s = stall_after(cfg.timeout_s)
        self._slots = [(i, n) for i, n in enumerate(cfg.channels) if n]
        super().__init__(cfg, base_dir)
        self.cfg: DconConfig = cfg
        self.poll_period_s = cfg.poll_period_s
        self.stale_after_s = cfg.stale_after_s

    def signal_names(self) -> list[str]:
        return [n for _, n in self._slots]

    def open(self, now_s: float) -> None:
        check_serial_port(self.cfg.serial_port, self.config_path)

    def make_poller(self, snapshot: Snapshot) -> DconPoller:
        return DconPoller(self.cfg, self._slots, snapshot)

    def get_status(self) -> dict[str, Any]:
        io = self.io_status()
        return {
            **super().get_status(),
            "polls": self.polls,
            "comm_errors": io["comm_errors"],
            "last_error": io["last_error"],
        }


class DconPoller(Poller):
    """The device half of a DCON source: `#AA` out, the reply parsed (the worker's thread)."""

    def __init__(self, cfg: DconConfig, slots: list[tuple[int, str]], snapshot: Snapshot) -> None:
        super().__init__(len(slots), snapshot)
        self.cfg = cfg
        self._slots = slots
        cmd = f"#{cfg.address:02X}".encode()
        self.command = cmd + (dcon_checksum(cmd) if cfg.checksum else b"") + b"\r"
        self._burnout = {c.encode() for c in cfg.burnout_codes}
        self._out_of_range = {c.encode() for c in cfg.out_of_range_codes}
        self._ser: Any = None
        self.comm_errors = 0

    def connect(self) -> None:
        import serial

        try:
            self._ser = serial.Serial(self.cfg.serial_port, self.cfg.baudrate, timeout=self.cfg.timeout_s)
        except (serial.SerialException, OSError) as e:
            raise LinkDown(f"open: {e}") from None

    def disconnect(self) -> None:
        if self._ser is not None:
            self._ser.close()
            self._ser = None

    def counters(self) -> dict[str, Any]:
        return {**super().counters(), "comm_errors": self.comm_errors}

    def poll(self, values: np.ndarray, quality: np.ndarray) -> None:
        try:
            self._ser.reset_input_buffer()  # a late reply to an earlier request
            self._ser.write(self.command)
            reply = self._ser.read_until(b"\r")
        except OSError as e:  # the port went away: the worker opens it again
            quality[:] = Quality.COMMS_LOST
            raise LinkDown(f"serial: {e}") from None
        try:
            fields = parse_reply(reply, self.cfg.address, self.cfg.checksum, len(self.cfg.channels))
        except ValueError as e:
            self.comm_errors += 1
            self.last_error = str(e)
            quality[:] = Quality.COMMS_LOST
            return
        for k, (i, _) in enumerate(self._slots):
            f = fields[i]
            if f in self._burnout:
                quality[k] = Quality.BURNOUT
            elif f in self._out_of_range:
                quality[k] = Quality.OUT_OF_RANGE
            else:
                try:
                    v = float(f)
                except ValueError:  # a field like "+1.2.3": the reply is garbled
                    v = math.nan
                if math.isfinite(v):
                    values[k] = v
                    quality[k] = Quality.GOOD
                else:
                    self.comm_errors += 1
                    self.last_error = f"not a number: {f!r}"
                    quality[k] = Quality.COMMS_LOST
