"""Modbus source against a raw-socket peer (not pymodbus) that answers with the wrong shape:
a bad reply is a comms fault for exactly the signals its request carries, never data."""

from __future__ import annotations

import logging

import pytest

from compd.sources.modbus import ModbusConfig, ModbusSource
from tests.sources.helpers import Harness
from tests.sources.rawmodbus import RawModbusServer

# two requests: registers 0+2 (A1, A2) and 10+2 (B1, B2)
TABLE = {0: 253, 1: 249, 10: 612, 11: 177}
GOOD = {"A1": 25.3, "A2": 24.9, "B1": 61.2, "B2": 17.7}
REQUEST = {"A": 0, "B": 10}

# misbehaviour → the source's counter that must count it
SHAPE = [
    ("extra", {}),
    ("fewer", {}),
    ("wrong_function", {}),  # 0x04 for 0x03
    ("wrong_function", {"function": 0x10}),
    ("wrong_function", {"function": 0x06}),
    ("bad_byte_count", {"byte_count_delta": -2}),  # byte count shorter than the data
    ("trailing", {}),  # byte count right, two more registers in the frame
]
TRANSPORT = [
    ("bad_byte_count", {}),  # byte count longer than the frame: pymodbus raises
    ("wrong_tid", {}),  # pymodbus skips the frame: a timeout
    ("wrong_unit", {}),
    ("truncated", {}),
    ("silence", {}),
]


def _cfg(port: int, **kw) -> ModbusConfig:  # noqa: ANN003
    base = {
        # a timeout a busy machine's late answer does not reach
        "kind": "modbus",
        "name": "raw",
        "port": port,
        "timeout_s": 0.5,
        "poll_period_s": 0.01,
        "reconnect_min_s": 0.02,
        "reconnect_max_s": 0.1,
        "channels": [{"name": n, "address": a} for n, a in (("A1", 0), ("A2", 1), ("B1", 10), ("B2", 11))],
    }
    base.update(kw)
    return ModbusConfig.model_validate(base)


def _all_good(h: Harness) -> None:
    s = h.sample_good()
    assert s == {n: (pytest.approx(v), "GOOD") for n, v in GOOD.items()}


def _bad_request(h: Harness, bad: str) -> None:
    """The signals of request `bad` are COMMS_LOST; the other request's keep their values."""
    s = h.sample(polls=3)
    for n, v in GOOD.items():
        if n.startswith(bad):
            assert s[n][1] == "COMMS_LOST", (n, s)
        else:
            assert s[n] == (pytest.approx(v), "GOOD"), (n, s)


def test_plan_is_two_requests() -> None:
    assert ModbusSource(_cfg(502)).requests == [(0, 2), (10, 2)]


@pytest.mark.parametrize("function", ["holding", "input"])
@pytest.mark.parametrize(
    ("mode", "opts"), SHAPE, ids=[f"{m}{o.get('function', '')}{o.get('byte_count_delta', '')}" for m, o in SHAPE]
)
def test_wrong_shape_is_comms_lost_for_its_request(
    mode: str, opts: dict, function: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="compd")
    with RawModbusServer(TABLE) as srv, Harness(ModbusSource(_cfg(srv.port, function=function))) as h:
        _all_good(h)
        for bad in ("A", "B"):
            srv.set(mode, address=REQUEST[bad], **opts)
            before = h.source.get_status()["malformed_replies"]
            _bad_request(h, bad)
            assert h.source.get_status()["malformed_replies"] > before
            st = h.source.get_status()
            assert st["malformed_replies"] == h.source.get_status()["malformed_replies"]
            assert st["last_error"].startswith(f"malformed reply to registers {REQUEST[bad]}+2")
            srv.set("none")
            _all_good(h)  # reads recover when the peer behaves again
        assert h.source.get_status()["comm_errors"] == 0 and h.source.get_status()["exception_replies"] == 0
    lines = [r for r in caplog.records if getattr(r, "event", None) == "modbus_bad_reply"]
    assert {r.request for r in lines} == {"0+2", "10+2"}
    assert len(lines) == 2  # one line per request and reason, not one per poll
    assert sum(getattr(r, "event", None) == "modbus_reply_ok" for r in caplog.records) == 2


@pytest.mark.parametrize(("mode", "opts"), TRANSPORT, ids=[m for m, _ in TRANSPORT])
def test_unmatched_or_broken_reply_is_comms_lost(mode: str, opts: dict) -> None:
    """pymodbus itself refuses these (a timeout or an exception): the request's signals and the
    ones after it in that poll are COMMS_LOST; the ones read before it stay good."""
    with RawModbusServer(TABLE) as srv, Harness(ModbusSource(_cfg(srv.port))) as h:
        _all_good(h)
        srv.set(mode, address=REQUEST["B"], **opts)
        before = h.source.get_status()["comm_errors"]
        _bad_request(h, "B")
        assert h.source.get_status()["comm_errors"] > before
        srv.set("none")
        _all_good(h)


def test_extra_registers_never_fill_another_requests_slots() -> None:
    """Request A's reply carries ten registers more, reaching into B's registers 10 and 11,
    while B's own read fails: B's signals are COMMS_LOST, not A's spill-over."""
    with RawModbusServer(TABLE) as srv, Harness(ModbusSource(_cfg(srv.port))) as h:
        _all_good(h)
        srv.set("extra", address=0, extra=10)
        srv.set("exception", address=10)
        s = h.sample(polls=3)
        assert {n: q for n, (_, q) in s.items()} == dict.fromkeys(GOOD, "COMMS_LOST")
        srv.set("none")
        _all_good(h)


def test_exception_reply_counts_as_exception() -> None:
    with RawModbusServer(TABLE) as srv, Harness(ModbusSource(_cfg(srv.port))) as h:
        _all_good(h)
        srv.set("exception", address=0)
        _bad_request(h, "A")
        assert h.source.get_status()["exception_replies"] > 0 and h.source.get_status()["malformed_replies"] == 0
        srv.set("none")
        _all_good(h)


@pytest.mark.parametrize(
    ("mode", "opts"),
    [("extra", {"extra": 10}), ("wrong_function", {}), ("fewer", {})],
    ids=["extra", "wrong_function", "fewer"],
)
def test_rtu_wrong_shape_is_comms_lost_for_its_request(tmp_path, mode: str, opts: dict) -> None:  # noqa: ANN001
    """The same over Modbus RTU: a raw peer on a socat pty answers with the wrong shape."""
    from hil_sim.devices.ptypair import PtyPair
    from tests.sources.rawmodbus import RawRtuPeer

    a, b = tmp_path / "ttyPeer", tmp_path / "ttyCompd"
    with PtyPair(a, b), RawRtuPeer(TABLE, str(a)) as peer:
        cfg = _cfg(0 + 1, transport="rtu", serial_port=str(b), baudrate=115200, timeout_s=0.2)
        with Harness(ModbusSource(cfg)) as h:
            _all_good(h)
            peer.set(mode, address=0, **opts)
            _bad_request(h, "A")
            assert h.source.get_status()["malformed_replies"] > 0
            peer.set("none")
            _all_good(h)
