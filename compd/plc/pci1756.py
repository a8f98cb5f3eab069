"""Advantech PCI-1756 as a virtual card: 32 isolated DI and 32 isolated DO, latching outputs."""

from __future__ import annotations

import threading

from compd.sinks.pci1756 import DoCard


class Pci1756Card(DoCard):
    """The card's register state.

    DO bytes 0–3 latch the last value written and keep it until written again or
    the card is reset (reset clears them to 0, as a power-up does). DI bytes 0–3
    are set by whatever is wired to the inputs (`set_di`). Byte access and 16-bit
    word access (little-endian: the low byte at the lower offset) as in the comedi
    driver. Thread-safe: a PMC may read the DO lines from another thread (`FanucPmc(card=...)`).
    """

    PORTS = 4

    def __init__(self) -> None:
        self._do = bytearray(self.PORTS)
        self._di = bytearray(self.PORTS)
        self._lock = threading.Lock()
        self.do_writes = 0
        self.resets = 0

    def write_do_word(self, port: int, value: int) -> None:
        self._check(port, 2)
        with self._lock:
            self._do[port] = value & 0xFF
            self._do[port + 1] = (value >> 8) & 0xFF
            self.do_writes += 1

    def write_do_bit(self, bit: int, on: bool) -> None:
        if not 0 <= bit < 8 * self.PORTS:
            raise ValueError(f"DO bit {bit} out of range 0..{8 * self.PORTS - 1}")
        with self._lock:
            if on:
                self._do[bit // 8] |= 1 << (bit % 8)
            else:
                self._do[bit // 8] &= ~(1 << (bit % 8)) & 0xFF
            self.do_writes += 1

    def read_do_byte(self, port: int) -> int:
        self._check(port, 1)
        with self._lock:
            return self._do[port]

    def read_do_word(self, port: int) -> int:
        self._check(port, 2)
        with self._lock:
            return self._do[port] | (self._do[port + 1] << 8)

    def read_do(self) -> int:
        """All 32 DO lines as one integer (bit 0 = DO0)."""
        with self._lock:
            return int.from_bytes(self._do, "little")

    def set_di(self, value: int) -> None:
        with self._lock:
            self._di[:] = (value & 0xFFFFFFFF).to_bytes(4, "little")

    def read_di_byte(self, port: int) -> int:
        self._check(port, 1)
        with self._lock:
            return self._di[port]

    def reset(self) -> None:
        """A card reset: every output off."""
        with self._lock:
            self._do[:] = bytes(self.PORTS)
            self.resets += 1

    def _check(self, port: int, width: int) -> None:
        if not 0 <= port <= self.PORTS - width:
            raise ValueError(f"port {port} out of range for a {width}-byte access")
