"""The probe-result block a CNC's probing cycle writes and the `probe` source reads: 8 registers.

One layout for every CNC (the FANUC PMC at registers 500–507, the Siemens NC at
1000–1007); 16-bit registers, 32-bit values high word first, two's complement:

| offset | meaning |
|---|---|
| +0 | sequence number, written first (the cycle starts writing result `seq`) |
| +1 | axis index (0-based: the `probe` source's `axes` in order) |
| +2, +3 | measured deviation, nm, int32 (with the correction in place) |
| +4, +5 | position where it was measured, µm (0.001 mm), int32; 0x80000000 = no position |
| +6 | σ of the measurement, nm, uint16; 0 = not given (compd's `adapt.sigma_um`) |
| +7 | sequence number, written last: a new result when it changes (mod 65536) |

A reader trusts a result only when +0 equals +7 (else the cycle is still writing it,
and the next poll sees it whole).
"""

from __future__ import annotations

from dataclasses import dataclass

PROBE_COUNT = 8
SEQ_BEGIN, AXIS, DEVIATION, POSITION, SIGMA, SEQ = 0, 1, 2, 4, 6, 7
NO_POSITION = 0x80000000


def _i32_regs(v: int) -> list[int]:
    u = v & 0xFFFFFFFF
    return [(u >> 16) & 0xFFFF, u & 0xFFFF]


def _regs_i32(hi: int, lo: int) -> int:
    u = ((hi & 0xFFFF) << 16) | (lo & 0xFFFF)
    return u - 0x100000000 if u & 0x80000000 else u


@dataclass(frozen=True)
class ProbeResult:
    """One result as the block holds it."""

    seq: int
    axis: int
    deviation_um: float
    position_mm: float | None
    sigma_um: float | None


def encode_result(
    seq: int, axis: int, deviation_um: float, position_mm: float | None = None, sigma_um: float | None = None
) -> list[int]:
    """The block's 8 registers for one result (deviation to 1 nm, position to 1 µm, σ to 1 nm)."""
    if not 0 <= axis <= 0xFFFF:
        raise ValueError(f"probe axis index {axis} is not 0..65535")
    dev_nm = int(round(deviation_um * 1000.0))
    if not -0x80000000 <= dev_nm <= 0x7FFFFFFF:
        raise ValueError(f"probe deviation {deviation_um} um does not fit the block")
    if position_mm is None:
        pos = NO_POSITION
    else:
        pos = int(round(position_mm * 1000.0))
        if not -0x7FFFFFFF <= pos <= 0x7FFFFFFF:
            raise ValueError(f"probe position {position_mm} mm does not fit the block")
    sig = 0 if sigma_um is None else int(round(sigma_um * 1000.0))
    if not 0 <= sig <= 0xFFFF:
        raise ValueError(f"probe sigma {sigma_um} um is not 0..65.535 um")
    s = seq & 0xFFFF
    return [s, axis, *_i32_regs(dev_nm), *_i32_regs(pos), sig, s]


def decode_result(regs: list[int] | tuple[int, ...]) -> ProbeResult | None:
    """The result the 8 registers hold, or None while it is being written (+0 ≠ +7).
    A list of another length is a ValueError (the caller checked the reply's shape)."""
    if len(regs) != PROBE_COUNT:
        raise ValueError(f"a probe block is {PROBE_COUNT} registers, got {len(regs)}")
    if regs[SEQ_BEGIN] != regs[SEQ]:
        return None
    pos_raw = ((regs[POSITION] & 0xFFFF) << 16) | (regs[POSITION + 1] & 0xFFFF)
    return ProbeResult(
        seq=regs[SEQ] & 0xFFFF,
        axis=regs[AXIS] & 0xFFFF,
        deviation_um=_regs_i32(regs[DEVIATION], regs[DEVIATION + 1]) / 1000.0,
        position_mm=None if pos_raw == NO_POSITION else _regs_i32(regs[POSITION], regs[POSITION + 1]) / 1000.0,
        sigma_um=regs[SIGMA] / 1000.0 if regs[SIGMA] else None,
    )


class ProbeBlock:
    """The block's memory in a software PLC device: `publish` writes a result whole (under
    the device's lock), the next sequence number; `regs` is the map's view of it."""

    def __init__(self) -> None:
        self.regs = [0] * PROBE_COUNT
        self.published = 0

    def publish(self, axis: int, deviation_um: float, position_mm: float | None, sigma_um: float | None) -> int:
        seq = (self.regs[SEQ] + 1) & 0xFFFF
        self.regs[:] = encode_result(seq, axis, deviation_um, position_mm, sigma_um)
        self.published += 1
        return seq
