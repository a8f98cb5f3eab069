"""A DCON ASCII PT100 module (ADAM-4015 style) on a serial line: `#AA\\r` → `>+025.30+024.90…\\r`.

Commands and replies are ASCII ending in CR. With the checksum option both carry
two upper-case hex digits before the CR: the sum of all preceding bytes mod 256.
`#AA` (AA = the module's hex address) returns every channel in engineering units,
`+ddd.dd`; over range reads `over_text`, under range `under_text` and a burned-out
sensor `burnout_text`. Any other command addressed to the module gets `?AA`; a
command for another address, or with a bad checksum, gets no answer.
Wire faults a test can switch on: no_answer, garbage, crc_error (a wrong checksum,
or a corrupted delimiter without the checksum option), slow (reply after `slow_s`),
invalid (`?AA` to everything).
"""

from __future__ import annotations

import os
from typing import Any

import serial

from hil_sim.devices.pt100 import Pt100Transmitter, ThreadedTransmitter

WIRE_FAULTS = ("none", "no_answer", "garbage", "crc_error", "slow", "invalid")


def checksum(text: bytes) -> bytes:
    """Two hex digits: the sum of the bytes mod 256."""
    return f"{sum(text) & 0xFF:02X}".encode()


class DconModule(ThreadedTransmitter):
    """Answers DCON commands for one address on a serial port, on its own thread."""

    wire_faults = WIRE_FAULTS
    thread_name = "dcon-module"

    def __init__(
        self,
        transmitter: Pt100Transmitter,
        serial_port: str,
        *,
        address: int = 1,
        baudrate: int = 9600,
        use_checksum: bool = False,
        over_text: str = "+9999",
        under_text: str = "-0000",
        burnout_text: str = "-9999.9",
    ) -> None:
        super().__init__(transmitter, slow_s=0.5)
        self.serial_port = serial_port
        self.address = address
        self.baudrate = baudrate
        self.use_checksum = use_checksum
        self.texts = {"over": over_text, "under": under_text, "burnout": burnout_text}
        self.requests = 0
        self._ser: serial.Serial | None = None

    def reply(self, command: bytes) -> bytes | None:
        """The reply to one command (without the wire faults), or None for silence."""
        body = command
        if self.use_checksum:
            if len(body) < 3 or checksum(body[:-2]) != body[-2:].upper():
                return None
            body = body[:-2]
        text = body.decode("ascii", "replace")
        if len(text) < 3 or text[1:3].upper() != f"{self.address:02X}":
            return None
        aa = f"{self.address:02X}"
        if text == f"#{aa}" and self.fault != "invalid":
            fields = []
            for state, v in self.tx.readings():
                fields.append(f"{v:+07.2f}" if state == "ok" else self.texts[state])
            out = (">" + "".join(fields)).encode()
        else:
            out = f"?{aa}".encode()
        if self.use_checksum:
            out += checksum(out)
        return out + b"\r"

    def _run(self) -> None:
        buf = b""
        assert self._ser is not None
        while not self._stop.is_set():
            try:
                chunk = self._ser.read(64)
            except (serial.SerialException, OSError):  # the pty went away: the module is gone
                return
            if not chunk:
                continue
            buf += chunk
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                self.requests += 1
                out = self.reply(line)
                if out is None or self.fault == "no_answer":
                    continue
                if self.fault == "garbage":
                    out = os.urandom(len(out) - 1).replace(b"\r", b"#") + b"\r"
                elif self.fault == "crc_error":
                    if self.use_checksum:
                        out = out[:-3] + (b"0" if out[-3:-2] != b"0" else b"1") + out[-2:]
                    else:
                        out = b"!" + out[1:]
                elif self.fault == "slow":
                    self._stop.wait(self.slow_s)
                try:
                    self._ser.write(out)
                except (serial.SerialException, OSError):
                    return

    def _open(self) -> None:
        self._ser = serial.Serial(self.serial_port, self.baudrate, timeout=0.05)

    def _close(self) -> None:
        if self._ser is not None:
            self._ser.close()
            self._ser = None

    def where(self) -> str:
        return f"dcon:{self.serial_port}@{self.baudrate} address {self.address:02X}"

    @classmethod
    def _from_section(cls, tx: Pt100Transmitter, channels: list[dict[str, Any]], cfg: dict[str, Any]) -> DconModule:
        return cls(tx, cfg.pop("serial_port"), **cfg)
