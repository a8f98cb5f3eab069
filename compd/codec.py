"""The 16-bit direction/enable/value compensation word of paper 002 (SPEC §2).

One word carries two axes: the high byte is the first axis (X1), the low byte the
second (X2). In each byte bit 7 is the direction (1 = positive correction), bit 6
the enable bit and bits 5..0 the magnitude in LSB (0..63).
"""

from __future__ import annotations

import math
from typing import NamedTuple

DIR_BIT = 0x80
ENABLE_BIT = 0x40
MAG_MASK = 0x3F
MAX_MAG = 63


class AxisCode(NamedTuple):
    """One axis of a decoded word: direction (+1/-1), enable, magnitude in LSB."""

    direction: int
    enable: bool
    magnitude: int


def encode_byte(c_um: float, lsb_um: float = 1.0, deadband_um: float = 1.0) -> tuple[int, bool]:
    """Encode one axis's correction into a byte; returns (byte, saturated).

    |c| <= dead-band, or a NaN/inf, encodes as 0x00 (disabled). The magnitude is
    round-half-up of |c|/LSB clamped to 63; a clamp reports saturation.
    """
    if not math.isfinite(c_um) or abs(c_um) <= deadband_um:
        return 0, False
    q = abs(c_um) / lsb_um + 0.5  # inf for a denormal LSB: clamp before floor() overflows
    mag = math.floor(q) if q < MAX_MAG + 1 else MAX_MAG + 1
    saturated = mag > MAX_MAG
    if saturated:
        mag = MAX_MAG
    if mag == 0:
        return 0, False
    byte = ENABLE_BIT | mag
    if c_um > 0:
        byte |= DIR_BIT
    return byte, saturated


def encode_ex(
    c1_um: float, c2_um: float, lsb_um: float = 1.0, deadband_um: float = 1.0
) -> tuple[int, bool, bool]:
    """Encode two corrections; returns (word, saturated_1, saturated_2)."""
    if not lsb_um > 0:
        raise ValueError(f"lsb_um must be > 0, got {lsb_um}")
    if not deadband_um >= 0:
        raise ValueError(f"deadband_um must be >= 0, got {deadband_um}")
    b1, s1 = encode_byte(c1_um, lsb_um, deadband_um)
    b2, s2 = encode_byte(c2_um, lsb_um, deadband_um)
    return (b1 << 8) | b2, s1, s2


def encode(c1_um: float, c2_um: float, lsb_um: float = 1.0, deadband_um: float = 1.0) -> int:
    """The 16-bit word for corrections c1 (high byte) and c2 (low byte), in µm."""
    return encode_ex(c1_um, c2_um, lsb_um, deadband_um)[0]


def decode_byte(byte: int) -> AxisCode:
    """Split one byte into (direction, enable, magnitude)."""
    return AxisCode(1 if byte & DIR_BIT else -1, bool(byte & ENABLE_BIT), byte & MAG_MASK)


def decode(word: int) -> tuple[AxisCode, AxisCode]:
    """Both axes of a word: ((dir, enable, mag) of X1, (dir, enable, mag) of X2)."""
    if not 0 <= word <= 0xFFFF:
        raise ValueError(f"word must be 0..0xFFFF, got {word}")
    return decode_byte(word >> 8), decode_byte(word & 0xFF)


def byte_to_um(byte: int, lsb_um: float = 1.0) -> float:
    """The correction a byte applies, in µm (0 when the enable bit is off)."""
    code = decode_byte(byte)
    if not code.enable:
        return 0.0
    return code.direction * code.magnitude * lsb_um


def word_to_um(word: int, lsb_um: float = 1.0) -> tuple[float, float]:
    """The corrections (X1, X2) a word applies, in µm."""
    return byte_to_um(word >> 8, lsb_um), byte_to_um(word & 0xFF, lsb_um)


class Encoder:
    """Stateful encoder with the no-chatter rule of SPEC §2.

    A new word is produced only when some axis's correction has moved by at least
    the dead-band from the value last emitted for it; otherwise the last word
    stands, so rounding boundaries do not chatter.
    """

    def __init__(self, lsb_um: float = 1.0, deadband_um: float = 1.0) -> None:
        if not lsb_um > 0:
            raise ValueError(f"lsb_um must be > 0, got {lsb_um}")
        if not deadband_um >= 0:
            raise ValueError(f"deadband_um must be >= 0, got {deadband_um}")
        self.lsb_um = lsb_um
        self.deadband_um = deadband_um
        self.word = 0
        self.saturated = [False, False]
        self.saturations = 0
        self.words_emitted = 0
        self._last1 = 0.0
        self._last2 = 0.0
        self._enabled = [True, True]

    def reset(self) -> None:
        """Forget what was emitted (the next update always emits)."""
        self.word = 0
        self._last1 = 0.0
        self._last2 = 0.0
        self.saturated[0] = self.saturated[1] = False

    def update(self, c1_um: float, c2_um: float, en1: bool = True, en2: bool = True) -> bool:
        """Offer new corrections; returns True when a new word was emitted.

        `en1`/`en2` False force that axis's byte to 0x00 (disabled) regardless of
        its value; a change of enable always emits.
        """
        if not math.isfinite(c1_um):
            c1_um, en1 = 0.0, False
        if not math.isfinite(c2_um):
            c2_um, en2 = 0.0, False
        db = self.deadband_um
        if (
            self.words_emitted
            and en1 == self._enabled[0]
            and en2 == self._enabled[1]
            and abs(c1_um - self._last1) < db
            and abs(c2_um - self._last2) < db
        ):
            return False
        b1, s1 = encode_byte(c1_um, self.lsb_um, db) if en1 else (0, False)
        b2, s2 = encode_byte(c2_um, self.lsb_um, db) if en2 else (0, False)
        self._last1, self._last2 = c1_um, c2_um
        self._enabled[0], self._enabled[1] = en1, en2
        self.saturated[0], self.saturated[1] = s1, s2
        if s1 or s2:
            self.saturations += 1
        word = (b1 << 8) | b2
        changed = word != self.word or not self.words_emitted
        self.word = word
        self.words_emitted += 1
        return changed
