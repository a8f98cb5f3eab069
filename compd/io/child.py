"""A forked child process beside the cycle: control pipe, ends with its parent.

Device I/O and the service work (status, metrics, logs) run Python; in the cycle's
interpreter that Python holds the GIL the cycle needs when it wakes. `Child` forks a
process that runs such work instead, so the cycle never waits on it. What the two
share is set up before the fork (shared memory: `compd.io.mailbox`, `compd.io.ring`;
an eventfd to wake the child); the control pipe carries only calls and their answers
(pickled, never on the cycle's path): `call(what, *args)` in the parent, answered by
the child's `serve_calls`. The parent has no thread reading the pipe: a call reads
its own answer.

The child:
* runs at normal priority on every CPU the cycle is not pinned to (a fork inherits
  the cycle thread's SCHED_FIFO and affinity), and is not memory-locked (mlockall is
  not inherited);
* writes its own log lines, with the handlers and format it inherited (stderr: the
  journal under systemd), so a device's error is logged without the parent running
  a line of Python for it;
* ignores SIGINT and SIGTERM: the parent, stopping, still sends the safe state through
  a sink's child; the parent stops its children. A parent killed outright (SIGKILL)
  takes its children along (PR_SET_PDEATHSIG), as it would its threads: nothing is
  written after it died;
* closes every file descriptor it inherited but stdin, stdout, stderr, its pipe and
  those it is given (`keep_fds`: the worker's eventfd, a listening socket it serves):
  another listening socket of the parent must not stay bound in a child, or its port
  could not be opened again at a reload; and it freezes the inherited objects out of
  the garbage collector's view, so no copy of a parent's socket is ever finalized
  there (its number may belong to the child's own socket by then);
* ends with `os._exit`: nothing of the parent's (atexit, buffered files, finalizers)
  runs twice.

Fork, not spawn: the device objects are built and checked in the parent (a bad config
is refused there, before anything runs) and the child starts in milliseconds with them.
The parent has threads when it forks (a simulated clock's workers): the child uses only
its own objects, and Python re-creates the import and logging locks after a fork. Pages
the parent writes after a fork are copied on the first write (a fault each), so
children are forked at start-up and at a reload, never while cycles run, and a
memory-locked daemon copies its pages before the first cycle (`compd.cycle.realtime.unshare_pages`).
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import itertools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, Pipe
from typing import Any

from compd.io import activity

log = logging.getLogger("compd.io")

PARENT_CHECK_S = 0.5  # how often a child checks that its parent is still there


@dataclass
class Hosting:
    """Where I/O workers started now run: `process` (a child each) or threads; `cpus`: the
    CPUs the cycle thread is pinned to (children keep off them when others are left)."""

    process: bool = False
    cpus: frozenset[int] = field(default_factory=frozenset)


_hosting = Hosting()


def hosting_now() -> Hosting:
    """How I/O workers started now are hosted (set around a loop's `open`)."""
    return _hosting


@contextlib.contextmanager
def hosting(process: bool, cpus: frozenset[int] | set[int] = frozenset()) -> Iterator[None]:
    """Workers started inside run in child processes (`process`) or threads."""
    global _hosting
    was = _hosting
    _hosting = Hosting(process, frozenset(cpus))
    try:
        yield
    finally:
        _hosting = was


class ChildGone(Exception):
    """The child process has exited, or did not answer in time."""


def _set_name(name: str) -> None:
    """The process name `ps` and `top` show (15 bytes)."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL when the parent dies (PR_SET_PDEATHSIG): a daemon killed with -9 takes its
    children along, as it would its threads (no late rows written after it)."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:  # it died before the signal was armed
        os._exit(0)


def _normal_scheduling(avoid: frozenset[int]) -> None:
    """Normal priority, on every CPU but the cycle's (when that leaves any)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    n = os.cpu_count() or 1
    cpus = set(range(n)) - set(avoid) or set(range(n))
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, cpus)


def exit_text(code: int | None) -> str:
    """A reaped child's end in words: "exited with code 1", "killed by SIGKILL"."""
    if code is None:
        return "ended"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


