"""The I/O worker's life cycle: start and stop (joined), open errors raised at start, reconnect
with back-off, errors counted, requests and wakes, a stop during back-off, a restart. No test
here measures speed: every wait is for a condition, with a generous timeout."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from compd.core.errors import BadInput
from compd.io.worker import DeviceWork, IoWorker, LinkDown

WAIT_S = 20.0  # generous: the machine may be busy


class Scripted(DeviceWork):
    """Device work that fails its first `connect_failures` connects and raises the rounds'
    outcomes in `round_script` ("ok", "down", "bug"; "ok" once the script is used up)."""

    def __init__(self, connect_failures: int = 0, round_script: list[str] | None = None) -> None:
        super().__init__()
        self.connect_failures = connect_failures
        self.round_script = list(round_script or [])
        self.connect_calls = 0
        self.disconnects = 0
        self.closes = 0
        self.rounds: list[Any] = []
        self.offline_calls: list[Any] = []
        self.threads: set[str] = set()
        self.worker: IoWorker | None = None
        self.retry_seen: list[float] = []  # the worker's retry_in_s at each connect

    def connect(self) -> None:
        self.threads.add(threading.current_thread().name)
        self.connect_calls += 1
        if self.worker is not None:
            self.retry_seen.append(self.worker.retry_in_s)
        if self.connect_calls <= self.connect_failures:
            raise LinkDown(f"refused #{self.connect_calls}")

    def disconnect(self) -> None:
        self.disconnects += 1

    def close(self) -> None:
        self.threads.add(threading.current_thread().name)
        self.closes += 1

    def round(self, request: Any) -> Any:
        self.threads.add(threading.current_thread().name)
        self.rounds.append(request)
        step = self.round_script.pop(0) if self.round_script else "ok"
        if step == "down":
            raise LinkDown("link lost")
        if step == "bug":
            raise ZeroDivisionError("driver bug")
        return ("reply", request)

    def offline(self, request: Any) -> Any:
        self.offline_calls.append(request)
        return ("offline", request)

    def counters(self) -> dict[str, Any]:
        return {"my_rounds": len(self.rounds)}


def _worker(work: Scripted, **kw: Any) -> IoWorker:
    w = IoWorker(work, name="t", **kw)
    work.worker = w
    return w


def test_start_runs_rounds_on_its_own_thread_and_stop_joins_it() -> None:
    work = Scripted()
    w = _worker(work, period_s=0.005)
    assert w.state == "closed" and not w.running
    w.start()
    try:
        assert w.wait_for(lambda: w.rounds >= 3, WAIT_S)
        assert w.state == "up" and w.connects == 1 and w.errors == 0
        assert w.round_hist.count >= 3
        st = w.get_status()
        assert st["state"] == "up" and st["my_rounds"] >= 3 and st["last_error"] is None
        assert all(r is None for r in work.rounds)  # paced rounds carry no request
    finally:
        assert w.stop() is True
    assert not w.running and w.state == "closed"
    assert work.closes == 1
    assert work.threads == {"t"}  # connect, rounds and close all ran on the worker's thread


def test_start_twice_is_refused() -> None:
    w = _worker(Scripted(), period_s=0.01)
    w.start()
    try:
        with pytest.raises(RuntimeError, match="running already"):
            w.start()
    finally:
        w.stop()


def test_an_open_error_is_raised_by_start_and_leaves_no_thread() -> None:
    class NoBus(Scripted):
        def open(self) -> None:
            raise BadInput("cannot open CAN channel 'can9'", path=("sources", 0, "channel"))

    w = _worker(NoBus(), period_s=0.01)
    with pytest.raises(BadInput, match="can9"):
        w.start()
    assert not w.running and w.state == "closed"
    assert w.stop() is True  # nothing to stop


def test_connect_failures_back_off_doubling_up_to_the_maximum_then_reset() -> None:
    """Five refused connects, then the link comes up, a round loses it once, and it comes
    up again: the wait before each connect doubles from the minimum to the maximum, and
    starts from the minimum again after a round went through."""
    work = Scripted(connect_failures=5, round_script=["ok", "down"])
    w = _worker(work, period_s=0.001, reconnect_min_s=0.001, reconnect_max_s=0.004)
    w.start()
    try:
        assert w.wait_for(lambda: len(work.rounds) >= 4, WAIT_S)
    finally:
        w.stop()
    assert work.connect_calls == 7
    # waits before connect 2…6 (after refusals 1…5), then before connect 7 (after the lost link)
    assert work.retry_seen[1:] == [0.001, 0.002, 0.004, 0.004, 0.004, 0.001]
    assert w.connects == 2
    assert w.errors == 6  # five refused connects, one lost link
    assert work.disconnects == 1  # after the lost link
    assert work.offline_calls  # paced rounds while down were offline rounds
    assert work.last_error == "link lost"


def test_a_driver_bug_in_a_round_is_counted_and_the_worker_goes_on() -> None:
    work = Scripted(round_script=["bug"])
    w = _worker(work, period_s=0.001, reconnect_min_s=0.001, reconnect_max_s=0.001)
    w.start()
    try:
        assert w.wait_for(lambda: w.rounds >= 2, WAIT_S)
    finally:
        w.stop()
    assert w.errors == 1 and w.connects == 2  # treated as a lost link: reconnected
    assert work.last_error == "ZeroDivisionError: driver bug"


def test_stop_during_back_off_does_not_wait_for_the_back_off() -> None:
    """The device refuses; the next connect is 60 s away. `stop` wakes the thread out of its
    back-off wait: it joins within the join timeout (5 s), far less than the back-off."""
    work = Scripted(connect_failures=10**6)
    w = _worker(work, period_s=None, reconnect_min_s=60.0, reconnect_max_s=60.0, join_timeout_s=5.0)
    w.start()
    assert w.wait_for(lambda: work.connect_calls == 1 and w.state == "down", WAIT_S)
    assert w.retry_in_s == 60.0
    assert w.stop() is True
    assert work.connect_calls == 1 and w.state == "closed"


def test_requests_get_the_rounds_reply_or_the_offline_reply() -> None:
    work = Scripted()
    w = _worker(work, period_s=0.01)
    assert w.request("early") is None  # not running
    w.start(paced=False)  # rounds only when asked
    try:
        assert w.request(("read", 3), timeout_s=WAIT_S) == ("reply", ("read", 3))
        assert w.request(7.5, timeout_s=WAIT_S) == ("reply", 7.5)
        assert work.rounds == [("read", 3), 7.5]  # no round of its own in between
    finally:
        w.stop()
    down = Scripted(connect_failures=10**6)
    w2 = _worker(down, reconnect_min_s=60.0, reconnect_max_s=60.0)
    w2.start(paced=False)
    try:
        assert w2.request("x", timeout_s=WAIT_S) == ("offline", "x")
    finally:
        w2.stop()
    assert down.rounds == []


def test_wake_runs_a_round_of_an_unpaced_worker() -> None:
    work = Scripted()
    w = _worker(work, period_s=None)
    w.start()
    try:
        assert w.wait_for(lambda: w.connects == 1, WAIT_S)
        assert w.rounds == 0  # nothing asked yet
        w.wake()
        assert w.wait_for(lambda: w.rounds == 1, WAIT_S)
        w.wake()
        assert w.wait_for(lambda: w.rounds == 2, WAIT_S)
    finally:
        w.stop()


def test_a_stopped_worker_starts_again() -> None:
    work = Scripted()
    w = _worker(work, period_s=0.002)
    for _ in range(2):
        w.start()
        n = w.rounds
        assert w.wait_for(lambda n=n: w.rounds >= n + 2, WAIT_S)
        assert w.stop() is True
    assert work.closes == 2 and w.connects == 2


def test_stop_reports_a_round_stuck_in_the_device_and_it_ends_by_itself() -> None:
    release = threading.Event()
    entered = threading.Event()

    class Stuck(Scripted):
        def round(self, request: Any) -> Any:
            entered.set()
            release.wait(WAIT_S)
            return super().round(request)

    work = Stuck()
    w = _worker(work, period_s=0.001)
    w.start()
    try:
        assert entered.wait(WAIT_S)
        assert w.stop(timeout_s=0.05) is False  # still in the device call
        assert w.running
    finally:
        release.set()
    assert w.stop() is True
    assert work.closes == 1 and w.state == "closed"
