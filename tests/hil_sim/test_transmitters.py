"""The threaded PT100 transmitters (DCON, CAN) built from a hil_sim device section, as serve builds them."""

from __future__ import annotations

import pytest

from hil_sim.devices.can_pt100 import CanPt100
from hil_sim.devices.dcon import DconModule
from hil_sim.devices.pt100_modbus import from_config as modbus_from_config


def _can(**kw: object) -> dict[str, object]:
    chans = [
        {"name": "T1", "can_id": 0x181, "value_c": 25.3, "fault": "burnout"},
        {"name": "T2", "can_id": 0x181, "offset": 2, "value_c": 24.9},
    ]
    return {"interface": "virtual", "channel": "t-can-section", "channels": chans, **kw}


def _dcon(**kw: object) -> dict[str, object]:
    chans = [{"name": "T1", "value_c": 25.3, "fault": "burnout"}, {"name": "T2", "value_c": 24.9}]
    return {"serial_port": "/dev/null", "address": 1, "channels": chans, **kw}


def test_a_channel_fault_in_the_section_is_sent_by_every_kind() -> None:
    """`fault` on a channel is the sensor fault on the wire (it was dropped by DCON and CAN)."""
    tx, can_dev = CanPt100.from_config(_can())
    assert [s for s, _ in tx.readings()] == ["burnout", "ok"]
    (frame,) = can_dev.frames()
    assert bytes(frame.data) == (0x8000).to_bytes(2, "little") + (249).to_bytes(2, "little")

    tx, mod = DconModule.from_config(_dcon())
    assert mod.reply(b"#01") == b">-9999.9+024.90\r"

    tx, dev, _ = modbus_from_config({"port": 0, "channels": _dcon()["channels"]})
    assert dev.snapshot()[:2] == [0x8000, 249]


@pytest.mark.parametrize(("cls", "section", "fault"), [(CanPt100, _can, "crc_error"), (DconModule, _dcon, "invalid")])
def test_wire_fault_from_the_section_and_the_switch(cls, section, fault) -> None:  # noqa: ANN001
    _, dev = cls.from_config(section(wire_fault=fault))
    assert dev.fault == fault
    dev.set_fault("slow", slow_s=0.25)
    assert (dev.fault, dev.slow_s) == ("slow", 0.25)
    with pytest.raises(ValueError, match=r"unknown fault 'exception' \(known: none, no_answer"):
        dev.set_fault("exception")
    with pytest.raises(ValueError, match="unknown fault 'nope'"):
        cls.from_config(section(wire_fault="nope"))
