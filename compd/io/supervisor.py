"""The daemon's supervisor of its I/O workers: a lost poll or link process is reported at once, restarted with back-off.

Every device worker (compd.io.worker: a polled source, the CAN reader, a sink's Modbus
link) runs a thread of its own, in a child process when the daemon hosts I/O so
(`loop.io: process`). Such a child can die (a crash, the OOM killer, `kill -9`) or stop
(SIGSTOP, a device call that never returns). `Supervisor.check` runs on the cycle's
thread between two cycles (compd/cycle/publish.py) and looks at every worker at most every
`check_every_s`: its heartbeat (a counter in shared memory the worker's thread bumps at
least every 50 ms) and, for a child, whether the process still exists (`waitpid` with
WNOHANG: the cycle's process reaps its children here). A worker that is gone or silent
for its `stall_after_s` (2 s) is

* reported at once: one error line, event `io_process_lost`, naming the worker, its pid
  and why (`exited with code 1`, `killed by SIGKILL`, `stopped beating for 2.1 s`);
* abandoned: a stalled process is killed (it must never wake up and write an old
  value), its link marked down, so status, metrics, Sparkplug and OPC UA say the axis is
  no longer confirmed at the machine; a poller's signals go stale and the guard applies
  the axis's fault policy, with the loss as the sensor's cause;
* restarted after `restart_min_s`, doubling after each further loss up to
  `restart_max_s` (event `io_process_restarted` with the new pid). The new process sends
  what the link's queue holds that the device had not acknowledged, and the sink's
  next writes; a poller publishes fresh samples.

More than `max_restarts` losses within `window_s` escalate (event `io_restarts_exhausted`,
critical): the daemon stops feeding systemd's watchdog (compd/service/notify.py), so systemd
restarts the whole daemon, the way its unit file asks (`Restart=on-failure`,
`WatchdogSec=`); restarts of the worker go on meanwhile. Without a watchdog the line is
all that happens.

A restart forks between two cycles (the child's start takes a few ms): the cycle after
it can be late, and is counted so. That is the price of getting the link back. It never
waits for the new process to open (`IoWorker.restart`): one that does not answer within its
`restart_open_s` (stopped or hung before it came up) is lost, reported and restarted again
with the back-off, like any other.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from compd.io.worker import started_workers

log = logging.getLogger("compd.io")


class Supervised(Protocol):
    """What the supervisor watches: an I/O worker (compd.io.worker.IoWorker) or the service's
    process (compd.daemon.host)."""

    name: str
    lost_event: str  # the event of its loss (io_process_lost, service_lost) ...
    restarted_event: str  # ... and of its restart

    @property
    def pid(self) -> int | None: ...

    @property
    def wanted(self) -> bool: ...

    def health(self, now_s: float) -> str | None: ...

    def abandon(self, reason: str) -> None: ...

    def restart(self) -> None: ...


@dataclass
class _Lost:
    """A worker the supervisor has lost, until its restart went through."""

    reason: str
    pid: int | None
    restart_at_s: float


@dataclass
class Supervisor:
    """Watches I/O workers from the cycle's thread (see the module)."""

    workers: Callable[[], Iterable[Supervised]] = started_workers
    restart_min_s: float = 0.5
    restart_max_s: float = 30.0
    max_restarts: int = 5
    window_s: float = 600.0
    check_every_s: float = 0.05
    clock: Callable[[], float] = time.monotonic
    escalated: bool = False  # too many restarts: the watchdog is no longer fed
    losses: int = 0
    restarts: int = 0
    _lost: dict[Supervised, _Lost] = field(default_factory=dict)
    _losses_of: dict[str, collections.deque[float]] = field(default_factory=dict)
    _restarts_of: dict[str, int] = field(default_factory=dict)
    _history: collections.deque[float] = field(default_factory=collections.deque)
    _next_s: float = 0.0
    _last_reason: dict[str, str] = field(default_factory=dict)

    def check(self) -> None:
        """Between cycles: look at the workers (at most every `check_every_s`), report and
        abandon the lost ones, restart those whose back-off has passed."""
        now = self.clock()
        if now < self._next_s:
            return
        self._next_s = now + self.check_every_s
        for w in self.workers():
            if w in self._lost:
                continue
            reason = w.health(now)
            if reason is not None:
                self._lose(w, reason, now)
        for w, lost in list(self._lost.items()):
            if not w.wanted:  # stopped meanwhile (the daemon is stopping, a reload)
                del self._lost[w]
            elif now >= lost.restart_at_s:
                self._restart(w, lost, now)

    def lost(self) -> dict[str, str]:
        """The workers lost and not yet back: name → why."""
        return {w.name: lost.reason for w, lost in self._lost.items()}

    def processes(self) -> list[dict[str, Any]]:
        """What the status says of each watched worker and service: name, pid, up (False while
        lost), restarts so far, and why it was last lost (None: never)."""
        out = []
        for w in self.workers():
            lost = self._lost.get(w)
            out.append(
                {
                    "name": w.name,
                    "pid": w.pid if lost is None else lost.pid,
                    "up": lost is None,
                    "restarts": self._restarts_of.get(w.name, 0),
                    "lost": self._last_reason.get(w.name),
                }
            )
        return out

    def _lose(self, w: Supervised, reason: str, now: float) -> None:
        pid = w.pid
        w.abandon(reason)
        wait = self._wait(w.name, now)
        self._lost[w] = _Lost(reason, pid, now + wait)
        self._last_reason[w.name] = reason
        self.losses += 1
        log.error(
            "%s (pid %s) %s; not served until it is restarted in %.1f s",
            w.name,
            pid,
            reason,
            wait,
            extra={"event": w.lost_event, "worker": w.name, "pid": pid, "reason": reason, "restart_in_s": wait},
        )
        if self._in_window(self._history, now) > self.max_restarts and not self.escalated:
            self.escalated = True
            log.critical(
                "%d I/O processes lost within %.0f s: compd stops feeding the watchdog"
                " (systemd restarts it when it has one)",
                len(self._history),
                self.window_s,
                extra={
                    "event": "io_restarts_exhausted",
                    "worker": w.name,
                    "losses": len(self._history),
                    "window_s": self.window_s,
                },
            )

    def _wait(self, name: str, now: float) -> float:
        """The back-off before the next restart of `name`: `restart_min_s`, doubled for every
        other loss or failed restart of it within `window_s`, at most `restart_max_s`."""
        n = self._in_window(self._losses_of.setdefault(name, collections.deque()), now)
        return min(self.restart_min_s * 2.0 ** (n - 1), self.restart_max_s)

    def _in_window(self, times: collections.deque[float], now: float) -> int:
        """Add `now` to `times` and forget those older than `window_s`; how many are left."""
        times.append(now)
        while times[0] < now - self.window_s:
            times.popleft()
        return len(times)

    def _restart(self, w: Supervised, lost: _Lost, now: float) -> None:
        try:
            w.restart()
        except Exception as e:
            wait = self._wait(w.name, now)
            lost.restart_at_s = now + wait
            log.error(
                "%s: restart failed (%s: %s); next try in %.1f s",
                w.name,
                type(e).__name__,
                e,
                wait,
                extra={"event": "io_restart_failed", "worker": w.name, "reason": str(e), "restart_in_s": wait},
            )
            w.abandon(lost.reason)
            return
        del self._lost[w]
        self.restarts += 1
        self._restarts_of[w.name] = self._restarts_of.get(w.name, 0) + 1
        log.warning(
            "%s restarted (pid %s; was pid %s: %s)",
            w.name,
            w.pid,
            lost.pid,
            lost.reason,
            extra={
                "event": w.restarted_event,
                "worker": w.name,
                "pid": w.pid,
                "old_pid": lost.pid,
                "reason": lost.reason,
            },
        )
