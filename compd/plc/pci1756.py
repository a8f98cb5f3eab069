"""The PCI-1756 card: what the sink needs of a driver (DoCard), and the card as a virtual device.

The virtual card has 32 DI, 32 DO, latching.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod

from compd.io.worker import LinkState


class DoCard(ABC):
    """What the sink needs of a PCI-1756 driver (the software PLC's card, the card over
    Modbus, a real driver): 16-bit words on two DO bytes (low byte at `port`), single DO bits."""

    def start(self) -> None:
        """Connect (a card reached over a network); called when the sink opens. A card in this
        process has its lines read back at once (`held`)."""
        self._held_epoch += 1

    def link_state(self) -> LinkState:
        """Whether what is written reaches the lines: a card in this process always does."""
        return "up"

    def flush(self, timeout_s: float) -> bool:
        """Wait until every write so far has reached the lines (in process: at once)."""
        return True

    def ensure_serving(self) -> bool:
        """Before the safe output: a card reached through a worker gets a fresh one when its
        worker is gone (see ModbusLink.ensure_serving); in process: nothing to do."""
        return True

    # what the DO lines hold when the card is reached (at the start, after its link is restored):
    # a card in this process reads its latch at once; a card over a link, at every connect
    _held_epoch = 0
    _taken_epoch = 0

    def held(self) -> tuple[int, int] | None:
        """(epoch, the 32 DO lines as read back) for a connection whose lines the sink has not
        yet taken; None otherwise. Never waits. A card in this process: its latch, once per start."""
        if self._held_epoch == self._taken_epoch:
            return None
        return self._held_epoch, self.read_do()

    def accept(self, epoch: int, lines: int) -> None:
        """The sink takes the lines read back (and writes from them from now on)."""
        self._taken_epoch = epoch

    def synced(self) -> bool:
        """Whether the lines have been taken for the current connection: what is written is sent."""
        return self._held_epoch > 0 and self._taken_epoch == self._held_epoch

    def await_held(self, timeout_s: float) -> bool:
        """Outside the cycle: wait until `held` (or the card is synced); in process: at once."""
        return True

    def read_do(self) -> int:
        """All 32 DO lines as one integer (bit 0 = DO0): the card's output latch read back."""
        raise NotImplementedError

    @abstractmethod
    def write_do_word(self, port: int, value: int) -> None: ...

    @abstractmethod
    def write_do_bit(self, bit: int, on: bool) -> None: ...

    @abstractmethod
    def read_do_word(self, port: int) -> int: ...

    def close(self) -> None:
        """Release the connection; called when the sink closes."""


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
