"""The sinks' Modbus link against a raw-socket peer (not pymodbus): a read-back of the wrong
shape is a link error, never the device's status or applied value."""

from __future__ import annotations

import time

import pytest

from compd.sinks.modbus_link import ModbusLink
from tests.sources.rawmodbus import RawModbusServer

TABLE = [7, 0, 0, 0, 0xFFFB, 3, 0, 0]  # scan lo/hi, alarm, reset, applied 1 (−5), applied 2, alarm counts


def _until(pred, timeout_s: float = 10.0) -> bool:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.mark.parametrize(("mode", "opts"), [("extra", {}), ("fewer", {}), ("wrong_function", {}),
                                            ("wrong_function", {"function": 0x06}), ("trailing", {})])
def test_malformed_read_back_is_a_link_error(mode: str, opts: dict) -> None:
    with RawModbusServer(TABLE) as srv:
        srv.set(mode, **opts)
        link = ModbusLink("127.0.0.1", srv.port, status=(0, 8), status_period_s=0.01, name="t")
        link.start()
        try:
            assert _until(lambda: link.bad_replies >= 3)
            assert link.status is None  # never taken as the device's status
            assert link.read_now(0, 8) is None
            st = link.get_status()
            assert st["bad_replies"] >= 3 and st["last_error"].startswith("malformed reply to registers 0+8")
            srv.set("none")
            assert _until(lambda: link.status is not None)
            assert link.status == TABLE
            assert link.read_now(4, 2) == [0xFFFB, 3]
        finally:
            link.stop()
