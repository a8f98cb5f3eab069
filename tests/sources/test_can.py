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
        {
            "kind": "can",
            "name": "can",
            "interface": "virtual",
            "channel": "t-can-1",
            "timeout_s": 0.25,
            "stale_after_s": 0.06,
            "signals": sigs,
        }
    )
    with (
        CanPt100(tx, layout, interface="virtual", channel="t-can-1", period_s=0.01) as dev,
        Harness(CanSource(cfg)) as h,
    ):
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
        assert h.source.get_status()["error_frames"] > 0 and h.source.get_status()["bad_frames"] > 0

        dev.set_fault("slow", slow_s=0.12)  # frames come, but later than stale_after_s
        time.sleep(0.15)
        seen = set()
        for _ in range(30):
            seen |= {q for _, q in _sample(h, 0.01).values()}
        assert "STALE" in seen and "COMMS_LOST" not in seen


def test_signal_must_fit_in_frame():
    with pytest.raises(ValueError, match="8 data bytes"):
        CanConfig.model_validate(
            {"kind": "can", "name": "c", "signals": [{"name": "a", "id": 1, "offset": 7, "size": 2}]}
        )


def _wait(h: Harness, pred, timeout_s: float = 10.0) -> dict[str, tuple[float, str]]:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while True:
        s = h.sample()
        if pred(s) or time.monotonic() > deadline:
            return s
        time.sleep(0.01)


def test_short_dlc_is_comms_lost_for_the_ids_signals():
    """A frame whose DLC does not cover every signal on its id is not data, even when the
    bytes past the DLC are there (padding); the other id's signal stays good."""
    import can

    sigs = [
        {"name": "A1", "id": 0x181, "offset": 0},
        {"name": "A2", "id": 0x181, "offset": 2},
        {"name": "B1", "id": 0x182, "offset": 0},
    ]
    chan = f"t-can-dlc-{time.monotonic_ns()}"
    cfg = CanConfig.model_validate(
        {"kind": "can", "name": "can", "interface": "virtual", "channel": chan, "timeout_s": 5.0, "signals": sigs}
    )
    good_a = bytes([253, 0, 249, 0])
    with can.Bus(interface="virtual", channel=chan) as bus, Harness(CanSource(cfg)) as h:

        def send(fid: int, data: bytes, dlc: int | None = None) -> None:
            bus.send(
                can.Message(
                    arbitration_id=fid,
                    data=data,
                    dlc=len(data) if dlc is None else dlc,
                    is_extended_id=False,
                    check=False,
                )
            )

        send(0x181, good_a)
        send(0x182, bytes([100, 0]))
        want = {
            "A1": (pytest.approx(25.3), "GOOD"),
            "A2": (pytest.approx(24.9), "GOOD"),
            "B1": (pytest.approx(10.0), "GOOD"),
        }
        assert _wait(h, lambda s: s == want) == want
        for what, data, dlc in [
            ("3 bytes", good_a[:3], None),
            ("DLC 2, 8 bytes of padding", good_a + bytes(4), 2),
            ("empty", b"", None),
        ]:
            bad = h.source.get_status()["bad_frames"]
            send(0x181, data, dlc)
            s = _wait(h, lambda s: s["A1"][1] != "GOOD")
            assert (s["A1"][1], s["A2"][1]) == ("COMMS_LOST", "COMMS_LOST"), what
            assert s["B1"] == (pytest.approx(10.0), "GOOD"), what
            assert h.source.get_status()["bad_frames"] == bad + 1 and "0x181" in h.source.get_status()["last_error"]
            send(0x181, good_a)
            assert _wait(h, lambda s: s == want) == want, what
        bus.send(can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=4, is_extended_id=False))
        send(0x182, bytes([101, 0]))  # after the RTR frame: once seen, the RTR frame was too
        s = _wait(h, lambda s: s["B1"][0] == pytest.approx(10.1))
        assert s["A1"] == (pytest.approx(25.3), "GOOD")  # a remote request is not a frame of data
