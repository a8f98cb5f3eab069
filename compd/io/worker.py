"""The one I/O worker: a device thread's life cycle (start, pace, wake, reconnect with back-off, stop).

Every device compd talks to beside the cycle — a polled source, the CAN reader, a
sink's Modbus link, a plant's clock — runs on an `IoWorker`. The device supplies only
its work, a `DeviceWork`: `open` (start-up checks that must pass), `connect`,
`round` (one round of I/O: poll once, send what is queued and read the status, take
one frame, step the plant), `offline` (a round while the link is down), `disconnect`
and `close`. The worker owns the rest:

* start and stop: `start` runs `open` on the worker's thread and re-raises its error
  in the caller (a device that must exist at start-up fails loudly); `stop` ends the
  thread and joins it within a timeout; a stopped worker can be started again.
* pace: a round every `period_s` (paced), or only when woken or asked (`paced=False`:
  a lockstep clock asks for every poll); `wake` asks for a round soon.
* reconnect: a failed `connect`, or a round that raises `LinkDown` (any exception, in
  fact), takes the link down; the next `connect` waits `reconnect_min_s`, doubling
  after every further failure up to `reconnect_max_s`, and back to the minimum after
  a round that went through. While the link is down, paced rounds and requests get
  `offline` (a poller publishes that its signals are lost).
* accounts: `state` (closed, connecting, up, down), `rounds`, `errors`, `connects`,
  the work's `last_error` and counters (`get_status`), and `round_hist`, the duration
  of every round (µs).
* the heartbeat: the thread counts `beats` in the shared accounts at every turn of its
  loop, at least every `BEAT_EVERY_S` while no device call hangs. `health` (the daemon's
  supervisor, compd.io.supervisor, between cycles) tells from it and from the process
  whether the worker still runs; `abandon` and `restart` are what the supervisor does
  when it does not.
* the log: the first failure of the device and every change of its error are logged
  (warning, logger `compd.io`, event `device_error`) with the reason as the work set it
  (the OS's text: "could not open port /dev/ttyUSB9: [Errno 2] No such file or
  directory"); the same error again, retry after retry, is not. Rounds without an error
  for `recovered_after_s` log one info line (`device_recovered`), so a device that flaps
  between an error and a good round logs the error once, not at every flap. This
  happens on the worker's thread, never in the cycle.

Where it runs: a thread of the daemon, or (`start(process=True)`, the daemon's choice
on the wall clock: `loop.io`) a child process of its own (`compd.io.child`), so that
its Python never holds the GIL the cycle needs. The interface between the cycle and
its device is data only, in memory shared with the child (`compd.io.mailbox`), so
sources and sinks are the same either way:

  cycle → worker   `WriteQueue.submit(address, values)` (which calls `wake()`);
                   `request(arg)`: one round now with `arg` (a stamp, a target time,
                   a register range), and its reply — for everything that is not the
                   cycle itself (a lockstep clock between cycles, a settle, a test);
                   over the child's pipe when the worker runs there;
  worker → cycle   `Snapshot` (values, quality and stamp of each signal),
                   `SharedRegisters` (status registers), the worker's accounts
                   (`state`, `rounds`, `errors`, `connects`, `round_hist`), and
                   `get_status()` (a dict of counts, over the pipe from a child).

The wake-up is an eventfd, made before the fork and so shared with the child.
The cycle only ever appends to a queue, reads a published object or writes to an
eventfd: it never takes a lock a worker could hold, never waits for a worker's
Python, never blocks on a device. Times that stamp samples come from the `clock`
given to `start` (the loop's), read on the worker's thread when a round starts.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import json
import logging
import os
import select
import threading
import time
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from compd.io import activity
from compd.io.child import Child, ChildGone, Heartbeat, exit_text
from compd.io.histogram import DurationHist
from compd.io.mailbox import shared_buffer
from compd.io.ring import SharedBlob

log = logging.getLogger("compd.io")

WORKER_STATES = ("closed", "connecting", "up", "down")
# a sink's link to its device, as the status names it (compd.sinks.base.Sink.link_state)
LinkState = Literal["up", "connecting", "down", "closed"]
LINK_STATES: tuple[LinkState, ...] = ("up", "connecting", "down", "closed")

# a device's recovery is logged once its rounds have gone through without an error this long
# (a device that flaps between an error and a good round logs the error once, not every flap)
RECOVERED_AFTER_S = 5.0
STATUS_BYTES = 4096  # a worker's status as JSON, at most
STATUS_EVERY_S = 0.1  # how often a worker refreshes its published status (and at every change of state or error)
BEAT_EVERY_S = 0.05  # a running worker's thread beats at least this often (its idle waits are capped to it) ...
OPEN_TIMEOUT_S = 60.0  # a worker's process started at start-up (not by the cycle) answers `open` within this
RESTART_OPEN_S = 10.0  # a process restarted between cycles that has not answered `open` by then is lost
STALL_AFTER_S = 2.0  # ... and one that has not beaten for this long has stalled (a device call that hangs, SIGSTOP)


def stall_after(timeout_s: float, calls: int = 4) -> float:
    """The silence after which a worker whose device calls wait up to `timeout_s` has
    stalled: `calls` of them in a row and a second more, never under `STALL_AFTER_S`."""
    return max(STALL_AFTER_S, calls * timeout_s + 1.0)


# the workers started here and not stopped: what the daemon's supervisor watches (compd.io.supervisor)
_started: weakref.WeakSet[IoWorker] = weakref.WeakSet()


def started_workers() -> list[IoWorker]:
    """The I/O workers started in this process and not stopped since (their thread or child
    may have died: that is what the supervisor looks for)."""
    return list(_started)


class LinkDown(Exception):
    """Raised by a round when the link to the device is gone (the worker reconnects)."""


class DeviceWork(ABC):
    """The device half of a source, sink link or clock: what its worker runs. Every method
    runs on the worker's thread (but `counters`, which only reads numbers)."""

    def __init__(self) -> None:
        self._last_error: str | None = None
        self.errors_set = 0  # times `last_error` was set: a round that set it had an error
        self.now: Callable[[], float] = time.monotonic  # the loop clock (set by IoWorker.start)

    @property
    def last_error(self) -> str | None:
        """The latest error of the device (its text names the reason), kept after recovery."""
        return self._last_error

    @last_error.setter
    def last_error(self, text: str | None) -> None:
        self._last_error = text
        if text is not None:
            self.errors_set += 1

    def open(self) -> None:
        """Start-up: open or check what must be there (an error is raised to `start`'s caller)."""

    def connect(self) -> None:
        """Open the link to the device; raise LinkDown when it cannot be reached."""

    def disconnect(self) -> None:
        """Close the link (after it went down)."""

    def close(self) -> None:
        """Release the device for good (the worker stops)."""
        self.disconnect()

    @abstractmethod
    def round(self, request: Any) -> Any:
        """One round of device I/O with the link up: `request` is None for a round of the
        worker's own (pace or wake), else what `IoWorker.request` was given; returns the
        reply to a request. Raise LinkDown when the link broke."""

    def offline(self, request: Any) -> Any:
        """A round while the link is down (e.g. publish that the signals are lost)."""
        return None

    def counters(self) -> dict[str, Any]:
        """The device's own counts, for status (plain data)."""
        return {}


