"""CAN source against the hil_sim CAN PT100 transmitter on python-can's virtual bus."""

from __future__ import annotations

import time

import pytest

from compd.sources.can import CanConfig, CanSource
from hil_sim.devices.can_pt100 import CanChannel, CanPt100
from hil_sim.devices.pt100 import Pt100Transmitter
from tests.sources.helpers import Harness

NAMES = ["T1", "T2", "T3"]
TEMPS = [25.3, -3.2, 61.7]


def _sample(h: Harness, wait_s: float) -> dict[str, tuple[float, str]]:
    time.sleep(wait_s)
    return h.sample()


def test_values_and_faults_on_virtual_bus():
    tx = Pt100Transmitter(NAMES, TEMPS)
    layout = [CanChannel("T1", 0x181, 0), CanChannel("T2", 0x181, 2), CanChannel("T3", 0x182, 4, byte_order="big")]
    sigs = [
        {"name": "T1", "id": 0x181, "offset": 0},
        {"name": "T2", "id": 0x181, "offset": 2},
        {"name": "T3", "id": 0x182, "offset": 4, "byte_order": "big"},
    ]
    cfg = CanConfig.model_validate(
        {"kind": "can", "name": "can", "interface": "virtual", "channel": "t-can-1",
         "timeout_s": 0.25, "stale_after_s": 0.06, "signals": sigs}
    )
    with CanPt100(tx, layout, interface="virtual", channel="t-can-1", period_s=0.01) as dev, Harness(CanSource(cfg)) as h:
        s = _sample(h, 0.1)
        assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS]

        tx.set_fault("T1", "burnout")
        tx.set("T3", 300.0)
        s = _sample(h, 0.05)
        assert (s["T1"][1], s["T2"][1], s["T3"][1]) == ("BURNOUT", "GOOD", "OUT_OF_RANGE")
        tx.set_fault("T1", "none")
        tx.set_all(TEMPS)

        expect = {"no_answer": "COMMS_LOST", "garbage": "COMMS_LOST", "crc_error": "COMMS_LOST"}
        for fault, quality in expect.items():
            dev.set_fault(fault)
            s = _sample(h, 0.4)
            assert {q for _, q in s.values()} == {quality}, fault
            dev.set_fault("none")
            s = _sample(h, 0.1)
            assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS], fault
        assert h.source.error_frames > 0 and h.source.bad_frames > 0

        dev.set_fault("slow", slow_s=0.12)  # frames come, but later than stale_after_s
        time.sleep(0.15)
        seen = set()
        for _ in range(30):
            seen |= {q for _, q in _sample(h, 0.01).values()}
        assert "STALE" in seen and "COMMS_LOST" not in seen


def test_signal_must_fit_in_frame():
    with pytest.raises(ValueError, match="8 data bytes"):
        CanConfig.model_validate({"kind": "can", "name": "c", "signals": [{"name": "a", "id": 1, "offset": 7, "size": 2}]})
