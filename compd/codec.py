"""The 16-bit direction/enable/value compensation word of paper 002 (docs/formats.md).

One word carries two axes: the high byte is the first axis (X1), the low byte the
second (X2). In each byte bit 7 is the direction (1 = positive correction), bit 6
the enable bit and bits 5..0 the magnitude in LSB (0..63).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

DIR_BIT = 0x80
ENABLE_BIT = 0x40
MAG_MASK = 0x3F
MAX_MAG = 63


class AxisCode(NamedTuple):
    """One axis of a decoded word: direction (+1/-1), enable, magnitude in LSB."""

    direction: int
    enable: bool
    magnitude: int


def join_bytes(high: int, low: int) -> int:
    """The word of two axis bytes: X1's byte high, X2's low."""
    return (high << 8) | low


def word_bytes(word: int) -> tuple[int, int]:
    """The two axis bytes of a word: (X1's, the high byte; X2's, the low byte)."""
    return word >> 8, word & 0xFF


def code_byte(q: int) -> int:
    """The byte of a signed code in LSB (0 → 0x00, disabled; |q| clamped to 63)."""
    if q == 0:
        return 0
    return ENABLE_BIT | min(abs(q), MAX_MAG) | (DIR_BIT if q > 0 else 0)


def word_from_codes(q1: int, q2: int) -> int:
    """The word for two signed codes already in LSB (X1 high byte, X2 low byte)."""
    return join_bytes(code_byte(q1), code_byte(q2))


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


def encode_ex(c1_um: float, c2_um: float, lsb_um: float = 1.0, deadband_um: float = 1.0) -> tuple[int, bool, bool]:
    """Encode two corrections; returns (word, saturated_1, saturated_2)."""
    if not lsb_um > 0:
        raise ValueError(f"lsb_um must be > 0, got {lsb_um}")
    if not deadband_um >= 0:
        raise ValueError(f"deadband_um must be >= 0, got {deadband_um}")
    b1, s1 = encode_byte(c1_um, lsb_um, deadband_um)
    b2, s2 = encode_byte(c2_um, lsb_um, deadband_um)
    return join_bytes(b1, b2), s1, s2


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
    high, low = word_bytes(word)
    return decode_byte(high), decode_byte(low)


def byte_to_um(byte: int, lsb_um: float = 1.0) -> float:
    """The correction a byte applies, in µm (0 when the enable bit is off)."""
    code = decode_byte(byte)
    if not code.enable:
        return 0.0
    return code.direction * code.magnitude * lsb_um


def word_to_um(word: int, lsb_um: float = 1.0) -> tuple[float, float]:
    """The corrections (X1, X2) a word applies, in µm."""
    high, low = word_bytes(word)
    return byte_to_um(high, lsb_um), byte_to_um(low, lsb_um)


def byte_code(byte: int) -> int:
    """The signed code (LSB) a byte carries: ±magnitude, 0 when the enable bit is off."""
    code = decode_byte(byte)
    return code.direction * code.magnitude if code.enable else 0


def codes_from_word(word: int) -> tuple[int, int]:
    """The signed codes (LSB) of X1 and X2 a word carries (0 for a disabled axis)."""
    high, low = word_bytes(word)
    return byte_code(high), byte_code(low)


class Encoder:
    """Stateful encoder: the word walks to the correction one LSB at a time (docs/formats.md).

    Per axis the encoder holds a signed code q (LSB; 0 is the disabled byte 0x00).
    The code starts to move when the guarded correction c is at least the band
    T = max(dead-band, LSB) away from q·LSB (the no-chatter rule: a correction
    hovering at a rounding boundary does not toggle the word), and then walks to
    its goal: round(c/LSB) clamped to ±63, or 0 when |c| ≤ dead-band (paper 002: a
    code is sent only when the error exceeds the dead-band).

    The walk spends a budget that refills at slew/LSB per second (the time the guard
    licensed, so never more than the guard itself moved) and moves the word one LSB a
    cycle at most (several only when the loop's period is longer than LSB/slew; a
    replay, whose rows stand for many of the daemon's cycles, sets an infinite period:
    a row after dt walks what the slew licensed in dt). A settled word banks at most one LSB plus one
    cycle's refill; after a stall, which licenses more than one LSB in one cycle, the
    word catches up one LSB a cycle. Since the guard slews the correction at the same
    rate, the word stays within T of it, plus what c moves in two cycles, plus what a
    stall licensed beyond one LSB a cycle while the word catches up. A dead-band
    below one LSB acts as one LSB: the word cannot hold the correction closer
    without chattering between two codes.

    A disabled axis (enable off, or a correction that is not finite) sends 0x00 at
    once: that is what the `disable` fault policy asks for. It walks up from 0.
    """

    def __init__(
        self,
        lsb_um: float = 1.0,
        deadband_um: float = 1.0,
        max_slew_um_per_s: float = math.inf,
        period_s: float = 0.0,
    ) -> None:
        if not (lsb_um > 0 and math.isfinite(lsb_um)):
            raise ValueError(f"lsb_um must be finite and > 0, got {lsb_um}")
        if not (deadband_um >= 0 and math.isfinite(deadband_um)):
            raise ValueError(f"deadband_um must be finite and >= 0, got {deadband_um}")
        self.lsb_um = lsb_um
        self.deadband_um = deadband_um
        self.band_um = max(deadband_um, lsb_um)
        self._rate_lsb_per_s = [0.0, 0.0]
        self._one_a_cycle = [True, True]
        self.set_slew([max_slew_um_per_s, max_slew_um_per_s], period_s)
        self.word = 0
        self.codes = [0, 0]  # held signed magnitude per axis, LSB
        self.saturated = [False, False]
        self.saturations = 0  # words emitted while some axis was clamped at 63 LSB
        self.words_emitted = 0
        self._moving = [False, False]
        self._budget = [0.0, 0.0]
        self.axis_names: list[str] = []  # the word's axes, high byte first (`bind_axes`)
        self.axes: list[int] = []  # ... as indices into the model's outputs

    def bind_axes(self, names: list[str], outputs: list[str]) -> None:
        """The axes of the word, high byte first (config `codec.axes`), among the model's
        `outputs`: the one place the pipeline, the status and the sinks learn them from."""
        if not 1 <= len(names) <= 2:
            raise ValueError(f"a word carries one or two axes, got {len(names)}")
        self.axis_names = list(names)
        self.axes = [outputs.index(a) for a in names]

    def set_slew(self, max_slew_um_per_s: list[float], period_s: float = 0.0) -> None:
        """The slew limit of the high byte's and the low byte's axis, µm/s (one value: both),
        and the loop's period: while a period is shorter than LSB/slew the word moves at
        most one LSB a cycle (also in the cycles after a stall, which licensed more).
        `math.inf` (a replay): no cap per call, only the budget the time licensed."""
        slew = list(max_slew_um_per_s) * (2 if len(max_slew_um_per_s) == 1 else 1)
        if len(slew) != 2 or not all(s > 0 for s in slew):
            raise ValueError(f"max_slew_um_per_s must be one or two values > 0, got {max_slew_um_per_s}")
        for i in range(2):
            self._rate_lsb_per_s[i] = slew[i] / self.lsb_um
            self._one_a_cycle[i] = self._rate_lsb_per_s[i] * period_s < 1.0

    def settled(self, i: int) -> bool:
        """Axis `i` (0 high byte, 1 low byte) is not walking toward a goal."""
        return not self._moving[i]

    def reset(self) -> None:
        """Forget the held codes (the word walks up again from 0x0000)."""
        self.word = 0
        self.codes[0] = self.codes[1] = 0
        self._moving[0] = self._moving[1] = False
        self._budget[0] = self._budget[1] = 0.0
        self.saturated[0] = self.saturated[1] = False

    def seed(self, i: int, c_um: float) -> None:
        """Axis `i` (0 high byte, 1 low byte) holds what the machine applies now (`c_um`, read
        back by the sink at its start or after its link was restored): its code is the one
        nearest, settled, and the word walks on from there."""
        q = c_um / self.lsb_um if math.isfinite(c_um) else 0.0
        q = math.floor(abs(q) + 0.5) * (1 if q >= 0 else -1)
        self.codes[i] = max(-MAX_MAG, min(MAX_MAG, q))
        self._moving[i] = False
        self._budget[i] = 0.0
        self.saturated[i] = False
        self.word = word_from_codes(self.codes[0], self.codes[1])

    def adopt(self, previous: Encoder) -> None:
        """Config reload: hold what the previous encoder sent (converted to this LSB)."""
        for i in range(2):
            q = previous.codes[i] * previous.lsb_um / self.lsb_um
            q = math.floor(abs(q) + 0.5) * (1 if q >= 0 else -1)
            self.codes[i] = max(-MAX_MAG, min(MAX_MAG, q))
        self.word = word_from_codes(self.codes[0], self.codes[1])
        self.words_emitted = previous.words_emitted

    def _axis(self, i: int, c_um: float, enabled: bool, dt_s: float) -> None:
        if not enabled or not math.isfinite(c_um):
            self.codes[i] = 0
            self._moving[i] = False
            self._budget[i] = 0.0
            self.saturated[i] = False
            return
        lsb = self.lsb_um
        q = self.codes[i]
        if abs(c_um) <= self.deadband_um:
            goal = 0
            self.saturated[i] = False
        else:
            r = abs(c_um) / lsb
            m = math.floor(r + 0.5) if r < MAX_MAG + 1 else MAX_MAG + 1
            self.saturated[i] = m > MAX_MAG
            goal = min(m, MAX_MAG) * (1 if c_um > 0 else -1)
        # the budget refills at slew/LSB per second; what a step leaves carries over, so
        # the word keeps the slew's pace exactly. A settled word keeps at most one LSB plus
        # this cycle's refill; a moving one keeps all (after a stall it catches up, one LSB
        # a cycle, with the time the stall licensed)
        gain = self._rate_lsb_per_s[i] * dt_s if dt_s > 0 else 0.0
        gain = gain if gain < 2 * MAX_MAG else 2.0 * MAX_MAG
        b = self._budget[i] + gain
        if not self._moving[i] and b > 1.0 + gain:  # settled: one LSB and this refill
            b = 1.0 + gain
        b = b if b < 4.0 * MAX_MAG else 4.0 * MAX_MAG
        if not self._moving[i] and goal != q and abs(c_um - q * lsb) >= self.band_um:
            self._moving[i] = True
        if self._moving[i]:
            steps = int(b + 1e-9)
            if steps > 1 and (gain < 1.0 or self._one_a_cycle[i]):  # one LSB a cycle, unless
                steps = 1  # the loop's period is longer than LSB/slew (a replay's rows)
            d = 1 if goal > q else -1
            # walk toward the goal while a step does not take the word further from c (the
            # goal jumps to 0 when c enters the dead-band: never walk away from c for that)
            while q != goal and abs(c_um - (q + d) * lsb) <= abs(c_um - q * lsb) + 1e-9:
                if not steps:
                    break
                q += d
                steps -= 1
                b = b - 1.0 if b > 1.0 else 0.0
            else:
                self._moving[i] = False
            self.codes[i] = q
        self._budget[i] = b

    def update_rows(
        self,
        c1_um: np.ndarray,
        c2_um: np.ndarray,
        en1: np.ndarray,
        en2: np.ndarray,
        dt_s: np.ndarray,
        words: np.ndarray,
        changed: np.ndarray,
    ) -> None:
        """`update` at every row of a replay (row i: c1_um[i], c2_um[i], en1[i], en2[i],
        dt_s[i]); each row's word and whether it changed into `words[i]`, `changed[i]`.

        A row in which both axes stay settled — enabled with the correction within the
        band of its code (or at a goal it holds), or disabled with the code 0 — only
        refills the budgets, with `_axis`'s arithmetic in plain floats; any other row
        calls `update` itself."""
        c1, c2, e1, e2, dts = c1_um.tolist(), c2_um.tolist(), en1.tolist(), en2.tolist(), dt_s.tolist()
        cs = (c1, c2)
        # per axis and row: enabled with a finite correction (else the byte is 0x00, no budget)
        ons = ((en1 & np.isfinite(c1_um)).tolist(), (en2 & np.isfinite(c2_um)).tolist())
        lsb, band = self.lsb_um, self.band_um
        rate = self._rate_lsb_per_s
        codes, moving, budget = self.codes, self._moving, self._budget
        words_out: list[int] = [0] * len(dts)
        changed_out = [False] * len(dts)
        word = self.word
        for i, dt in enumerate(dts):
            quiet = self.words_emitted > 0
            if quiet:
                for a in (0, 1):
                    if ons[a][i]:
                        c = cs[a][i]
                        # moving, or far enough from its code to move (unless it holds its goal)
                        if moving[a] or (abs(c - codes[a] * lsb) >= band and self._goal(c) != codes[a]):
                            quiet = False
                            break
                    elif codes[a]:
                        quiet = False
                        break
            if not quiet:
                changed_out[i] = self.update(c1[i], c2[i], e1[i], e2[i], dt)
                words_out[i] = word = self.word
                continue
            for a in (0, 1):
                if not ons[a][i]:
                    moving[a] = False
                    budget[a] = 0.0
                    continue
                # _axis's refill of a settled axis
                gain = rate[a] * dt if dt > 0 else 0.0
                gain = gain if gain < 2 * MAX_MAG else 2.0 * MAX_MAG
                b = budget[a] + gain
                if b > 1.0 + gain:
                    b = 1.0 + gain
                budget[a] = b if b < 4.0 * MAX_MAG else 4.0 * MAX_MAG
            words_out[i] = word
        if words_out:  # the flags `_axis` leaves, as of the last row
            for a in (0, 1):
                c = cs[a][-1]
                if ons[a][-1] and abs(c) > self.deadband_um:
                    r = abs(c) / lsb
                    self.saturated[a] = (math.floor(r + 0.5) if r < MAX_MAG + 1 else MAX_MAG + 1) > MAX_MAG
                else:
                    self.saturated[a] = False
        words[:] = words_out
        changed[:] = changed_out

    def _goal(self, c_um: float) -> int:
        """The code `_axis` walks toward for the correction c (enabled, finite)."""
        if abs(c_um) <= self.deadband_um:
            return 0
        r = abs(c_um) / self.lsb_um
        m = math.floor(r + 0.5) if r < MAX_MAG + 1 else MAX_MAG + 1
        return min(m, MAX_MAG) * (1 if c_um > 0 else -1)

    def update(self, c1_um: float, c2_um: float, en1: bool = True, en2: bool = True, dt_s: float = math.inf) -> bool:
        """Offer the guarded corrections of one cycle; returns True when the word changed.

        `dt_s` is the time this cycle licenses (the guard's: one period after a clock
        jump, 0 when time went backwards); inf lets the word reach its goal at once.
        `en1`/`en2` False force that axis's byte to 0x00 (disabled).
        """
        self._axis(0, c1_um, en1, dt_s)
        self._axis(1, c2_um, en2, dt_s)
        word = word_from_codes(self.codes[0], self.codes[1])
        changed = word != self.word or not self.words_emitted
        if changed:
            self.word = word
            self.words_emitted += 1
            if self.saturated[0] or self.saturated[1]:
                self.saturations += 1
        return changed
