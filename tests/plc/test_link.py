"""VirtualLink: a software PLC device behind the Modbus link's interface, on the sink's time."""

from __future__ import annotations

import inspect

from compd.io.device_time import LoopTime
from compd.io.modbus_link import ModbusLink
from compd.plc.fanuc_pmc import APPLIED, COMMAND, SCAN_LO, STEP_LIMIT, FanucPmc
from compd.plc.link import VirtualLink


def _link() -> tuple[VirtualLink, FanucPmc, LoopTime]:
    pmc = FanucPmc(scan_s=0.01, step_limit_um=10)
    t = LoopTime()
    t.set(5.0)
    link = VirtualLink(pmc, t, status=(400, 8), name="t")
    link.start()
    return link, pmc, t


def test_has_the_modbus_links_public_methods():
    def public_methods(cls: type) -> set[str]:
        return {n for n, v in inspect.getmembers(cls) if not n.startswith("_") and callable(v)}

    assert public_methods(ModbusLink) <= public_methods(VirtualLink)
    link, _, _ = _link()
    for attr in ("state", "status", "writes", "errors", "bad_replies", "last_error", "write_hist", "latency_hist"):
        assert hasattr(link, attr), attr


def test_writes_land_at_once_and_the_device_runs_on_the_sinks_time():
    link, pmc, t = _link()
    assert link.state == "up" and pmc.t_s == 5.0  # the device's clock starts at the sink's time
    link.submit(COMMAND, [7, (-4) & 0xFFFF])
    assert not link.pending() and link.writes == 1
    assert pmc.read_registers(COMMAND, 2) == [7, 0xFFFC]
    assert link.read_now(APPLIED, 2) == [0, 0]  # no scan yet: the sink's time has not moved
    t.wait(0.025)  # device time passes: the next access runs the scans due
    assert link.read_now(APPLIED, 2) == [7, 0xFFFC]
    scans = pmc.scans
    t.set(6.0)
    assert link.flush()  # brings the device's clock up to the sink's time: 5.03 .. 6.00, every 10 ms
    assert pmc.t_s == 6.0 and abs(pmc.scans - (scans + 98)) <= 1
    assert link.status is not None and link.status[0] == pmc.read_registers(SCAN_LO, 1)[0]


def test_time_never_runs_backwards_and_refused_writes_are_errors():
    link, pmc, t = _link()
    t.wait(1.0)
    t.set(5.5)  # an earlier loop time than the wait reached
    assert t.now_s == 6.0
    link.submit(STEP_LIMIT - 50, [1])  # between the PMC's areas: not in its map
    assert link.errors == 1 and link.writes == 0 and "250+1" in (link.last_error or "")
    assert link.get_status()["errors"] == 1
    link.stop()
    assert link.state == "closed"
