"""The mailboxes between the cycle and a worker: a published sample is a copy, whole; queued
writes keep their first place, the newest values win, a lost write goes back unless replaced."""

from __future__ import annotations

import threading

import numpy as np

from compd.frame import Frame, Quality
from compd.io.mailbox import Latest, Snapshot, WriteQueue


def test_snapshot_publishes_copies_and_copies_into_the_frame_slots() -> None:
    snap = Snapshot(2)
    frame = Frame(["x", "a", "b"])
    idx = frame.indices(["a", "b"], what="signal")
    stamps = snap.copy_to(frame, idx)
    assert np.isnan(frame.values[1:]).all() and (frame.quality[1:] == Quality.NO_DATA).all()
    assert (stamps == -np.inf).all() and snap.count == 0

    values = np.array([21.5, 22.5])
    quality = np.array([Quality.GOOD, Quality.BURNOUT], dtype=np.uint8)
    snap.publish(values, quality, 12.0)
    values[:] = 99.0  # the worker reuses its buffers: the published sample must not change
    quality[:] = Quality.COMMS_LOST
    stamps = snap.copy_to(frame, idx)
    assert frame.values[1:].tolist() == [21.5, 22.5]
    assert frame.quality[1:].tolist() == [Quality.GOOD, Quality.BURNOUT]
    assert frame.stamp_s[1:].tolist() == [12.0, 12.0] and stamps.tolist() == [12.0, 12.0]
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
