"""Siemens NC temperature compensation data (paper 001): the register map and the NC's IPO-cycle ramp.

ΔK = K0 + tanβ·(P − P0), with K0 = SD43900 TEMP_COMP_ABS_VALUE (mm), tanβ = SD43910
TEMP_COMP_SLOPE, P0 = SD43920 TEMP_COMP_REF_POSITION (mm). MD32750 TEMP_COMP_TYPE:
bit 0 enables the position-independent part K0, bit 1 the position-dependent part.
The NC never steps: per interpolation (IPO) cycle the applied ΔK moves toward the
target by at most MD32760 COMP_ADD_VELO_FACTOR × max axis velocity × IPO cycle.

Register map, 16 holding registers per axis at 16·axis (float32 as two registers,
high word first, IEEE 754 big-endian):
+0 K0 mm, +2 tanβ, +4 P0 mm, +6 MD32750 (uint16), +7 MD32760 (fraction of the max
velocity per IPO cycle), +9 axis position P mm (written by the plant or a test),
+11 applied ΔK mm (read only), +13 target ΔK mm (read only), +15 IPO counter (mod 65536).
The siemens sink writes this map, to the NC here in process or to an NC gateway over Modbus TCP.

Probe result, registers 1000–1007 whatever the number of axes (compd.plc.probe_block),
written by the NC's probing cycle (R parameters the gateway maps here; `publish_probe`
in the emulator) and only held by the NC: 1000 sequence (written first), 1001 axis index,
1002–1003 deviation nm int32, 1004–1005 position µm int32 (0x80000000 = none),
1006 σ nm (0 = not given), 1007 sequence (written last; a new result when it changes).
"""

from __future__ import annotations

import struct
import threading

from compd.plc.link import VirtualDevice, last_due
from compd.plc.probe_block import PROBE_COUNT, ProbeBlock

K0, SLOPE, P0, TYPE, VELO_FACTOR, POSITION, APPLIED, TARGET, IPO = 0, 2, 4, 6, 7, 9, 11, 13, 15
BLOCK = 16
READ_ONLY = (APPLIED, APPLIED + 1, TARGET, TARGET + 1, IPO)
_F32 = struct.Struct(">f")
PROBE_BASE = 1000  # above the axis blocks of up to 62 axes
MAX_AXES = PROBE_BASE // BLOCK


def f32_regs(v: float) -> list[int]:
    """float32 as two registers, high word first (IEEE 754 big-endian)."""
    b = struct.pack(">f", v)
    return [int.from_bytes(b[0:2], "big"), int.from_bytes(b[2:4], "big")]


def _f32(v: float) -> float:
    """`v` as a float32 holds it (what two registers store and give back)."""
    return _F32.unpack(_F32.pack(v))[0]


def regs_f32(hi: int, lo: int) -> float:
    """The float32 two registers hold (high word first)."""
    return struct.unpack(">f", hi.to_bytes(2, "big") + lo.to_bytes(2, "big"))[0]


