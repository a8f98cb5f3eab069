"""The cycle's side of the service: a snapshot a section a cycle, each only in a cycle that leaves room for it, events and rows as
they come, probes from the service stamped by the cycle; and the pages a fork shares copied before the first
cycle."""

from __future__ import annotations

import math
import os
import time

import numpy as np

from compd.adapt import Probe
from compd.app import App
from compd.config import load_config
from compd.realtime import unshare_pages
from tests.service_helpers import sim_config


def _app(tmp_path):  # noqa: ANN001, ANN202
    return App(load_config(sim_config(tmp_path, "adapt: {}\nstatus: {path: st.json, period_s: 0.05}")))


def _take_snapshot(pub, room_s: float, most: int = 50) -> int:  # noqa: ANN001
    """Steps after cycles with `room_s` left until a snapshot is handed over; how many."""
    for n in range(1, most + 1):
        pub.after_cycle(room_s)
        if pub.outbox.pending():
            return n
    raise AssertionError(f"no snapshot after {most} cycles")


def test_a_due_snapshot_is_taken_a_section_a_cycle_each_waiting_for_room(tmp_path) -> None:
    app = _app(tmp_path)
    pub = app.service.publisher
    steps = _take_snapshot(pub, math.inf)
    # axes, signals, timing, model, the source, the adapter: six sections, then the hand-over
    assert steps == 7 and len(pub.step_cost_s) == 7 and all(0 < c < 1.0 for c in pub.step_cost_s)
    (msg,) = pub.outbox.take()
    assert msg[0] == "status" and set(msg[1]) >= {"axes", "signals", "loop", "model", "sources", "adapt"}
    assert msg[1]["sources"][0]["name"] and msg[1]["loop"]["cycles"] == app.loop.stats.cycles
    pub.after_cycle(math.inf)  # not due again before status.period_s has passed
    assert not pub.outbox.pending()
    time.sleep(0.06)
    pub.step_cost_s[:] = [400e-6] * 7
    pub.after_cycle(0.5e-3)  # 0.5 ms left: 1.5 × 0.4 ms + 0.1 ms does not fit
    assert pub.snapshots_waited == 1 and pub._step == 0 and pub.step_cost_s[0] < 400e-6  # shrinks waiting
    assert _take_snapshot(pub, 1.0e-3) == 7  # each step fits in 1 ms
    (msg,) = pub.outbox.take()
    assert msg[1]["publisher"]["snapshots_waited"] == 1 and pub.snapshots == 2


def test_events_rows_and_state_go_as_they_come_and_probes_come_back_stamped(tmp_path) -> None:
    app = _app(tmp_path)
    pub, loop = app.service.publisher, app.loop
    pub._next_status_s = math.inf  # no snapshots here
    loop.guard.events.append((12.0, "T_xi", "bad", "stale"))
    pub.row((1.0, 2.0))
    pub.model_state({"t0_c": 20.0})
    pub.after_cycle(0.0)  # no room at all: events still go
    msgs = pub.outbox.take()
    assert msgs == [("row", (1.0, 2.0)), ("model_state", {"t0_c": 20.0}), ("events", [(12.0, "T_xi", "bad", "stale", None)])]
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


def test_a_status_that_cannot_be_built_is_dropped_and_logged_once_the_cycle_goes_on(tmp_path, caplog) -> None:  # noqa: ANN001
    """A bug in a source's status (a key missing, say) must never stop compensation: the snapshot
    is dropped, the failure logged once, the next snapshot tried a period later."""
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
    for _ in range(3):
        for _ in range(20):
            pub.after_cycle(math.inf)
        pub._next_status_s = 0.0  # due again at once
    assert pub.status_failures == 3 and not pub.outbox.pending()
    lines = [r for r in caplog.records if getattr(r, "event", None) == "status_error"]
    assert len(lines) == 1 and "KeyError" in lines[0].reason
    broken["on"] = False
    assert _take_snapshot(pub, math.inf) > 0  # and snapshots come again once it can be built
