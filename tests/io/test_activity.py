"""compd.io.activity: late cycles matched with the spans of other threads' work (the bench's attribution)."""

from __future__ import annotations

import pytest

from compd.io import activity


@pytest.fixture()
def recording():
    activity.enable(late_us=100.0)
    yield
    activity.disable()


def test_off_unless_enabled():
    activity.disable()
    assert activity.ring("anything") is None and activity.late_threshold_ns() == 0


def test_late_cycles_are_counted_per_thread_that_overlapped_them(recording):
    assert activity.late_threshold_ns() == 100_000
    cycle, poller, status = activity.ring("cycle"), activity.ring("poller"), activity.ring("compd-status")
    # three late cycles: waits [1000, 1500], [5000, 5400], [9000, 9300] ns
    for d, w in ((1000, 1500), (5000, 5400), (9000, 9300)):
        cycle.mark(d, w)
    poller.mark(800, 1100)  # overlaps the first
    poller.mark(2000, 4000)  # overlaps none
    poller.mark(5300, 6000)  # overlaps the second
    status.mark(100, 900)  # ended before the first deadline
    status.mark(4000, 8000)  # overlaps the second
    out = activity.attribute()
    assert out["late_cycles"] == 3
    assert out["overlapping"] == {"compd-status": 1, "poller": 2}
    assert out["overlapping_none"] == 1  # the third: the kernel's or the host's wait
    assert out["late_wait_us"]["max"] == pytest.approx(0.5)


def test_a_ring_keeps_its_newest_spans():
    r = activity.Ring(4)
    for k in range(6):
        r.mark(k, k + 1)
    s, e = r.spans()
    assert sorted(s.tolist()) == [2, 3, 4, 5] and sorted(e.tolist()) == [3, 4, 5, 6]


def test_no_late_cycle(recording):
    activity.ring("poller").mark(0, 10)
    assert activity.attribute()["late_cycles"] == 0