class SiemensNc(VirtualDevice):
    """Per-axis setting data, machine data and the IPO-cycle rate limit."""

    def __init__(
        self,
        axes: int = 2,
        *,
        ipo_s: float = 0.004,
        max_velo_mm_min: float = 30000.0,
        velo_factor: float = 1e-5,
        comp_type: int = 1,
    ) -> None:
        if not 1 <= axes <= MAX_AXES:
            raise ValueError(f"siemens_nc: axes must be 1..{MAX_AXES}, got {axes}")
        self.n = axes
        self.ipo_s = ipo_s
        self.max_velo_mm_min = max_velo_mm_min
        self.register_count = PROBE_BASE + PROBE_COUNT  # the axis blocks, a gap, the probe block
        self.mem = [0] * (BLOCK * axes)
        self.probe = ProbeBlock()
        for a in range(axes):
            self._set(a, VELO_FACTOR, velo_factor)
            self.mem[BLOCK * a + TYPE] = comp_type
        self.t_s = 0.0
        self.next_ipo_s = 0.0
        # IPO cycle k is due at start + k·ipo_s: the same times however the sink's calls fall
        self._t0_s = 0.0
        self._k = 0
        self.cycles = 0
        self._lock = threading.Lock()

    def _get(self, a: int, off: int) -> float:
        return regs_f32(self.mem[BLOCK * a + off], self.mem[BLOCK * a + off + 1])

    def _set(self, a: int, off: int, v: float) -> None:
        self.mem[BLOCK * a + off : BLOCK * a + off + 2] = f32_regs(v)

    def _in_probe(self, address: int, count: int) -> bool:
        return address >= PROBE_BASE and address + count <= PROBE_BASE + PROBE_COUNT

    def read_registers(self, address: int, count: int) -> list[int] | None:
        if self._in_probe(address, count):
            with self._lock:
                return self.probe.regs[address - PROBE_BASE : address - PROBE_BASE + count]
        if address < 0 or address + count > len(self.mem):
            return None
        with self._lock:
            return self.mem[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> bool:
        if self._in_probe(address, len(values)):
            with self._lock:
                self.probe.regs[address - PROBE_BASE : address - PROBE_BASE + len(values)] = [
                    v & 0xFFFF for v in values
                ]
            return True
        if address < 0 or address + len(values) > len(self.mem):
            return False
        if any((address + k) % BLOCK in READ_ONLY for k in range(len(values))):
            return False
        with self._lock:
            self.mem[address : address + len(values)] = [v & 0xFFFF for v in values]
        return True

    def cap_mm(self, a: int) -> float:
        """Largest change of ΔK per IPO cycle (MD32760 × max velocity × IPO cycle), mm."""
        return self._get(a, VELO_FACTOR) * self.max_velo_mm_min / 60.0 * self.ipo_s

    def ipo(self) -> None:
        """One IPO cycle."""
        self._cycles(1)

    def _cycles(self, due: int) -> int:
        """Run IPO cycles (their inputs, K0, tanβ, P0, P, do not change in between) until every
        axis sits on its target, at least one and at most `due`; how many ran. Per axis the
        applied ΔK moves toward the target by at most the cap per cycle and is stored as a
        float32 each cycle, as the registers hold it; once on its target it stays there."""
        with self._lock:
            axes = []
            for a in range(self.n):
                target = self._target(a)
                axes.append((target, _f32(target), self._get(a, APPLIED), self.cap_mm(a)))
            pack, unpack = _F32.pack, _F32.unpack
            run = 1
            ramps = []
            for target, stored, applied, cap in axes:
                k = 0
                while k < due:  # the cycles this axis needs to reach its target (or all that are due)
                    d = target - applied
                    applied = unpack(pack(applied + (cap if d > cap else (-cap if d < -cap else d))))[0]
                    k += 1
                    if applied == stored:
                        break
                ramps.append((k, applied))
                run = max(run, k)
            for a, ((target, _, _, cap), (k, applied)) in enumerate(zip(axes, ramps, strict=True)):
                for _ in range(run - k):  # the cycles it runs after reaching its target (as a float32 rounds)
                    d = target - applied
                    applied = unpack(pack(applied + (cap if d > cap else (-cap if d < -cap else d))))[0]
                self._set(a, APPLIED, applied)
                self._set(a, TARGET, target)
                self.mem[BLOCK * a + IPO] = (self.mem[BLOCK * a + IPO] + run) & 0xFFFF
            self.cycles += run
            return run

    def start_at(self, t_s: float) -> None:
        self.next_ipo_s = self.t_s = self._t0_s = t_s
        self._k = 0

    def _target(self, a: int) -> float:
        """ΔK = K0 + tanβ·(P − P0) of axis `a` from its registers now, as the IPO cycle computes it."""
        typ = self.mem[BLOCK * a + TYPE]
        target = 0.0
        if typ & 1:
            target += self._get(a, K0)
        if typ & 2:
            target += self._get(a, SLOPE) * (self._get(a, POSITION) - self._get(a, P0))
        return target

    def settled(self) -> bool:
        """Every axis applies the target its registers give now and holds it there: IPO cycles
        change nothing until the next write."""
        with self._lock:
            return all(
                self._get(a, APPLIED) == _f32(t) == self._get(a, TARGET)
                for a, t in ((a, self._target(a)) for a in range(self.n))
            )

    def advance_to(self, t_s: float) -> None:
        """Run the IPO cycles due up to `t_s` (cycle k at start + k·ipo_s); once every axis
        sits on its target the rest are counted without being run (nothing can change
        between writes)."""
        due = last_due(self._t0_s, self.ipo_s, t_s) - self._k + 1
        if due > 0:
            run = self._cycles(due)
            if due > run:  # counted, not run: every axis's IPO counter too
                with self._lock:
                    self.cycles += due - run
                    for a in range(self.n):
                        self.mem[BLOCK * a + IPO] = (self.mem[BLOCK * a + IPO] + due - run) & 0xFFFF
            self._k += due
        self.next_ipo_s = self._t0_s + self._k * self.ipo_s
        self.t_s = t_s

    def applied_mm(self) -> list[float]:
        with self._lock:
            return [self._get(a, APPLIED) for a in range(self.n)]

    def publish_probe(
        self, axis: int, deviation_um: float, position_mm: float | None = None, sigma_um: float | None = None
    ) -> int:
        """The probing cycle ran: write its result (axis index 0-based, deviation µm measured
        with the correction in place, position mm or None, σ µm or None) into 1000–1007 at
        once, with the next sequence number, which it returns."""
        with self._lock:
            return self.probe.publish(axis, deviation_um, position_mm, sigma_um)

    def set_position(self, a: int, p_mm: float) -> None:
        with self._lock:
            self._set(a, POSITION, p_mm)
