"""Who ran Python when the cycle was late: spans of each thread's work, and the late cycles, for the bench.

Off unless `enable()` is called before the threads start (the bench does; a daemon
does not). Then every I/O worker's round and every status or log write marks its
span (`perf_counter_ns` start and end) in a preallocated ring of its own, and the
loop marks each cycle that woke more than `late_ns` after its deadline: the span
from the deadline to the first bytecode of the cycle. A thread whose span overlaps
a late cycle's was running Python (or waiting in a device call, which releases the
GIL) while the cycle thread waited: `attribute` counts, per thread, the late cycles
it overlapped, and how many overlapped no one (the wait was the kernel's or the
host's, not another thread's Python). On the wall clock the I/O and the service run in
processes of their own and the loop's process has no other thread: what delayed a cycle
is then the kernel's or the host's, which `rig.late_trace` tells apart from a kernel trace.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

SPANS = 1 << 16  # spans kept per thread (a few minutes of 2 ms rounds)
LATE = "cycle"  # the ring of the late cycles: from the deadline to the cycle's first bytecode
SLOW = "cycle-slow"  # the ring of the cycles whose own work took longer than the threshold

_enabled = False
_late_ns = 0
_rings: dict[str, Ring] = {}
_lock = threading.Lock()


class Ring:
    """The last SPANS (start, end) spans of one thread, perf_counter_ns; written by that thread only."""

    def __init__(self, n: int = SPANS) -> None:
        self.start_ns = np.full(n, 0, dtype=np.int64)  # written now: no page fault when marking
        self.end_ns = np.full(n, 0, dtype=np.int64)
        self.n = n
        self.count = 0

    def mark(self, start_ns: int, end_ns: int) -> None:
        i = self.count % self.n
        self.start_ns[i] = start_ns
        self.end_ns[i] = end_ns
        self.count += 1

    def spans(self) -> tuple[np.ndarray, np.ndarray]:
        k = min(self.count, self.n)
        return self.start_ns[:k], self.end_ns[:k]


def enable(late_us: float) -> None:
    """Record from now on: spans of threads that start after this, cycles late by more than `late_us`."""
    global _enabled, _late_ns
    with _lock:
        _enabled = True
        _late_ns = int(late_us * 1000)
        _rings.clear()


def disable() -> None:
    global _enabled
    _enabled = False


def ring(name: str) -> Ring | None:
    """The ring a thread named `name` marks its spans in, or None when recording is off."""
    if not _enabled:
        return None
    with _lock:
        r = _rings.get(name)
        if r is None:
            r = _rings[name] = Ring()
        return r


def spans(name: str) -> tuple[list[int], list[int]]:
    """The (start, end) perf_counter_ns of the spans kept in ring `name` (empty when none)."""
    with _lock:
        r = _rings.get(name)
    if r is None:
        return [], []
    s, e = r.spans()
    return s.tolist(), e.tolist()


def late_threshold_ns() -> int:
    """Cycles later than this are marked (0: recording is off)."""
    return _late_ns if _enabled else 0


def attribute() -> dict[str, Any]:
    """Per thread, the late cycles (ring "cycle") whose wait overlapped one of its spans."""
    with _lock:
        rings = dict(_rings)
    late = rings.pop(LATE, None)
    rings.pop(SLOW, None)
    if late is None or late.count == 0:
        return {"late_cycles": 0, "threshold_us": _late_ns / 1000, "overlapping": {}, "overlapping_none": 0}
    d0, w0 = late.spans()
    hit_any = np.zeros(d0.shape[0], dtype=bool)
    out: dict[str, int] = {}
    for name, r in sorted(rings.items()):
        s, e = r.spans()
        if s.size == 0:
            continue
        order = np.argsort(s)
        s, e = s[order], e[order]
        # spans that started before the cycle woke and ended after its deadline
        last = np.searchsorted(s, w0, side="left")  # spans [0, last) started before the wake
        emax = np.maximum.accumulate(e)
        hit = (last > 0) & (emax[np.maximum(last - 1, 0)] > d0)
        out[name] = int(hit.sum())
        hit_any |= hit
    waits_us = (w0 - d0) / 1000.0
    return {
        "late_cycles": int(d0.shape[0]),
        "threshold_us": _late_ns / 1000,
        "late_wait_us": {"p50": float(np.percentile(waits_us, 50)), "max": float(waits_us.max())},
        "overlapping": out,
        "overlapping_none": int((~hit_any).sum()),
    }
