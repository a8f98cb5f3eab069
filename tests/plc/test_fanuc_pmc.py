"""The PMC software PLC: strobe latch, decode, absolute shift, step-limit alarm, reset, scans."""

from __future__ import annotations

from compd.plc.fanuc_pmc import (
    ALARM,
    APPLIED,
    COMMAND,
    LATCH_COUNT,
    RESET,
    FanucPmc,
    decode_byte_um,
)
from compd.plc.pci1756 import Pci1756Card


def _strobe_word(pmc: FanucPmc, word: int, strobe: int) -> None:
    pmc.write_registers(0, [word & 0xFF, word >> 8, strobe])


def test_decode_byte():
    assert decode_byte_um(0xC5, 1.0) == 5.0
    assert decode_byte_um(0x43, 1.0) == -3.0
    assert decode_byte_um(0x85, 1.0) == 0.0  # enable off
    assert decode_byte_um(0xFF, 0.5) == 31.5


def test_latches_on_strobe_edge_only():
    pmc = FanucPmc()
    _strobe_word(pmc, 0xC543, 0)
    pmc.advance_to(0.1)
    assert pmc.applied_um() == [0.0, 0.0]  # no edge yet
    _strobe_word(pmc, 0xC543, 1)
    pmc.advance_to(0.2)
    assert pmc.applied_um() == [5.0, -3.0]
    assert pmc.read_registers(LATCH_COUNT, 1) == [1]
    _strobe_word(pmc, 0xC143, 1)  # word changes, strobe does not: ignored
    pmc.advance_to(0.3)
    assert pmc.applied_um() == [5.0, -3.0]
    _strobe_word(pmc, 0xC143, 0)  # falling edge latches too
    pmc.advance_to(0.4)
    assert pmc.applied_um() == [1.0, -3.0]


def test_step_limit_alarm_holds_until_reset():
    pmc = FanucPmc(step_limit_um=10)
    _strobe_word(pmc, 0xCC00, 1)  # +12 µm on axis 1: more than 10 in one change
    pmc.advance_to(0.05)
    assert pmc.alarms() == 0b01
    assert pmc.applied_um() == [0.0, 0.0]
    assert pmc.read_registers(100, 1)[0] & 1  # alarm lamp Y0.0
    _strobe_word(pmc, 0xC800, 0)  # +8 while alarmed: still held
    pmc.advance_to(0.1)
    assert pmc.applied_um() == [0.0, 0.0]
    pmc.write_registers(RESET, [1])
    pmc.advance_to(0.15)
    assert pmc.alarms() == 0 and pmc.applied_um() == [8.0, 0.0]
    assert pmc.read_registers(RESET, 1) == [0]


def test_shift_registers_written_directly():
    pmc = FanucPmc(step_limit_um=10)
    pmc.write_registers(COMMAND, [7, (-4) & 0xFFFF])
    pmc.advance_to(0.01)
    assert pmc.applied_um() == [7.0, -4.0]
    assert pmc.read_registers(APPLIED, 2) == [7, 0xFFFC]
    assert pmc.read_registers(ALARM, 1) == [0]


def test_scan_counter_follows_simulated_time():
    pmc = FanucPmc(scan_s=0.008)
    pmc.advance_to(86400.0)
    assert pmc.scans == int(86400.0 / 0.008) + 1
    lo, hi = pmc.read_registers(400, 2)
    assert lo | (hi << 16) == pmc.scans


def test_wired_to_pci1756_card():
    card = Pci1756Card()
    pmc = FanucPmc(card=card)
    card.write_do_word(0, 0xC543)
    card.write_do_bit(16, True)  # DO2.0 is the strobe (X2.0)
    pmc.advance_to(0.02)
    assert pmc.applied_um() == [5.0, -3.0]


def test_invalid_addresses_rejected():
    pmc = FanucPmc()
    assert pmc.read_registers(50, 1) is None
    assert not pmc.write_registers(15, [0, 0])  # runs past X15


def test_scans_fall_on_an_absolute_schedule_however_the_calls_fall():
    """Scan k is due at start + k·scan_s: run in one call or many, the PMC scans as often and
    applies the same; a write after quiet scans still gets its scan."""
    a, b = FanucPmc(scan_s=0.008), FanucPmc(scan_s=0.008)
    a.start_at(100.0)
    b.start_at(100.0)
    t = 100.0
    for _ in range(997):
        t += 0.0037
        a.advance_to(t)
    b.advance_to(t)
    assert a.scans == b.scans == int((t - 100.0) / 0.008) + 1
    for pmc in (a, b):
        _strobe_word(pmc, 0xC543, 1)
        pmc.advance_to(t + 0.008)
    assert a.applied_um() == b.applied_um() == [5.0, -3.0]
    assert a.mem == b.mem
