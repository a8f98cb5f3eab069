"""The mailboxes between the cycle and a worker: a published sample is a copy, whole, also across a
fork; queued writes keep their first place, the newest values win, a lost write goes back unless
replaced."""

from __future__ import annotations

import os
import threading

import numpy as np

from compd.core.frame import Frame, Quality
from compd.io.mailbox import READ_TRIES, Latest, SharedRegisters, Snapshot, WriteQueue


def test_snapshot_publishes_copies_and_copies_into_the_frame_slots() -> None:
    snap = Snapshot(2)
    frame = Frame(["x", "a", "b"])
    idx = frame.indices(["a", "b"], what="signal")
    stamp = snap.copy_to(frame, idx)
    assert np.isnan(frame.values[1:]).all() and (frame.quality[1:] == Quality.NO_DATA).all()
    assert stamp == -np.inf and snap.count == 0

    values = np.array([21.5, 22.5])
    quality = np.array([Quality.GOOD, Quality.BURNOUT], dtype=np.uint8)
    snap.publish(values, quality, 12.0)
    values[:] = 99.0  # the worker reuses its buffers: the published sample must not change
    quality[:] = Quality.COMMS_LOST
    stamp = snap.copy_to(frame, idx)
    assert frame.values[1:].tolist() == [21.5, 22.5]
    assert frame.quality[1:].tolist() == [Quality.GOOD, Quality.BURNOUT]
    assert frame.stamp_s[1:].tolist() == [12.0, 12.0] and stamp == 12.0
    assert np.isnan(frame.values[0])  # another source's slot untouched
    snap.publish(values, quality, np.array([13.0, 14.0]))  # one stamp per signal
    snap.copy_to(frame, idx)
    assert frame.stamp_s[1:].tolist() == [13.0, 14.0] and snap.count == 2


def test_latest_holds_the_newest_value() -> None:
    box: Latest[tuple[int, ...] | None] = Latest(None)
    assert box.value is None and box.count == 0
    box.publish((1, 2))
    box.publish((3, 4))
    assert box.value == (3, 4) and box.count == 2


def test_write_queue_newest_values_in_order_of_first_submission() -> None:
    wakes = []
    q = WriteQueue(wake=lambda: wakes.append(1))
    assert not q.pending() and q.take() is None
    q.submit(10, [1, 2])
    q.submit(20, [3])
    q.submit(10, [0x1_0005, 6])  # replaces the unsent write to 10, keeps its place
    assert len(wakes) == 3 and q.pending()
    w = q.take()
    assert w is not None and w[:2] == (10, [5, 6])
    q.done(w, sent=True)
    assert q.pending()  # 20 still queued
    w = q.take()
    assert w is not None and w[:2] == (20, [3])
    q.done(w, sent=True)
    assert q.take() is None and not q.pending()


def test_write_queue_a_lost_write_goes_back_unless_replaced() -> None:
    q = WriteQueue()
    q.submit(1, [7])
    w = q.take()
    assert w is not None
    q.done(w, sent=False)
    assert q.pending()
    again = q.take()
    assert again is not None and again[:2] == (1, [7])
    q.submit(1, [8])  # a newer write while the old one is on its way
    q.done(again, sent=False)
    newest = q.take()
    assert newest is not None and newest[:2] == (1, [8])
    q.done(newest, sent=True)
    assert q.take() is None and not q.pending()


def test_write_queue_wait_empty_returns_when_the_worker_has_sent_everything() -> None:
    q = WriteQueue()
    q.submit(3, [1])
    assert q.wait_empty(0.01) is False  # nobody is sending

    def worker() -> None:
        while (w := q.take()) is not None:
            q.done(w, sent=True)

    th = threading.Thread(target=worker)
    th.start()
    try:
        assert q.wait_empty(20.0) is True
    finally:
        th.join(20.0)
    q.submit(4, [2])
    q.clear()
    assert not q.pending() and q.wait_empty(0.0) is True


def _in_child(body) -> int:  # type: ignore[no-untyped-def]
    """Run `body()` in a forked child; its exit code (0: it returned)."""
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            body()
            code = 0
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def test_a_forked_worker_publishes_whole_samples_the_parent_reads() -> None:
    """The child publishes samples whose two values are always equal: the parent, reading
    while it writes, never sees a torn one (the seqlock), and sees the last one whole."""
    snap = Snapshot(2)
    regs = SharedRegisters(4)
    frame = Frame(["a", "b"])
    idx = frame.indices(["a", "b"], what="signal")
    n = 20_000
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(r)
            q = np.full(2, Quality.GOOD, dtype=np.uint8)
            for i in range(1, n + 1):
                snap.publish(np.array([i, i], dtype=float), q, float(i))
            regs.publish(([1, 2, 3], 5.0))
            code = 0
        finally:
            os.close(w)
            os._exit(code)
    os.close(w)
    seen = 0
    while seen < n:
        snap.copy_to(frame, idx)
        a, b = frame.values
        if frame.quality[0] == Quality.GOOD:
            assert a == b and frame.stamp_s[0] == a  # whole, never half of two samples
            seen = int(a)
    os.read(r, 1)  # the child has closed its end: it is done
    os.close(r)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    assert snap.count == n and regs.value == ([1, 2, 3], 5.0) and regs.count == 1


def test_a_reader_gives_up_on_a_sample_its_writer_left_half_written() -> None:
    snap = Snapshot(1)
    snap.publish(np.array([1.0]), np.array([Quality.GOOD], dtype=np.uint8), 1.0)
    snap._head[0] += 1  # the writer died between the two halves
    frame = Frame(["a"])
    snap.copy_to(frame, frame.indices(["a"], what="signal"))
    assert frame.quality[0] == Quality.COMMS_LOST and READ_TRIES > 1


def test_a_forked_worker_takes_and_acknowledges_the_cycles_writes() -> None:
    """Writes submitted in the parent are taken, in order, by a forked child; its
    acknowledgements are what `pending` and `wait_empty` see."""
    q = WriteQueue()
    q.submit(10, [1, 2])
    q.submit(20, [3])
    q.submit(10, [5, 6])
    sent = SharedRegisters(8)

    def child() -> None:
        order = []
        while (w := q.take()) is not None:
            order += [w[0], *w[1]]
            q.done(w, sent=True)
        sent.publish((order, 0.0))

    assert _in_child(child) == 0
    assert sent.value[0] == [10, 5, 6, 20, 3]
    assert not q.pending() and q.wait_empty(0.0)
    q.submit(10, [7])
    assert q.pending()
