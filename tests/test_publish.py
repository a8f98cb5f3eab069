"""The cycle's side of the service: a snapshot only in a cycle that leaves room for it, events and rows as
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


def test_a_due_snapshot_waits_for_a_cycle_with_room_for_it(tmp_path) -> None:
    app = _app(tmp_path)
    pub = app.service.publisher
    pub.snapshot_cost_s = 400e-6
    pub.after_cycle(0.5e-3)  # 0.5 ms left: 1.5 × 0.4 ms + 0.1 ms does not fit
    assert pub.snapshots == 0 and pub.snapshots_waited == 1 and not pub.outbox.pending()
    pub.after_cycle(1.0e-3)
    (msg,) = pub.outbox.take()
    assert msg[0] == "status" and pub.snapshots == 1 and msg[1]["publisher"]["snapshots_waited"] == 1
    assert 0 < pub.snapshot_cost_s < 1.0  # measured now
    pub.after_cycle(math.inf)  # not due again before status.period_s has passed
    assert not pub.outbox.pending()
    time.sleep(0.06)
    pub.after_cycle(math.inf)
    assert [m[0] for m in pub.outbox.take()] == ["status"]


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
