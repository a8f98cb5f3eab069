"""The cycle's side of the service: what status, logs and metrics need from the loop, handed over between cycles.

The service work (status file, metrics, event log lines, the data log, model state,
the probe socket) runs beside the loop, in a process of its own on the wall clock
(compd/service.py). It never reads the pipeline's objects: the cycle's thread hands
it what it needs, as plain values in a `MessageRing` (compd/io/ring.py), so there is
never a second thread of Python in the cycle's interpreter and nothing the cycle
writes is read half-written.

After every cycle the loop calls `Publisher.after_cycle` with the time left before
the next deadline:

* the guard's new events and the adapter's new probe events (few, cheap), each
  sensor event with its source's last error as the cause;
* every `status.period_s` of wall time, a snapshot of the loop (compd/status.py),
  one section a cycle (`snapshot_steps`: axes, signals, timing, model, each source),
  then handed over whole; each step only when the time left holds it with room to
  spare (each step's cost is measured each time, and averaged): a snapshot does not
  make a cycle late, its next step waits for a cycle with room;
* probes that arrived for the adapter (`compd probe` through the service, a CNC's
  probe block through its source's worker) go into the adapter's inbox.

Model and adapter state and the data log's rows are put in the ring when the cycle
makes them (a few µs: pickling a tuple). A full ring drops the message and counts it
(the service is gone or far behind); the cycle never waits for room.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from compd.adapt import Probe
from compd.io.ring import MessageRing
from compd.io.supervisor import Supervised, Supervisor
from compd.io.worker import started_workers
from compd.metrics import LATENESS_BOUNDS_US
from compd.status import lateness_buckets, snapshot, snapshot_steps

log = logging.getLogger("compd.service")

ROOM_FACTOR = 1.5  # a snapshot's step is taken only when the time left is this many times its cost ...
ROOM_EXTRA_S = 100e-6  # ... plus this
COST_WEIGHT = 0.25  # a step's cost estimate: an average of its costs with this weight on the newest
WAIT_DECAY = 0.99  # ... and it shrinks by this for every cycle the step waits for room
FIRST_COST_S = 100e-6  # a step's estimate before it was first measured


class Tail:
    """The items a list or deque gained since the last call (it may be trimmed at the
    front meanwhile): found by the identity of the last item seen, O(1) when none."""

    def __init__(self, items: Callable[[], Any]) -> None:
        self._items = items
        self._last: Any = None

    def new(self) -> list[Any]:
        items = self._items()
        if not items or items[-1] is self._last:
            return []
        copy = list(items)
        start = 0
        if self._last is not None:
            for i in range(len(copy) - 1, -1, -1):
                if copy[i] is self._last:
                    start = i + 1
                    break
        self._last = copy[-1]
        return copy[start:]


def sensor_cause(sources: list[Any], signal: str) -> str | None:
    """`source NAME: its last error` of the source that publishes `signal`, if it has one."""
    for src in sources:
        try:
            if signal in src.signal_names():
                err = src.get_status().get("last_error")
                return f"source {src.name}: {err}" if err else None
        except Exception:  # a source's status must not stop the events
            return None
    return None


def with_causes(events: list[tuple[float, str, str, str]], sources: list[Any]) -> list[tuple[float, str, str, str, str | None]]:
    """The guard's events as handed to the service: each sensor event that is a lost link, no
    data or staleness with its source's last error as the cause (`sensor_cause`)."""
    out = []
    for t, subject, event, reason in events:
        cause = None
        if event == "bad" and reason in ("comms_lost", "no_data", "stale"):
            cause = sensor_cause(sources, subject)
        out.append((float(t), subject, event, reason, cause))
    return out


