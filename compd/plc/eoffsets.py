"""LinuxCNC's external offsets as a register map, and a device of the software PLC that emulates them.

The map is the one compd's linuxcnc sink reads and writes.

compd drives LinuxCNC through HAL pins (compd.sinks.hal_link), but its sinks speak registers
through one link interface (compd.io.modbus_link, compd.plc.link). So the pins are shown
as registers, per axis a block of `BLOCK`:

  COUNTS  (2, s32, high word first)  the counts compd's `eoffset-counts` pin carries       read/write
  ENABLE  (1)                        compd's `eoffset-enable` pin                          read/write
                                     (a write of its own: a link's queue merges writes to one address)
  APPLIED (2, float32 µm)            `axis.L.eoffset`: the offset LinuxCNC applies          read
  FLAGS   (1)                        NETTED, ON (motion enabled), HOMED (all joints), LIMITED read

LinuxCNC counts like a jog wheel (measured, docs/linuxcnc.md): while the offset is enabled and
the machine is on, the applied offset moves by Δcounts × the scale in effect; counts that move
while it is disabled move the baseline instead, and nothing moves. `Eoffsets` is that rule
in this process (replay, tests), the offset applied at once (LinuxCNC blends it at the axis's
OFFSET_AV_RATIO share of its velocity: fast against compd's steps).
"""

from __future__ import annotations

from compd.plc.link import VirtualDevice
from compd.plc.siemens_nc import f32_regs

BLOCK = 8  # registers per axis
COUNTS, ENABLE, APPLIED, FLAGS = 0, 2, 3, 5
NETTED, ON, HOMED, LIMITED = 1, 2, 4, 8  # FLAGS bits


def s32_regs(v: int) -> list[int]:
    """A signed 32-bit value as two registers, high word first."""
    u = int(v) & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def regs_s32(hi: int, lo: int) -> int:
    """The signed 32-bit value two registers hold (high word first)."""
    u = ((int(hi) & 0xFFFF) << 16) | (int(lo) & 0xFFFF)
    return u - (1 << 32) if u & 0x80000000 else u


S32_MIN, S32_MAX = -(1 << 31), (1 << 31) - 1


class Eoffsets(VirtualDevice):
    """LinuxCNC's external offsets of `n` axes in this process: its register of counts × `count_um`."""

    def __init__(self, n: int, count_um: float, *, on: bool = True, homed: bool = True) -> None:
        self.n = n
        self.count_um = count_um
        self.register_count = BLOCK * n
        self.on, self.homed = on, homed
        self.counts = [0] * n  # the counts pin (compd's)
        self.enable = [0] * n
        self.register = [0] * n  # LinuxCNC's internal register: the counts that act, summed
        self.applied_um = [0.0] * n

    def read_registers(self, address: int, count: int) -> list[int] | None:
        if address < 0 or count < 0 or address + count > self.register_count:
            return None
        regs: list[int] = []
        for i in range(self.n):
            flags = NETTED | (ON if self.on else 0) | (HOMED if self.homed else 0)
            regs += [*s32_regs(self.counts[i]), self.enable[i], *f32_regs(self.applied_um[i]), flags, 0, 0]
        return regs[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> bool:
        """COUNTS of one axis (two registers), or its ENABLE (one): the register takes Δcounts while
        the offset is enabled and the machine on and homed, else nothing moves."""
        i, off = divmod(address, BLOCK)
        if not 0 <= i < self.n:
            return False
        if off == ENABLE and len(values) == 1 and values[0] in (0, 1):
            self.enable[i] = int(values[0])
            return True
        if off != COUNTS or len(values) != 2:
            return False
        counts = regs_s32(values[0], values[1])
        if self.enable[i] and self.on and self.homed:
            self.register[i] += counts - self.counts[i]
        self.counts[i] = counts
        self.applied_um[i] = self.register[i] * self.count_um
        return True

    def advance_to(self, t_s: float) -> None:
        """The offset is applied at once (nothing runs on time)."""

    def start_at(self, t_s: float) -> None:
        """Nothing runs on time."""
