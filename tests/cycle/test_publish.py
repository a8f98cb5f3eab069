"""The cycle's side of the service: the status record every cycle, the devices' accounts once a period in a cycle
that leaves room for them, events and rows as they come, probes from the service stamped by the cycle; and the pages
a fork shares copied before the first cycle."""

from __future__ import annotations

import math
import os
import time

import numpy as np

from compd.config import load_config
from compd.core.probe import Probe
from compd.cycle.realtime import unshare_pages
from compd.daemon.app import App
from tests.service_helpers import sim_config


def _app(tmp_path):  # noqa: ANN001, ANN202
    return App(load_config(sim_config(tmp_path, "adapt: {}\nstatus: {path: st.json, period_s: 0.05}")))


def _take_devices(pub, room_s: float, most: int = 50) -> int:  # noqa: ANN001
    """Cycles with `room_s` left until the devices' accounts are handed over; how many."""
    for n in range(1, most + 1):
        pub.after_cycle(room_s)
        if pub.outbox.pending():
            return n
    raise AssertionError(f"no devices' accounts after {most} cycles")


def test_the_record_is_written_every_cycle_and_the_devices_once_a_period_when_there_is_room(tmp_path) -> None:
    app = _app(tmp_path)
    pub = app.service.publisher
    writes = pub.block.writes
    assert _take_devices(pub, math.inf) == 1  # due at once
    assert pub.block.writes == writes + 1  # the record: every cycle, room or not
    (msg,) = pub.outbox.take()
    assert msg[0] == "devices" and set(msg[1]) >= {"sources", "sink", "adapt", "faults", "processes", "model_state"}
    assert msg[1]["sources"][0]["name"] and msg[1]["sink"]["kind"] == "pci1756"
    pub.after_cycle(math.inf)  # not due again before status.period_s has passed
    assert not pub.outbox.pending() and pub.block.writes == writes + 2
    time.sleep(0.06)
    pub.devices_cost_s = 400e-6
    pub.after_cycle(0.5e-3)  # 0.5 ms left: 1.5 × 0.4 ms + 0.1 ms does not fit
    assert pub.devices_waited == 1 and pub.devices_cost_s < 400e-6 and not pub.outbox.pending()  # shrinks waiting
    assert pub.block.writes == writes + 3
    assert _take_devices(pub, 1.0e-3) == 1
    (msg,) = pub.outbox.take()
    assert msg[1]["publisher"]["devices_waited"] == 1 and pub.devices_sent == 2


def test_events_rows_and_state_go_as_they_come_and_probes_come_back_stamped(tmp_path) -> None:
    app = _app(tmp_path)
    pub, loop = app.service.publisher, app.loop
    pub._next_devices_s = math.inf  # no devices' accounts here
    loop.guard.events.append((12.0, "T_xi", "bad", "stale"))
    pub.row((1.0, 2.0))
    pub.model_state({"t0_c": 20.0})
    pub.after_cycle(0.0)  # no room at all: events still go
    msgs = pub.outbox.take()
    assert msgs == [
        ("row", (1.0, 2.0)),
        ("model_state", {"t0_c": 20.0}),
        ("events", [(12.0, "T_xi", "bad", "stale", None)]),
    ]
    pub.after_cycle(0.0)
    assert not pub.outbox.pending()  # each event once
    loop.now_s = 33.0
    app.service.inbox.put(Probe(t_s=math.nan, axis="z", error_um=1.5, source="cli#1"))
    pub.after_cycle(0.0)
    (probe,) = loop.adapter.inbox
    assert probe.t_s == 33.0 and probe.error_um == 1.5


def test_the_pages_a_fork_shares_are_copied_once_and_nothing_else_is_allocated() -> None:
    data = np.ones(4_000_000)  # 32 MB written before the fork: shared with the child afterwards
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(w)
        os.read(r, 1)  # until the parent is done
        os._exit(0)
    os.close(r)
    try:
        copied = unshare_pages()
        assert copied >= data.nbytes // 1024  # at least the array's pages
        assert unshare_pages() == 0  # nothing is shared any more
        assert data.sum() == 4_000_000.0
    finally:
        os.close(w)
        os.waitpid(pid, 0)


def test_devices_that_cannot_be_described_are_dropped_and_logged_once_the_cycle_goes_on(tmp_path, caplog) -> None:  # noqa: ANN001
    """A bug in a source's status (a key missing, say) must never stop compensation: the devices'
    accounts are dropped, the failure logged once, tried again a period later; the record goes on."""
    import logging

    app = _app(tmp_path)
    pub = app.service.publisher
    src = app.loop.sources[0]
    broken = {"on": True}
    real = src.get_status

    def get_status():  # noqa: ANN202
        if broken["on"]:
            raise KeyError("client_connects")
        return real()

    src.get_status = get_status
    caplog.set_level(logging.INFO, logger="compd.service")
    writes = pub.block.writes
    for _ in range(3):
        for _ in range(20):
            pub.after_cycle(math.inf)
        pub._next_devices_s = 0.0  # due again at once
    assert pub.status_failures == 3 and not pub.outbox.pending() and pub.block.writes == writes + 60
    lines = [r for r in caplog.records if getattr(r, "event", None) == "status_error"]
    assert len(lines) == 1 and "KeyError" in lines[0].reason
    broken["on"] = False
    assert _take_devices(pub, math.inf) == 1  # and they come again once they can be taken
