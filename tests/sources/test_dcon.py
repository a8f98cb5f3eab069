"""DCON source against the hil_sim ADAM-4015-style module over a socat pseudo-terminal pair."""

from __future__ import annotations

import pytest

from compd.sources.dcon import DconConfig, DconSource, dcon_checksum, parse_reply
from hil_sim.devices.dcon import DconModule
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.ptypair import PtyPair
from tests.sources.helpers import Harness

NAMES = ["T1", "T2", "T3"]
TEMPS = [25.3, 24.9, -3.2]


def test_checksum_and_parse():
    assert dcon_checksum(b"#01") == b"84"  # 0x23 + 0x30 + 0x31 = 0x84
    assert parse_reply(b">+025.30+024.90\r", 1, False) == [b"+025.30", b"+024.90"]
    body = b">+025.30-0000"
    assert parse_reply(body + dcon_checksum(body) + b"\r", 1, True) == [b"+025.30", b"-0000"]
    for bad, msg in [
        (b"", "timeout"),
        (b"?01\r", "rejected"),
        (b">+02x.30\r", "garbled"),
        (b"*+025.30\r", "'>'"),
        (b"!+025.30\r", "another address"),
    ]:
        with pytest.raises(ValueError, match=msg):
            parse_reply(bad, 1, False)
    with pytest.raises(ValueError, match="checksum"):
        parse_reply(b">+025.3000\r", 1, True)


@pytest.mark.parametrize("use_checksum", [False, True])
def test_values_and_faults_over_pty(tmp_path, use_checksum):
    tx = Pt100Transmitter(NAMES, TEMPS)
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), DconModule(tx, str(a), address=0x1A, baudrate=115200, use_checksum=use_checksum) as mod:
        cfg = DconConfig.model_validate(
            {
                "kind": "dcon",
                "name": "adam",
                "serial_port": str(b),
                "baudrate": 115200,
                "address": 0x1A,
                "checksum": use_checksum,
                "channels": NAMES,
                "poll_period_s": 0.01,
                "timeout_s": 0.5,
            }
        )
        with Harness(DconSource(cfg)) as h:
            s = h.sample_good()
            assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS]

            tx.set_fault("T1", "burnout")
            tx.set("T2", 400.0)  # over the module's range
            tx.set("T3", -80.0)  # under it
            s = h.sample()
            assert [s[n][1] for n in NAMES] == ["BURNOUT", "OUT_OF_RANGE", "OUT_OF_RANGE"]
            tx.set_fault("T1", "none")
            tx.set_all(TEMPS)

            for fault in ("no_answer", "garbage", "crc_error", "slow", "invalid"):
                mod.set_fault(fault, slow_s=1.5)  # later than the timeout, even on a busy machine
                s = h.sample(polls=2)
                assert {q for _, q in s.values()} == {"COMMS_LOST"}, fault
                mod.set_fault("none")
                s = h.sample_good()
                assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS], fault
            assert h.source.get_status()["comm_errors"] >= 5


def test_skipped_channel_and_stale(tmp_path):
    tx = Pt100Transmitter(NAMES, TEMPS)
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), DconModule(tx, str(a), baudrate=115200) as mod:
        cfg = DconConfig.model_validate(
            {
                "kind": "dcon",
                "name": "adam",
                "serial_port": str(b),
                "baudrate": 115200,
                "channels": ["T1", None, "T3"],
                "poll_period_s": 0.01,
                "timeout_s": 5.0,
                "stale_after_s": 1.0,
            }
        )
        with Harness(DconSource(cfg)) as h:
            s = h.sample_good()
            assert s == {"T1": (pytest.approx(25.3), "GOOD"), "T3": (pytest.approx(-3.2), "GOOD")}
            mod.set_fault("slow", slow_s=2.5)  # answered within the timeout, but late
            assert h.sample(polls=2)["T1"][1] == "STALE"


def test_parse_reply_shape():
    assert parse_reply(b">+025.30+024.90\r", 1, False, fields=2) == [b"+025.30", b"+024.90"]
    for bad, msg in [
        (b">+025.30+024.90+001.00\r", "3 values, 2 channels"),  # more values than the module has
        (b">+025.30\r", "1 values, 2 channels"),
        (b"?02\r", "another address"),
        (b"!01+025.30+024.90\r", "another command"),
        (b"!02\r", "another address"),
    ]:
        with pytest.raises(ValueError, match=msg):
            parse_reply(bad, 1, False, fields=2)


class _Mangled(DconModule):
    """The hil_sim module with its reply rewritten by `mangle` (checksum recomputed)."""

    mangle = None

    def reply(self, command: bytes) -> bytes | None:
        out = super().reply(command)
        if out is None or self.mangle is None:
            return out
        body = out[:-3] if self.use_checksum else out[:-1]
        body = self.mangle(body)
        return body + (dcon_checksum(body) if self.use_checksum else b"") + b"\r"


@pytest.mark.parametrize("use_checksum", [False, True])
def test_wrong_shape_reply_is_comms_lost(tmp_path, use_checksum):
    tx = Pt100Transmitter(NAMES, TEMPS)
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    with PtyPair(a, b), _Mangled(tx, str(a), address=0x1A, baudrate=115200, use_checksum=use_checksum) as mod:
        cfg = DconConfig.model_validate(
            {
                "kind": "dcon",
                "name": "adam",
                "serial_port": str(b),
                "baudrate": 115200,
                "address": 0x1A,
                "checksum": use_checksum,
                "channels": NAMES,
                "poll_period_s": 0.01,
                "timeout_s": 0.5,
            }
        )
        with Harness(DconSource(cfg)) as h:
            assert [h.sample_good()[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS]
            cases = {
                "extra value": lambda r: r + b"+099.00",
                "missing value": lambda r: r[:-7],
                "other address": lambda r: b"?1B",
                "other command": lambda r: b"!1A" + r[1:],
            }
            for what, mangle in cases.items():
                mod.mangle = mangle
                before = h.source.get_status()["comm_errors"]
                s = h.sample(polls=2)
                assert {q for _, q in s.values()} == {"COMMS_LOST"}, what
                assert h.source.get_status()["comm_errors"] > before, what
                mod.mangle = None
                s = h.sample_good()
                assert [s[n] for n in NAMES] == [(pytest.approx(t), "GOOD") for t in TEMPS], what