class Publisher:
    """Feeds the service from the cycle's thread (see the module); one per pipeline."""

    def __init__(
        self,
        loop: Any,
        outbox: MessageRing,
        inbox: MessageRing,
        *,
        status_period_s: float,
        status_extra: Callable[[], dict[str, Any]],
        observe: bool,
        probe_rings: list[MessageRing] = (),  # type: ignore[assignment]
    ) -> None:
        self.loop = loop
        self.outbox = outbox
        self.inbox = inbox
        self.status_period_s = status_period_s
        self.status_extra = status_extra
        self.observe = observe
        self.state = "starting"
        self.probe_rings = [inbox, *probe_rings]
        self._guard_events = Tail(lambda: loop.guard.events)
        self._probe_events = Tail(lambda: loop.adapter.events) if loop.adapter is not None else None
        self._next_status_s = -math.inf  # wall (monotonic) time of the next snapshot
        self._steps: Any = None  # the snapshot being taken (snapshot_steps), or None
        self._step = 0  # its next step's index; the last one hands the snapshot over
        self._snap: dict[str, Any] | None = None  # the snapshot taken, not yet handed over
        self.step_cost_s: list[float] = []  # per step, the estimate it needs room for
        self.snapshots = 0
        self.snapshots_waited = 0  # cycles a snapshot's due step waited for room
        self.rows_dropped = 0  # data-log rows the ring had no room for
        self.status_failures = 0  # snapshots dropped because one of their steps raised
        self._failures_logged: set[str] = set()
        # the I/O workers' processes and the service's (compd/io/supervisor.py), watched between cycles
        self.supervised: list[Supervised] = []
        self.supervisor = Supervisor(workers=lambda: [*started_workers(), *self.supervised])

    # ------------------------------------------------------------ the cycle's thread
    def after_cycle(self, room_s: float) -> None:
        """After a cycle, with `room_s` before the next deadline (inf: no real-time schedule)."""
        self.supervisor.check()
        for ring in self.probe_rings:
            if ring.pending():
                self._take_probes(ring)
        events = self._guard_events.new()
        if events:
            self._put_events(events)
        if self._probe_events is not None:
            pe = self._probe_events.new()
            if pe:
                self.outbox.put(("probe_events", pe))
        if self._steps is None and self._snap is None:
            if time.monotonic() < self._next_status_s:
                return
            self._steps = snapshot_steps(self.loop, state=self.state, observe=self.observe, extra=self.status_extra())
            self._step = 0
        costs, i = self.step_cost_s, self._step
        if i == len(costs):
            costs.append(FIRST_COST_S)
        if room_s < ROOM_FACTOR * costs[i] + ROOM_EXTRA_S:
            self.snapshots_waited += 1
            costs[i] *= WAIT_DECAY  # one step the host slowed down must not hold the next ones back for good
            return
        t0 = time.perf_counter()
        if self._snap is not None:  # the last step: hand it over
            self._hand_over(self._snap)
            self._snap = None
            self._next_status_s = time.monotonic() + self.status_period_s
        else:
            try:
                next(self._steps)
            except StopIteration as done:
                self._snap, self._steps = done.value, None
            except Exception as e:  # a status that cannot be built never stops the cycle: this one is dropped
                self._status_failed(e)
                return
        costs[i] = (1.0 - COST_WEIGHT) * costs[i] + COST_WEIGHT * (time.perf_counter() - t0)
        self._step = i + 1

    def watch_probes(self, sources: list[Any]) -> None:
        """Take probes from these sources' rings (a CNC's probe block) besides the inbox."""
        self.probe_rings = [self.inbox, *(r for s in sources if (r := s.probe_ring()) is not None)]

    def publish_status(self, state: str | None = None) -> None:
        """Put a snapshot of the loop in the ring (also from outside the loop: start, stop)."""
        if state is not None:
            self.state = state
        if self._next_status_s == -math.inf:  # the first: the loop's next one a period later
            self._next_status_s = time.monotonic() + self.status_period_s
        self._hand_over(snapshot(self.loop, state=self.state, observe=self.observe, extra=self.status_extra()))

    def _hand_over(self, snap: dict[str, Any]) -> None:
        snap["publisher"] = {"snapshots_waited": self.snapshots_waited, "messages_dropped": self.outbox.dropped,
                             "rows_dropped": self.rows_dropped,
                             "snapshot_cost_us": round(sum(self.step_cost_s) * 1e6, 1),
                             "snapshot_step_max_us": round(max(self.step_cost_s, default=0.0) * 1e6, 1)}
        buckets = lateness_buckets(self.loop.stats, LATENESS_BOUNDS_US)
        self.outbox.put(("status", snap, buckets))
        self.snapshots += 1

    def row(self, row: tuple[float, ...]) -> None:
        """A data-log row (LogObserver, on the cycle)."""
        if not self.outbox.put(("row", row)):
            self.rows_dropped += 1

    def model_state(self, state: dict[str, Any]) -> None:
        """The model's state after a step (Loop.on_model_state, on the cycle)."""
        self.outbox.put(("model_state", state))

    def adapt_state(self, axes: dict[str, Any]) -> None:
        """The adapter's state after a probe (Adapter.on_state, on the cycle)."""
        self.outbox.put(("adapt_state", axes, time.time()))

    def flush_events(self) -> None:
        """Events not yet handed over (outside the loop: the loop has stopped)."""
        self.after_cycle(0.0)

    # ------------------------------------------------------------ helpers
    def _status_failed(self, e: Exception) -> None:
        """A snapshot's step raised: drop the snapshot, try again a period later, log the first
        failure of each kind (the cycle goes on compensating)."""
        self._steps, self._snap, self._step = None, None, 0
        self._next_status_s = time.monotonic() + self.status_period_s
        self.status_failures += 1
        reason = f"{type(e).__name__}: {e}"
        if reason not in self._failures_logged:
            self._failures_logged.add(reason)
            log.error("status snapshot failed (compensation goes on; the status is not refreshed): %s", reason,
                      extra={"event": "status_error", "reason": reason})

    def _put_events(self, events: list[tuple[float, str, str, str]]) -> None:
        self.outbox.put(("events", with_causes(events, self.loop.sources)))

    def _take_probes(self, ring: MessageRing) -> None:
        adapter = self.loop.adapter
        for msg in ring.take():
            if adapter is None:
                continue
            probe = msg if isinstance(msg, Probe) else Probe(**msg)
            if math.isnan(probe.t_s):  # sent without a time: it was measured now
                probe = dataclasses.replace(probe, t_s=float(self.loop.now_s))
            adapter.inbox.append(probe)
