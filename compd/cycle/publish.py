"""The cycle's side of the service: what status, logs and metrics need from the loop, handed over between cycles.

The service work (status file, metrics, event log lines, the data log, model state,
the probe socket) runs beside the loop, in a process of its own on the wall clock
(compd/daemon/host.py). It never reads the pipeline's objects: the cycle's thread hands
it what it needs, in shared memory, so there is never a second thread of Python in
the cycle's interpreter and nothing the cycle writes is read half-written.

After every cycle the loop calls `Publisher.after_cycle` with the time left before
the next deadline:

* the cycle's status record (compd/cycle/statusblock.py): per axis, per signal and for the
  loop, a fixed-layout write under a seqlock (a few µs), from which the service
  composes status.json, metrics, Sparkplug and OPC UA whenever it wants;
* the supervisor's look at the child processes (compd/io/supervisor.py);
* the guard's new events and the adapter's new probe events (few, cheap), each
  sensor event with its source's last error as the cause;
* once a `status.period_s` of wall time, the devices' own accounts (each source's and
  the sink's status, the adapter, fault counts, the processes): one message, sent only
  when the time left holds it with room to spare (its cost is measured each time);
* probes that arrived for the adapter (`compd probe` through the service, a CNC's
  probe block through its source's worker) go into the adapter's inbox.

Model and adapter state and the data log's rows go through a `MessageRing`
(compd/io/ring.py) when the cycle makes them (a few µs: pickling a tuple). A full ring
drops the message and counts it (the service is gone or far behind); the cycle never
waits for room.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from compd.core.probe import Probe
from compd.cycle.statusblock import StatusBlock, describe_devices
from compd.io.ring import MessageRing
from compd.io.supervisor import Supervised, Supervisor
from compd.io.worker import started_workers

log = logging.getLogger("compd.service")

ROOM_FACTOR = 1.5  # the devices' accounts are taken only when the time left is this many times their cost ...
ROOM_EXTRA_S = 100e-6  # ... plus this
COST_WEIGHT = 0.25  # their cost estimate: an average of the costs with this weight on the newest
WAIT_DECAY = 0.99  # ... and it shrinks by this for every cycle they wait for room
FIRST_COST_S = 100e-6  # the estimate before it was first measured


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


def with_causes(
    events: list[tuple[float, str, str, str]], sources: list[Any]
) -> list[tuple[float, str, str, str, str | None]]:
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
        observe: bool,
        probe_rings: list[MessageRing] = (),  # type: ignore[assignment]
    ) -> None:
        self.loop = loop
        self.outbox = outbox
        self.inbox = inbox
        self.status_period_s = status_period_s
        self.observe = observe
        self.block = StatusBlock(loop)  # made before the service's fork: shared with it
        self.block.messages_dropped = lambda: outbox.dropped
        self.probe_rings = [inbox, *probe_rings]
        self._guard_events = Tail(lambda: loop.guard.events)
        self._probe_events = Tail(lambda: loop.adapter.events) if loop.adapter is not None else None
        self._next_devices_s = -math.inf  # wall (monotonic) time the devices' accounts are next due
        self.devices_cost_s = FIRST_COST_S  # the estimate they need room for
        self.devices_sent = 0
        self.devices_waited = 0  # cycles the devices' accounts waited for room
        self.status_failures = 0  # devices' accounts that could not be taken (one raised)
        self._failures_logged: set[str] = set()
        # the I/O workers' processes and the service's (compd/io/supervisor.py), watched between cycles
        self.supervised: list[Supervised] = []
        self.supervisor = Supervisor(workers=lambda: [*started_workers(), *self.supervised])

    @property
    def state(self) -> str:
        return self.block.state

    @property
    def rows_dropped(self) -> int:
        """Data-log rows the ring had no room for."""
        return self.block.rows_dropped

    # ------------------------------------------------------------ the cycle's thread
    def after_cycle(self, room_s: float) -> None:
        """After a cycle, with `room_s` before the next deadline (inf: no real-time schedule)."""
        self.block.write()
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
        if time.monotonic() < self._next_devices_s:
            return
        if room_s < ROOM_FACTOR * self.devices_cost_s + ROOM_EXTRA_S:
            self.devices_waited += 1
            self.devices_cost_s *= WAIT_DECAY  # one slow take must not hold the next ones back for good
            return
        t0 = time.perf_counter()
        self._send_devices()
        self.devices_cost_s = (1.0 - COST_WEIGHT) * self.devices_cost_s + COST_WEIGHT * (time.perf_counter() - t0)

    def watch_probes(self, sources: list[Any]) -> None:
        """Take probes from these sources' rings (a CNC's probe block) besides the inbox."""
        self.probe_rings = [self.inbox, *(r for s in sources if (r := s.probe_ring()) is not None)]

    def publish_status(self, state: str | None = None) -> None:
        """The record and the devices' accounts now, and the service asked to write the status
        at once (also from outside the loop: start, stop)."""
        if state is not None:
            self.block.state = state
        self.block.write()
        self._send_devices()
        self.outbox.put(("status_now",))

    def _send_devices(self) -> None:
        """The devices' accounts to the service (`describe_devices`); the next a period later."""
        self._next_devices_s = time.monotonic() + self.status_period_s
        try:
            devices = describe_devices(self.loop, self.supervisor.processes())
            devices["model_state"] = self.loop.model.get_state()
        except Exception as e:  # accounts that cannot be taken never stop the cycle: these are dropped
            self._status_failed(e)
            return
        devices["publisher"] = {
            "devices_waited": self.devices_waited,
            "devices_cost_us": round(self.devices_cost_s * 1e6, 1),
        }
        self.outbox.put(("devices", devices))
        self.devices_sent += 1

    def row(self, row: tuple[float, ...]) -> None:
        """A data-log row (LogObserver, on the cycle)."""
        if not self.outbox.put(("row", row)):
            self.block.rows_dropped += 1

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
        """The devices' accounts raised: drop them, try again a period later, log the first
        failure of each kind (the cycle goes on compensating; the record is still written)."""
        self.status_failures += 1
        reason = f"{type(e).__name__}: {e}"
        if reason not in self._failures_logged:
            self._failures_logged.add(reason)
            log.error(
                "status of the devices failed (compensation goes on; the status shows the last one): %s",
                reason,
                extra={"event": "status_error", "reason": reason},
            )

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