class Heartbeat:
    """A child's heartbeat as its parent watches it (compd.io.supervisor): `beat`, a counter
    in memory shared with the child, which bumps it at every turn of its loop; silent for
    longer than `stall_after_s`, the child has stalled (stopped, or hung in a call)."""

    def __init__(self, beat: Any, stall_after_s: float) -> None:
        self.beat = beat  # a one-element int64 array in shared memory
        self.stall_after_s = stall_after_s
        self._seen = -1  # the count last seen, and when (monotonic s)
        self._seen_s = 0.0

    def reset(self, now_s: float) -> None:
        """A child (re)started now: its silence counts from here."""
        self._seen, self._seen_s = -1, now_s

    def health(self, child: Child, now_s: float) -> str | None:
        """None while `child` runs and beats; else why not: "killed by SIGKILL", "exited with
        code 1", "stopped beating for 2.1 s" (reaps a child that ended)."""
        beat = int(self.beat[0])
        if beat != self._seen:
            self._seen, self._seen_s = beat, now_s
        if not child.alive():
            return exit_text(child.exit_code)
        silent_s = now_s - self._seen_s
        return f"stopped beating for {silent_s:.1f} s" if silent_s > self.stall_after_s else None


class Child:
    """A forked child running `serve(child)` (see the module). In the parent: `start`,
    `call`, `alive`, `stop`; in the child: `send` (replies, sent by `serve_calls`)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.pid: int | None = None
        self.exit_code: int | None = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()  # parent: one call on the pipe at a time
        self._seq = itertools.count(1)
        self._gone = False

    # ------------------------------------------------------------ parent
    def start(
        self,
        serve: Callable[[Child], None],
        avoid_cpus: frozenset[int] = frozenset(),
        keep_fds: Iterable[int] = (),
    ) -> None:
        """Fork; the child runs `serve(self)` and exits when it returns. The child keeps of
        its inherited file descriptors only stdio, its pipe and `keep_fds`."""
        keep = set(keep_fds)
        mine, theirs = Pipe(duplex=True)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        parent_pid = os.getpid()
        pid = os.fork()
        if pid == 0:  # the child
            code = 0
            try:
                mine.close()
                self._conn = theirs
                self._in_child(parent_pid, avoid_cpus, keep | {0, 1, 2, theirs.fileno()})
                serve(self)
            except BaseException:
                code = 1
                with contextlib.suppress(Exception):
                    log.exception(
                        "%s process failed", self.name, extra={"event": "io_process_failed", "worker": self.name}
                    )
            finally:
                with contextlib.suppress(Exception):
                    logging.shutdown()  # the child's own handlers: flush what it logged
                os._exit(code)
        theirs.close()
        self.pid = pid
        self._conn = mine
        self._gone = False

    def alive(self) -> bool:
        """Whether the child still runs (reaps it when it has exited)."""
        if self.pid is None or self.exit_code is not None:
            return False
        try:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
        except ChildProcessError:
            self.exit_code = -1
            return False
        if pid == 0:
            return True
        self.exit_code = os.waitstatus_to_exitcode(status)
        return False

    def call(self, *msg: Any, timeout_s: float) -> Any:
        """Send `msg` to the child and read its answer; ChildGone when the child has exited
        or did not answer within `timeout_s`. Not for the cycle: it waits."""
        ok, value = self.wait_answer(self.begin(*msg), timeout_s)
        if not ok:
            raise value
        return value

    def wait_answer(self, seq: int, timeout_s: float) -> tuple[bool, Any]:
        """Wait for the answer to the call `begin` returned `seq` for: (ok, value; the exception
        when not ok); ChildGone when the child has exited or did not answer within `timeout_s`."""
        with self._lock:
            conn = self._conn
            if conn is None or self._gone:
                raise ChildGone(f"{self.name}: the process has exited")
            deadline = time.monotonic() + timeout_s
            while True:
                rest = deadline - time.monotonic()
                try:
                    if rest <= 0 or not conn.poll(min(rest, 0.5)):
                        if rest <= 0 or not self.alive():
                            raise ChildGone(f"{self.name}: no answer from the process")
                        continue
                    answer = conn.recv()
                except (EOFError, OSError) as e:
                    self._gone = True
                    raise ChildGone(f"{self.name}: the process has exited ({e or 'pipe closed'})") from None
                if answer[0] == "reply" and answer[1] == seq:  # an older call's late answer is passed over
                    return bool(answer[2]), answer[3]

    def begin(self, *msg: Any) -> int:
        """Send `msg` to the child without waiting for its answer (the cycle's thread, between
        cycles: a restart); `answer` tells later whether it came. ChildGone when the child has
        exited."""
        with self._lock:
            conn = self._conn
            if conn is None or self._gone:
                raise ChildGone(f"{self.name}: the process has exited")
            seq = next(self._seq)
            try:
                conn.send((seq, *msg))
            except (OSError, ValueError) as e:
                self._gone = True
                raise ChildGone(f"{self.name}: {e}") from None
            return seq

    def answer(self, seq: int) -> tuple[bool, Any] | None:
        """The answer to the call `begin` returned `seq` for, if it has come: (ok, value; the
        exception when not ok), else None. Never waits. ChildGone when the pipe is closed."""
        with self._lock:
            conn = self._conn
            if conn is None or self._gone:
                raise ChildGone(f"{self.name}: the process has exited")
            try:
                while conn.poll(0):
                    reply = conn.recv()
                    if reply[0] == "reply" and reply[1] == seq:
                        return bool(reply[2]), reply[3]
            except (EOFError, OSError) as e:
                self._gone = True
                raise ChildGone(f"{self.name}: the process has exited ({e or 'pipe closed'})") from None
        return None

    def stop(self, timeout_s: float) -> bool:
        """Wait up to `timeout_s` for the child to exit (after it was told to), then kill
        it; True when it exited by itself."""
        if self.pid is None:
            return True
        deadline = time.monotonic() + timeout_s
        clean = True
        while self.alive():
            if time.monotonic() >= deadline:
                clean = False
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(self.pid, 0)
                self.exit_code = -signal.SIGKILL
                break
            time.sleep(0.005)
        with self._lock:
            if self._conn is not None:
                with contextlib.suppress(OSError):
                    self._conn.close()
            self._conn = None
            self._gone = True
        return clean

    # ------------------------------------------------------------ child
    def _in_child(self, parent_pid: int, avoid_cpus: frozenset[int], keep_fds: set[int]) -> None:
        gc.freeze()
        for name in os.listdir("/proc/self/fd"):
            fd = int(name)
            if fd not in keep_fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
        for name in ("stdout", "stderr"):  # a stream on a descriptor just closed (a test's capture): fd 1, 2
            stream = getattr(sys, name)
            try:
                ok = stream.fileno() in keep_fds
            except (AttributeError, OSError, ValueError):
                ok = False
            if not ok:
                setattr(sys, name, open(1 if name == "stdout" else 2, "w", buffering=1, closefd=False))  # noqa: SIM115
        self.pid = None
        self._parent_pid = parent_pid
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _die_with_parent(parent_pid)
        with contextlib.suppress(ValueError, OSError):
            signal.set_wakeup_fd(-1)
        _set_name(f"compd:{self.name}")
        _normal_scheduling(avoid_cpus)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        activity.disable()

    def send(self, msg: Any) -> None:
        """In the child: a message to the parent (never raises: a gone parent is seen by `serve_calls`)."""
        with self._send_lock, contextlib.suppress(OSError, ValueError):
            assert self._conn is not None
            self._conn.send(msg)

    def serve_calls(self, answer: Callable[..., Any]) -> None:
        """In the child: answer the parent's calls with `answer(what, *args)` until it sends
        ("exit",) or goes away. An exception is sent back to the caller and raised there."""
        conn = self._conn
        assert conn is not None
        while True:
            if os.getppid() != self._parent_pid:
                return
            try:
                if not conn.poll(PARENT_CHECK_S):
                    continue
                msg = conn.recv()
            except (EOFError, OSError):
                return
            seq, what, *args = msg
            if what == "exit":
                self.send(("reply", seq, True, None))
                return
            try:
                value, ok = answer(what, *args), True
            except Exception as e:
                value, ok = e, False
            try:
                conn.send(("reply", seq, ok, value))
            except Exception as e:  # an answer that does not pickle
                self.send(("reply", seq, False, RuntimeError(f"{type(e).__name__}: {e}")))