class _Account:
    """One count of an IoWorker's accounts, held in its shared memory (`_acct[index]`)."""

    def __init__(self, index: int, doc: str) -> None:
        self.index = index
        self.__doc__ = doc

    def __get__(self, worker: IoWorker | None, owner: type) -> Any:
        return self if worker is None else int(worker._acct[self.index])

    def __set__(self, worker: IoWorker, value: int) -> None:
        worker._acct[self.index] = value


class IoWorker:
    """Runs one `DeviceWork` on a thread of its own, named `name`: see the module."""

    lost_event = "io_process_lost"  # the supervisor's events (compd.io.supervisor)
    restarted_event = "io_process_restarted"

    def __init__(
        self,
        work: DeviceWork,
        *,
        name: str,
        period_s: float | None = None,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 10.0,
        join_timeout_s: float = 5.0,
        round_hist: DurationHist | None = None,
        recovered_after_s: float = RECOVERED_AFTER_S,
        stall_after_s: float = STALL_AFTER_S,
    ) -> None:
        if reconnect_max_s < reconnect_min_s:
            raise ValueError("reconnect_max_s is below reconnect_min_s")
        self.work = work
        self.name = name
        self.period_s = period_s
        self.reconnect_min_s, self.reconnect_max_s = reconnect_min_s, reconnect_max_s
        self.join_timeout_s = join_timeout_s
        self.round_hist = round_hist if round_hist is not None else DurationHist()
        # the accounts, in memory shared with a child the worker may run in: state (an
        # index of WORKER_STATES), rounds, errors, connects, wakes asked; the retry wait (s);
        # the heartbeat (the thread counts it at every turn of its loop)
        self._acct_buf = shared_buffer(56)
        self._acct = np.frombuffer(self._acct_buf, dtype=np.int64, count=5)
        self._retry = np.frombuffer(self._acct_buf, dtype=np.float64, count=1, offset=40)
        self._beat = np.frombuffer(self._acct_buf, dtype=np.int64, count=1, offset=48)
        self._heartbeat = Heartbeat(self._beat, stall_after_s)  # the supervisor's watch on a child
        self._start_args: tuple[bool, Callable[[], float] | None, bool, frozenset[int]] | None = None
        self.lost: str | None = None  # why the worker's thread or process is gone (None: it runs, or was stopped)
        self.lost_pid: int | None = None
        self.reported_error: str | None = None  # the error the log last said the device has (None: fine)
        # `get_status()` as JSON, refreshed by the worker's thread: read from shared memory
        # when the worker runs in a child, so that asking never waits on the child
        self._status_blob = SharedBlob(STATUS_BYTES)
        self._status_published = (-1.0, b"")
        self.recovered_after_s = recovered_after_s
        self._healthy_since: float | None = None  # rounds without an error since (monotonic s)
        self._child: Child | None = None  # the process the worker runs in (None: a thread here)
        # a process restarted between cycles that has not answered `open` yet: it, the call's
        # number, and when it is lost if it still has not (monotonic s); `health` looks
        self._opening: tuple[Child, int, float] | None = None
        self.restart_open_s = max(RESTART_OPEN_S, 2.0 * stall_after_s)
        self._last_status: dict[str, Any] | None = None  # a stopped child's final counts
        self._paced = True
        self._stop = False
        self._wakes_seen = 0
        self._thread: threading.Thread | None = None
        self._open_error: BaseException | None = None
        self._done = threading.Condition()  # a round ended; a reply is there
        self._requests: collections.deque[tuple[int, Any]] = collections.deque()
        self._replies: dict[int, Any] = {}
        self._waiting: set[int] = set()
        self._seq = itertools.count(1)
        # wakes the thread without a lock: the cycle writes, the thread selects on it
        self._fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        weakref.finalize(self, os.close, self._fd)

    # ------------------------------------------------------------ accounts (shared)
    rounds = _Account(1, "rounds of I/O done")
    errors = _Account(2, "failed connects and rounds")
    connects = _Account(3, "connects that went through")
    _wakes = _Account(4, "counted by `wake`; the thread runs a round when it changed (no flag to lose)")

    @property
    def state(self) -> str:
        """closed, connecting, up or down."""
        return WORKER_STATES[int(self._acct[0])]

    @state.setter
    def state(self, value: str) -> None:
        self._acct[0] = WORKER_STATES.index(value)

    @property
    def retry_in_s(self) -> float:
        """The wait before the connect after the latest failure."""
        return float(self._retry[0])

    @retry_in_s.setter
    def retry_in_s(self, value: float) -> None:
        self._retry[0] = value

    # ------------------------------------------------------------ life cycle
    @property
    def running(self) -> bool:
        if self._child is not None:
            return self._child.alive()
        th = self._thread
        return th is not None and th.is_alive()

    @property
    def in_process(self) -> bool:
        """Whether the worker runs in a child process of its own."""
        return self._child is not None

    @property
    def pid(self) -> int | None:
        """The process the worker runs in (None: stopped or gone)."""
        if self._child is not None:
            return self._child.pid
        if self._opening is not None:
            return self._opening[0].pid
        return os.getpid() if self._thread is not None else None

    @property
    def wanted(self) -> bool:
        """Started and not stopped since: the worker should be running."""
        return self._start_args is not None

    @property
    def beats(self) -> int:
        """The heartbeat: counted by the worker's thread at every turn of its loop (at
        least every `BEAT_EVERY_S` while it runs and no device call hangs)."""
        return int(self._beat[0])

    def health(self, now_s: float) -> str | None:
        """Between cycles (the supervisor, a few µs): None while the worker's thread or
        process runs and beats; else why not ("exited with code 1", "killed by SIGKILL",
        "stopped beating for 2.1 s"; a thread only when it has ended: it cannot be killed).
        A stopped worker is healthy (nothing to run)."""
        if self._start_args is None:
            return None
        if self._opening is not None:
            return self._opened(now_s)
        if self._child is not None:
            return self._heartbeat.health(self._child, now_s)
        th = self._thread
        if th is None or not th.is_alive():
            return "its thread has ended"
        return None  # a thread cannot be killed: one stuck in a device call is waited for, never doubled

    def abandon(self, reason: str) -> None:
        """The worker's process or thread is lost (`health` said why): kill the process if it
        still exists (a stalled one must never wake and write), reap it, mark the link down
        and keep `reason` as its error until `restart`."""
        child = self._child
        self.lost_pid = self.pid
        if self._opening is not None:  # a restarted process that never answered `open`
            self._opening[0].stop(0.0)
            self._opening = None
        if child is not None:
            self._child = None
            child.stop(0.0)  # kills what is left (SIGKILL works on a stopped process) and reaps
        self._thread = None
        self.lost = reason
        self.state = "down"

    def restart(self) -> None:
        """Start the worker again as it was started last (after `abandon`); raises what
        `start` raises. The queued writes a lost process had not had acknowledged are sent
        by the new one.

        The supervisor calls this on the cycle's thread, between two cycles, so it never
        waits for the new process: it forks it and asks it to open; `health` then takes its
        answer, or says it is lost when it fails, ends, or has not answered within
        `RESTART_OPEN_S` (a process stopped before it answered)."""
        if self._start_args is None:
            raise RuntimeError(f"I/O worker {self.name} was never started")
        paced, clock, process, avoid = self._start_args
        self.work.last_error = None
        if not process:
            self.start(paced=paced, clock=clock, process=process, avoid_cpus=avoid)
        else:
            self._last_status = None
            child, seq = self._fork(paced, clock, avoid)
            self._opening = (child, seq, time.monotonic() + self.restart_open_s)
            self._started(paced, clock, process, avoid)
        self.lost = None

    def _opened(self, now_s: float) -> str | None:
        """`health` of a process restarted and not yet open: None while it may still answer
        (or once it has: it is the worker's process from then on), else why it is lost."""
        assert self._opening is not None
        child, seq, deadline_s = self._opening
        try:
            got = child.answer(seq)
        except ChildGone:
            got = None
            if child.alive():
                return "its new process closed its pipe before it opened"
        if got is not None:
            ok, value = got
            if not ok:
                return f"its new process failed to open: {type(value).__name__}: {value}"
            self._opening = None
            self._child = child
            self._heartbeat.reset(now_s)
            return None
        if not child.alive():
            return f"its new process {exit_text(child.exit_code)} before it opened"
        if time.monotonic() > deadline_s:
            return f"its new process did not open within {self.restart_open_s:.0f} s"
        return None

    def start(
        self,
        *,
        paced: bool = True,
        clock: Callable[[], float] | None = None,
        process: bool = False,
        avoid_cpus: frozenset[int] = frozenset(),
    ) -> None:
        """Start the worker: `open` the work on its thread (its error is raised here), then
        run rounds every `period_s` (paced, and a period set) or only when woken or asked.
        `process`: the thread runs in a child process of its own (forked now; `clock` must
        be readable there, e.g. the wall clock), kept off the CPUs `avoid_cpus`."""
        if self.running:
            raise RuntimeError(f"I/O worker {self.name} is running already")
        self._last_status = None
        if not process:
            self._start_thread(paced, clock)
            self._started(paced, clock, process, avoid_cpus)
            return
        child, seq = self._fork(paced, clock, avoid_cpus)
        try:
            ok, value = child.wait_answer(seq, timeout_s=OPEN_TIMEOUT_S)
            if not ok:
                raise value
        except BaseException:
            self._end_child(child)
            raise
        self._child = child
        self._started(paced, clock, process, avoid_cpus)

    def _fork(self, paced: bool, clock: Callable[[], float] | None, avoid: frozenset[int]) -> tuple[Child, int]:
        """Fork the worker's process and ask it to open the work (not waiting for the answer);
        the child and the number of that call."""
        child = Child(self.name)

        def answer(what: str, *args: Any) -> Any:
            if what == "open":
                self._start_thread(paced, clock)
                return None
            if what == "request":
                return self.request(args[0], args[1])
            if what == "status":
                return self.get_status()
            if what == "stop":
                return self.stop(args[0])
            raise ValueError(f"unknown call {what!r}")

        def serve(ch: Child) -> None:
            self._child = None  # in the child, the worker is a thread of its own process
            self._opening = None
            try:
                ch.serve_calls(answer)
            finally:
                self.stop()

        self.state = "connecting"
        child.start(serve, avoid, keep_fds=(self._fd,))
        return child, child.begin("open")

    def _end_child(self, child: Child) -> None:
        """A child that did not open: asked to exit, killed when it does not within the join timeout."""
        with contextlib.suppress(ChildGone):
            child.call("exit", timeout_s=self.join_timeout_s)
        child.stop(self.join_timeout_s)
        self.state = "closed"

    def _started(self, paced: bool, clock: Callable[[], float] | None, process: bool, avoid: frozenset[int]) -> None:
        self._start_args = (paced, clock, process, avoid)
        self._heartbeat.reset(time.monotonic())
        _started.add(self)

    def _start_thread(self, paced: bool, clock: Callable[[], float] | None) -> None:
        if clock is not None:
            self.work.now = clock
        self._paced = paced and self.period_s is not None
        self._stop = False
        self._wakes_seen = self._wakes
        self._drain_wakes()
        self._open_error = None
        opened = threading.Event()
        self.state = "connecting"
        th = threading.Thread(target=self._main, args=(opened,), name=self.name, daemon=True)
        self._thread = th
        th.start()
        opened.wait()
        if self._open_error is not None:
            th.join(self.join_timeout_s)
            self._thread = None
            self.state = "closed"
            err, self._open_error = self._open_error, None
            raise err

    def stop(self, timeout_s: float | None = None) -> bool:
        """Stop the worker and join it (within `timeout_s`, default `join_timeout_s`); False
        when it is still in a device call (it ends, and closes the device, by itself; a
        child process that does not end is killed)."""
        timeout = self.join_timeout_s if timeout_s is None else timeout_s
        _started.discard(self)
        self._start_args = None
        self.lost = None
        if self._opening is not None:  # restarted, never opened: nothing of it to keep
            self._end_child(self._opening[0])
            self._opening = None
        child = self._child
        if child is not None:
            self._child = None
            stopped = False
            with contextlib.suppress(ChildGone):
                stopped = bool(child.call("stop", timeout, timeout_s=timeout + 1.0))
                self._last_status = dict(child.call("status", timeout_s=1.0))
                child.call("exit", timeout_s=1.0)
            clean = child.stop(timeout + 1.0)
            self.state = "closed"
            if not (stopped and clean):
                log.warning(
                    "I/O worker %s did not stop in time",
                    self.name,
                    extra={"event": "io_worker_stuck", "worker": self.name},
                )
            return stopped and clean
        th = self._thread
        if th is None:
            return True
        self._stop = True
        self._signal()
        th.join(timeout)
        if th.is_alive():
            log.warning(
                "I/O worker %s did not stop in time", self.name, extra={"event": "io_worker_stuck", "worker": self.name}
            )
            return False
        self._thread = None
        return True

    # ------------------------------------------------------------ the cycle's side
    def wake(self) -> None:
        """Ask for a round soon (something was queued). Never waits."""
        self._acct[4] += 1
        self._signal()

    def request(self, arg: Any = None, timeout_s: float = 5.0) -> Any:
        """One round now with `arg`, on the worker's thread; its reply, or None when the
        worker is not running or the round did not end within `timeout_s`. Not for the
        cycle: it waits."""
        child = self._child
        if child is not None:
            try:
                return child.call("request", arg, timeout_s, timeout_s=timeout_s + 1.0)
            except ChildGone:
                return None
        if not self.running:
            return None
        seq = next(self._seq)
        with self._done:
            self._waiting.add(seq)
            self._requests.append((seq, arg))
        self._signal()
        deadline = time.monotonic() + timeout_s
        with self._done:
            try:
                while seq not in self._replies:
                    rest = deadline - time.monotonic()
                    if rest <= 0 or not self.running:
                        self._requests = collections.deque(r for r in self._requests if r[0] != seq)
                        return None
                    self._done.wait(min(rest, 0.5))
                return self._replies.pop(seq)
            finally:
                self._waiting.discard(seq)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait until `predicate()` holds (checked after every round, or every few ms when
        the worker runs in a child), or `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        if self._child is not None:
            while not predicate():
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.002)
            return True
        with self._done:
            while not predicate():
                rest = deadline - time.monotonic()
                if rest <= 0:
                    return False
                self._done.wait(min(rest, 0.05))
        return True

    def get_status(self) -> dict[str, Any]:
        """state, rounds, errors, connects, last_error, pid and the work's counters. When the
        worker runs in a child, what its thread last published in shared memory (at most
        `STATUS_EVERY_S` old; the counts are live): asking never waits on the child."""
        if self.lost is not None:  # the counts the lost process last published, and why it is gone
            raw = self._status_blob.read()
            last: dict[str, Any] = json.loads(raw) if raw else self._own_status()
            return {
                **last,
                **self._accounts(),
                "last_error": f"{self.name}: {self.lost}",
                "pid": self.lost_pid,
                "lost": self.lost,
            }
        child = self._child if self._child is not None else self._opening[0] if self._opening is not None else None
        if child is not None:
            raw = self._status_blob.read()
            # nothing published yet: the counts as they were when the child was forked
            published: dict[str, Any] = json.loads(raw) if raw else {**self._own_status(), "pid": child.pid}
            return {**published, **self._accounts()}
        if self._last_status is not None:  # stopped: the counts its process had at the end
            return {**self._last_status, "state": self.state}
        return self._own_status()

    def _accounts(self) -> dict[str, Any]:
        return {"state": self.state, "rounds": self.rounds, "errors": self.errors, "connects": self.connects}

    def _own_status(self) -> dict[str, Any]:
        return {**self._accounts(), "last_error": self.work.last_error, "pid": os.getpid(), **self.work.counters()}

    def _publish_status(self, force: bool = False) -> None:
        """On the worker's thread: put `get_status()` where the parent reads it (JSON in
        shared memory), every `STATUS_EVERY_S` or when `force`d (state or error changed)."""
        now = time.monotonic()
        last_s, last = self._status_published
        if not force and now - last_s < STATUS_EVERY_S:
            return
        try:
            data = json.dumps(self._own_status(), default=str).encode()
        except (TypeError, ValueError) as e:
            data = json.dumps({"last_error": f"status: {e}", "pid": os.getpid()}).encode()
        if len(data) > STATUS_BYTES:
            data = json.dumps(
                {
                    "last_error": self.work.last_error,
                    "pid": os.getpid(),
                    "status_error": f"status of {len(data)} bytes cut",
                }
            ).encode()
        if data != last:
            self._status_blob.publish(data)
        self._status_published = (now, data)

    # ------------------------------------------------------------ the thread
    def _signal(self) -> None:
        with contextlib.suppress(OSError):  # the counter is full: the thread has wakes to read
            os.eventfd_write(self._fd, 1)

    def _drain_wakes(self) -> None:
        with contextlib.suppress(BlockingIOError):
            os.eventfd_read(self._fd)

    def _idle(self, deadline: float | None) -> None:
        """Until `deadline` (monotonic; None: no limit), a wake, a request or stop, and never
        longer than `BEAT_EVERY_S`: the thread beats at every turn of its loop."""
        if deadline is None:
            timeout = BEAT_EVERY_S
        else:
            timeout = min(deadline - time.monotonic(), BEAT_EVERY_S)
            if timeout <= 0:
                return
        ready, _, _ = select.select([self._fd], [], [], timeout)
        if ready:
            self._drain_wakes()

    def _main(self, opened: threading.Event) -> None:
        try:
            self.work.open()
        except BaseException as e:  # handed to start()'s caller
            self._open_error = e
            opened.set()
            return
        opened.set()
        try:
            self._run()
        except Exception:
            log.exception("I/O worker %s failed", self.name, extra={"event": "io_worker_failed", "worker": self.name})
        finally:
            try:
                self.work.close()
            except Exception as e:
                self.work.last_error = f"close: {type(e).__name__}: {e}"
            self.state = "closed"
            self._publish_status(force=True)
            with self._done:
                self._done.notify_all()

    def _report(self, error: str | None) -> None:
        """Log the device's error when it changed (warning), and its recovery (info) once it
        has held `recovered_after_s`: once per change, on this thread. `error` None: the
        round went through without one."""
        if error is not None:
            self._healthy_since = None
            if error != self.reported_error:
                self.reported_error = error
                log.warning(
                    "%s: %s", self.name, error, extra={"event": "device_error", "worker": self.name, "reason": error}
                )
            return
        if self.reported_error is None:
            return
        now = time.monotonic()
        if self._healthy_since is None:
            self._healthy_since = now
        if now - self._healthy_since < self.recovered_after_s:
            return
        was, self.reported_error, self._healthy_since = self.reported_error, None, None
        log.info(
            "%s: recovered (was: %s)",
            self.name,
            was,
            extra={"event": "device_recovered", "worker": self.name, "reason": was},
        )

    def _next_request(self) -> tuple[int, Any] | None:
        with self._done:
            return self._requests.popleft() if self._requests else None

    def _run(self) -> None:
        work = self.work
        perf = time.perf_counter_ns
        spans = activity.ring(self.name)  # None unless the bench records who runs when
        backoff = self.reconnect_min_s
        next_connect = 0.0
        next_paced = 0.0
        up = False
        published: tuple[str, str | None] = ("", None)
        while not self._stop:
            self._beat[0] += 1
            req = self._next_request()
            wakes = self._wakes
            woken = wakes != self._wakes_seen
            self._wakes_seen = wakes
            now = time.monotonic()
            if not up and now >= next_connect:
                try:
                    work.connect()
                    up = True
                    self.connects += 1
                except Exception as e:
                    self.errors += 1
                    work.last_error = str(e) if isinstance(e, LinkDown) else f"connect: {type(e).__name__}: {e}"
                    self._report(work.last_error)
                    self.state = "down"
                    self.retry_in_s = backoff
                    next_connect = now + backoff
                    backoff = min(backoff * 2.0, self.reconnect_max_s)
            paced_due = self._paced and now >= next_paced
            reply = None
            if up and (req is not None or paced_due or woken):
                if self._paced:
                    next_paced = now + (self.period_s or 0.0)
                p0 = perf()
                set_before = work.errors_set
                try:
                    reply = work.round(None if req is None else req[1])
                    ok = True
                except Exception as e:
                    ok = False
                    reply = None
                    work.last_error = str(e) if isinstance(e, LinkDown) else f"{type(e).__name__}: {e}"
                p1 = perf()
                self.round_hist.add_ns(p1 - p0)
                if spans is not None:
                    spans.mark(p0, p1)
                self._report(work.last_error if work.errors_set != set_before else None)
                if ok:
                    self.rounds += 1
                    self.state = "up"
                    backoff = self.reconnect_min_s
                else:
                    self.errors += 1
                    self.state = "down"
                    up = False
                    with contextlib.suppress(Exception):
                        work.disconnect()
                    self.retry_in_s = backoff
                    next_connect = time.monotonic() + backoff
                    backoff = min(backoff * 2.0, self.reconnect_max_s)
            elif not up and (req is not None or paced_due):
                if self._paced:  # no faster than reconnect_min_s (a reader with period 0)
                    next_paced = now + (self.period_s or self.reconnect_min_s)
                try:
                    reply = work.offline(None if req is None else req[1])
                except Exception as e:
                    work.last_error = f"offline: {type(e).__name__}: {e}"
            with self._done:
                if req is not None and req[0] in self._waiting:
                    self._replies[req[0]] = reply
                self._done.notify_all()
            seen = (self.state, work.last_error)
            self._publish_status(force=seen != published)
            published = seen
            if self._stop or self._requests or self._wakes != self._wakes_seen:
                continue
            deadline = next_paced if self._paced else None
            if not up:
                deadline = next_connect if deadline is None else min(deadline, next_connect)
            self._idle(deadline)
