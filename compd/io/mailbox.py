"""What crosses between the cycle and an I/O worker: plain data in mailboxes that never make the cycle wait.

Worker → cycle: `Snapshot` (the newest sample of n signals: value, quality and stamp
each) and `Latest` (the newest value of anything else: status registers, a plant
time). The worker publishes a new immutable object with one reference store, so a
reader sees the old sample or the new one, whole, and never takes a lock.

Cycle → worker: `WriteQueue` (register writes). The cycle appends and wakes the
worker (a deque append and an eventfd write: no lock the worker could hold); the
worker takes the writes in order of first submission, newest values per address.

Everything put in or taken out is plain data (numbers, lists of register values), so
the same interface can later be carried between processes (shared memory, a pipe)
without the sources and sinks that use it changing.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Sequence
from typing import Generic, TypeVar

import numpy as np

from compd.frame import Frame, Quality

T = TypeVar("T")


class Snapshot:
    """The newest sample of `n` signals; written by one worker, read by the cycle."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._sample = (np.full(n, np.nan), np.full(n, Quality.NO_DATA, dtype=np.uint8), np.full(n, -np.inf))
        self.count = 0  # samples published

    def publish(self, values: np.ndarray, quality: np.ndarray, stamp_s: float | np.ndarray) -> None:
        """Worker side: publish copies of `values`, `quality` and the stamps (one loop-clock
        time for all signals, or one per signal)."""
        stamps = np.full(self.n, float(stamp_s)) if np.ndim(stamp_s) == 0 else np.array(stamp_s, dtype=float)
        self._sample = (np.array(values, dtype=float), np.array(quality, dtype=np.uint8), stamps)
        self.count += 1

    def sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(values, quality, stamps) of the newest sample, read only."""
        return self._sample

    def copy_to(self, frame: Frame, idx: np.ndarray) -> np.ndarray:
        """Cycle side: copy the newest sample into the frame's slots `idx` (no lock, no wait);
        returns its stamps (read only)."""
        values, quality, stamps = self._sample
        frame.values[idx] = values
        frame.quality[idx] = quality
        frame.stamp_s[idx] = stamps
        return stamps


class Latest(Generic[T]):
    """The newest value of something a worker reads (keep it immutable: a tuple, not a list
    that is changed later); reading never waits."""

    def __init__(self, value: T) -> None:
        self.value = value
        self.count = 0  # values published

    def publish(self, value: T) -> None:
        self.value = value
        self.count += 1


class WriteQueue:
    """Register writes from the cycle to a worker. A newer write to an address replaces one
    not yet sent (it keeps the place of the first); a write that failed on the way is put
    back unless a newer one replaced it meanwhile.

    Cycle side: `submit`, `pending`. Worker side: `take`, `done`. Anyone but the cycle:
    `wait_empty`.
    """

    def __init__(self, wake: Callable[[], None] | None = None) -> None:
        self._in: collections.deque[tuple[int, list[int], int]] = collections.deque()
        self._queued: dict[int, tuple[list[int], int]] = {}  # worker's: address → (values, queued at, ns)
        self._holding = False  # the worker holds writes not yet acknowledged
        self.wake = wake  # tells the worker there is something to send
        self._changed = threading.Condition()

    def submit(self, address: int, values: Sequence[int]) -> None:
        """Queue a write (never waits)."""
        self._in.append((address, [v & 0xFFFF for v in values], time.perf_counter_ns()))
        if self.wake is not None:
            self.wake()

    def pending(self) -> bool:
        """Whether a write is queued or on its way (not yet acknowledged by the device)."""
        return bool(self._in) or self._holding

    def take(self) -> tuple[int, list[int], int] | None:
        """Worker side: the next write (address, values, queued at ns), or None when every
        write so far is acknowledged."""
        self._holding = True  # before anything leaves _in: `pending` never misses a write
        while self._in:
            address, values, queued_ns = self._in.popleft()
            self._queued[address] = (values, queued_ns)
        if not self._queued:
            self._holding = False
            with self._changed:
                self._changed.notify_all()
            return None
        address = next(iter(self._queued))
        values, queued_ns = self._queued.pop(address)
        return address, values, queued_ns

    def done(self, write: tuple[int, list[int], int], sent: bool) -> None:
        """Worker side: `write` (from `take`) was acknowledged (or refused by the device:
        `sent` True all the same), or was lost on the way (`sent` False: it goes back)."""
        if not sent:
            while self._in:
                address, values, queued_ns = self._in.popleft()
                self._queued[address] = (values, queued_ns)
            self._queued.setdefault(write[0], (write[1], write[2]))

    def wait_empty(self, timeout_s: float) -> bool:
        """Until every write so far has been acknowledged (True), or `timeout_s` (False)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while self.pending():
                rest = deadline - time.monotonic()
                if rest <= 0:
                    return False
                self._changed.wait(min(rest, 0.05))
        return True

    def clear(self) -> None:
        """Drop every write not yet sent (the worker has stopped)."""
        self._in.clear()
        self._queued.clear()
        self._holding = False
