"""The software PLC's PCI-1756 card: DO latch, reset, DI, byte order, bounds."""

from __future__ import annotations

import pytest

from compd.plc.pci1756 import Pci1756Card


def test_card_latches_and_resets() -> None:
    card = Pci1756Card()
    card.write_do_word(0, 0xC543)
    assert card.read_do_byte(0) == 0x43 and card.read_do_byte(1) == 0xC5  # low byte first
    assert card.read_do_word(0) == 0xC543  # latched until written again
    card.write_do_bit(31, True)
    assert card.read_do() == 0x8000C543
    card.reset()
    assert card.read_do() == 0
    card.set_di(0x01020304)
    assert card.read_di_byte(0) == 0x04 and card.read_di_byte(3) == 0x01
    with pytest.raises(ValueError):
        card.write_do_word(3, 1)
