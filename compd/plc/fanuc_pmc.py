"""FANUC PMC software PLC (paper 003): fixed scan, X/Y/R/D memory, the external-shift ladder.

Memory map (Modbus holding registers, one register per PMC byte for X and Y, one
16-bit word per register for R, D and status; signed values are two's complement):

| register | PMC | meaning |
|---|---|---|
| 0–15     | X0–X15  | inputs; X0 = word low byte, X1 = word high byte, X2.0 = strobe (defaults, see D2–D4) |
| 100–115  | Y0–Y15  | outputs; Y0.0 = alarm lamp, Y0.1 = strobe acknowledge (the strobe level last latched) |
| 200      | R0      | latched word |
| 201      | R1      | latch count (mod 65536) |
| 202, 203 | R2, R3  | commanded shift, axis 1 and 2, µm (written by the ladder on a strobe edge, or directly) |
| 300      | D0      | step limit, µm: a larger single change of the shift raises the axis alarm |
| 301      | D1      | word LSB, nm (1000 = 1 µm) |
| 302–304  | D2–D4   | X byte of the word's low byte, X byte of the strobe, strobe bit |
| 400, 401 | —       | scan counter, low and high word |
| 402      | —       | alarm bits (bit 0 axis 1, bit 1 axis 2); latched until reset |
| 403      | —       | alarm reset: write non-zero, the next scan clears the alarms and this register |
| 404, 405 | —       | applied external machine coordinate shift, axis 1 and 2, µm |
| 406, 407 | —       | alarm count, axis 1 and 2 |
| 500–507  | D100–D107 | probe result, written by the CNC's probing cycle (compd.plc.probe_block): 500 sequence\
 (first), 501 axis index, 502–503 deviation nm int32, 504–505 position µm int32 (0x80000000 none), 506 σ nm, 507\
 sequence (last) |

Ladder, every scan (default 8 ms): copy the wired card's DO bytes into X0–X3 (if a
PCI-1756 card is wired); on any edge of the strobe bit latch X(word)..X(word)+1
into R0 and decode it (bit 7 direction, 1 = positive; bit 6 enable; bits 5..0
magnitude × LSB) into R2/R3; then per axis, if the command differs from the applied
shift: apply it when the change is within the step limit, otherwise raise the
axis alarm and hold the shift until reset (the shift is absolute: the axis moves by
the difference, FANUC external machine coordinate shift).

The probe result (500–507) is not the ladder's: the CNC's probing cycle writes it
(`publish_probe`, or a client over Modbus); the PMC only holds it.
"""

from __future__ import annotations

import threading

from compd.plc.link import VirtualDevice, last_due
from compd.plc.pci1756 import DoCard
from compd.plc.probe_block import PROBE_COUNT, ProbeBlock

X_BASE, Y_BASE, R_BASE, D_BASE, S_BASE, PROBE_BASE = 0, 100, 200, 300, 400, 500
N_X, N_Y, N_R, N_D, N_S = 16, 16, 16, 16, 16
REGISTER_COUNT = PROBE_BASE + PROBE_COUNT
SCAN_LO, SCAN_HI, ALARM, RESET, APPLIED, ALARM_COUNT = 400, 401, 402, 403, 404, 406
LATCHED, LATCH_COUNT, COMMAND = 200, 201, 202
STEP_LIMIT, LSB_NM, WORD_X, STROBE_X, STROBE_BIT = 300, 301, 302, 303, 304
AREAS = [(X_BASE, N_X), (Y_BASE, N_Y), (R_BASE, N_R), (D_BASE, N_D), (S_BASE, N_S), (PROBE_BASE, PROBE_COUNT)]


def _signed(v: int) -> int:
    return v - 0x10000 if v & 0x8000 else v


def decode_byte_um(byte: int, lsb_um: float) -> float:
    """One axis byte of the word in µm: bit 7 sign (1 = +), bit 6 enable, bits 5..0 magnitude."""
    if not byte & 0x40:
        return 0.0
    mag = (byte & 0x3F) * lsb_um
    return mag if byte & 0x80 else -mag


class FanucPmc(VirtualDevice):
    """The PLC's memory and ladder; `scan` runs one scan, `advance_to` all scans up to a time."""

    def __init__(
        self,
        *,
        scan_s: float = 0.008,
        step_limit_um: int = 10,
        lsb_um: float = 1.0,
        word_x: int = 0,
        strobe_x: int = 2,
        strobe_bit: int = 0,
        card: DoCard | None = None,
    ) -> None:
        self.scan_s = scan_s
        self.mem = [0] * PROBE_BASE  # X..status; the probe block lives in `probe`
        self.probe = ProbeBlock()
        self.mem[STEP_LIMIT] = step_limit_um
        self.mem[LSB_NM] = int(round(lsb_um * 1000))
        self.mem[WORD_X], self.mem[STROBE_X], self.mem[STROBE_BIT] = word_x, strobe_x, strobe_bit
        self.card = card
        self.register_count = REGISTER_COUNT
        self.t_s = 0.0
        self.next_scan_s = 0.0
        self.scans = 0
        # scan k is due at start + k·scan_s: the same times however the sink's calls fall
        # (a replay that reads the PMC every row and one that skips the idle rows agree)
        self._t0_s = 0.0
        self._k = 0
        # the last scan changed nothing and no register was written since: later scans
        # cannot change anything either (without a card, inputs change only by writes)
        self._quiet = False
        self._last_strobe = 0
        self._lock = threading.Lock()

    # ----------------------------------------------------------- Modbus access
    @staticmethod
    def _valid(address: int, count: int) -> bool:
        return any(base <= address and address + count <= base + n for base, n in AREAS)

    def read_registers(self, address: int, count: int) -> list[int] | None:
        if not self._valid(address, count):
            return None
        with self._lock:
            if address >= PROBE_BASE:
                return self.probe.regs[address - PROBE_BASE : address - PROBE_BASE + count]
            return self.mem[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> bool:
        if not self._valid(address, len(values)):
            return False
        with self._lock:
            mem, base = (self.probe.regs, PROBE_BASE) if address >= PROBE_BASE else (self.mem, 0)
            for k, v in enumerate(values):
                mem[address - base + k] = v & 0xFFFF
            self._quiet = False
        return True

    def publish_probe(
        self, axis: int, deviation_um: float, position_mm: float | None = None, sigma_um: float | None = None
    ) -> int:
        """The probing cycle ran: write its result (axis index 0-based, deviation µm measured
        with the correction in place, position mm or None, σ µm or None) into D100–D107 at
        once, with the next sequence number, which it returns."""
        with self._lock:
            return self.probe.publish(axis, deviation_um, position_mm, sigma_um)

    # ------------------------------------------------------------------ ladder
    def scan(self) -> bool:
        """One scan of the ladder; True when it changed anything but the scan counter."""
        with self._lock:
            m = self.mem
            before = m[Y_BASE : Y_BASE + N_Y] + m[R_BASE : R_BASE + N_R] + m[S_BASE + 2 : S_BASE + N_S]
            if self.card is not None:
                do = self.card.read_do()
                for k in range(4):
                    m[X_BASE + k] = (do >> (8 * k)) & 0xFF
            sx, sb, wx = m[STROBE_X], m[STROBE_BIT], m[WORD_X]
            strobe = (m[X_BASE + sx] >> sb) & 1 if sx < N_X and sb < 8 else 0
            if strobe != self._last_strobe and wx + 1 < N_X:
                word = (m[X_BASE + wx] & 0xFF) | ((m[X_BASE + wx + 1] & 0xFF) << 8)
                m[LATCHED] = word
                m[LATCH_COUNT] = (m[LATCH_COUNT] + 1) & 0xFFFF
                lsb = m[LSB_NM] / 1000.0
                for a, byte in enumerate((word >> 8, word & 0xFF)):
                    m[COMMAND + a] = int(round(decode_byte_um(byte, lsb))) & 0xFFFF
                m[Y_BASE] = (m[Y_BASE] & ~0x02) | (strobe << 1)
            self._last_strobe = strobe
            if m[RESET]:
                m[ALARM] = 0
                m[RESET] = 0
            limit = m[STEP_LIMIT]
            for a in range(2):
                if m[ALARM] & (1 << a):
                    continue
                cmd, applied = _signed(m[COMMAND + a]), _signed(m[APPLIED + a])
                if cmd != applied:
                    if abs(cmd - applied) > limit:
                        m[ALARM] |= 1 << a
                        m[ALARM_COUNT + a] = (m[ALARM_COUNT + a] + 1) & 0xFFFF
                    else:
                        m[APPLIED + a] = cmd & 0xFFFF
            m[Y_BASE] = (m[Y_BASE] & ~0x01) | (1 if m[ALARM] else 0)
            self.scans += 1
            m[SCAN_LO], m[SCAN_HI] = self.scans & 0xFFFF, (self.scans >> 16) & 0xFFFF
            after = m[Y_BASE : Y_BASE + N_Y] + m[R_BASE : R_BASE + N_R] + m[S_BASE + 2 : S_BASE + N_S]
            changed = after != before
            self._quiet = not changed
            return changed

    def start_at(self, t_s: float) -> None:
        self.next_scan_s = self.t_s = self._t0_s = t_s
        self._k = 0

    def _due_s(self, k: int) -> float:
        return self._t0_s + k * self.scan_s

    def advance_to(self, t_s: float) -> None:
        """Run every scan due up to `t_s` (simulated time); scan k is due at start + k·scan_s.

        Once a scan changes nothing and no card is wired, later scans cannot change
        anything either until a register is written (inputs only change between calls,
        through `write_registers`), so they are counted without being run: a day of
        replay costs a few scans per write.
        """
        k_last = last_due(self._t0_s, self.scan_s, t_s)
        while self._k <= k_last:
            if self._quiet and self.card is None:
                with self._lock:
                    self.scans += k_last - self._k + 1
                    self.mem[SCAN_LO] = self.scans & 0xFFFF
                    self.mem[SCAN_HI] = (self.scans >> 16) & 0xFFFF
                self._k = k_last + 1
                break
            self.scan()
            self._k += 1
        self.next_scan_s = self._due_s(self._k)
        self.t_s = t_s

    # ------------------------------------------------------------- convenience
    def applied_um(self) -> list[float]:
        with self._lock:
            return [float(_signed(self.mem[APPLIED + a])) for a in range(2)]

    def alarms(self) -> int:
        with self._lock:
            return self.mem[ALARM]
