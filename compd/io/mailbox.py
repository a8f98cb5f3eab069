"""What crosses between the cycle and an I/O worker: plain numbers in shared memory that never make the cycle wait.

Worker → cycle: `Snapshot` (the newest sample of n signals: value, quality and stamp
each), `SharedRegisters` (the newest block of registers a worker read, and when) and
`Latest` (the newest of anything else, within one process: a plant clock's time).

Cycle → worker: `WriteQueue` (register writes): the cycle stores the newest values per
register address and wakes the worker; the worker sends them in order of first
submission and acknowledges each.

`Snapshot`, `SharedRegisters`, `WriteQueue` and their counts live in an anonymous
shared mapping made before any fork, so the worker may run in the cycle's process (a
thread) or in a child of its own (`compd.io.child`) with nothing changed: no lock, no
pickling. Each record is a seqlock: its writer makes the sequence number odd, writes,
makes it even again; a reader copies and takes the copy only when the number was even
and unchanged across the copy, else copies again. One writer per record. This relies
on stores reaching the other CPU in program order, as x86-64 guarantees (the industrial
PCs compd runs on); a reader gives up after `READ_TRIES` torn copies (a writer that
died in the middle) and reports the signals lost instead of waiting.
"""

from __future__ import annotations

import mmap
import time
from collections.abc import Callable, Sequence
from typing import Generic, TypeVar

import numpy as np

from compd.core.frame import Frame, Quality

T = TypeVar("T")

READ_TRIES = 1000  # torn copies in a row before a reader gives up on a record


def shared_buffer(nbytes: int) -> mmap.mmap:
    """Zeroed memory shared with every child forked after this call. Every page is touched
    now: the cycle never takes a page fault on its first write to one (a ring that wraps
    round onto pages it has not used yet, a histogram bin never hit)."""
    buf = mmap.mmap(-1, max(nbytes, 1), flags=mmap.MAP_SHARED | mmap.MAP_ANONYMOUS)
    np.frombuffer(buf, dtype=np.uint8)[:: mmap.PAGESIZE] = 0
    return buf


class Snapshot:
    """The newest sample of `n` signals; written by one worker, read by the cycle."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._buf = shared_buffer(16 + 17 * n)
        # header: sequence number, samples published
        self._head = np.frombuffer(self._buf, dtype=np.int64, count=2)
        self._values = np.frombuffer(self._buf, dtype=np.float64, count=n, offset=16)
        self._stamps = np.frombuffer(self._buf, dtype=np.float64, count=n, offset=16 + 8 * n)
        self._quality = np.frombuffer(self._buf, dtype=np.uint8, count=n, offset=16 + 16 * n)
        self._values.fill(np.nan)
        self._stamps.fill(-np.inf)
        self._quality.fill(Quality.NO_DATA)
        self._lost = np.full(n, Quality.COMMS_LOST, dtype=np.uint8)

    @property
    def count(self) -> int:
        """Samples published."""
        return int(self._head[1])

    def publish(self, values: np.ndarray, quality: np.ndarray, stamp_s: float | np.ndarray) -> None:
        """Worker side: publish `values`, `quality` and the stamps (one loop-clock time for
        all signals, or one per signal), copied."""
        head = self._head
        head[0] += 1  # odd: being written
        self._values[:] = values
        self._quality[:] = quality
        self._stamps[:] = stamp_s
        head[1] += 1
        head[0] += 1

    def sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(values, quality, stamps) of the newest sample, copies."""
        head = self._head
        for _ in range(READ_TRIES):
            seq = int(head[0])
            if seq & 1 == 0:
                out = (self._values.copy(), self._quality.copy(), self._stamps.copy())
                if int(head[0]) == seq:
                    return out
        return (self._values.copy(), self._lost.copy(), self._stamps.copy())

    def copy_to(self, frame: Frame, idx: np.ndarray) -> float:
        """Cycle side: copy the newest sample into the frame's slots `idx` (no lock, no wait);
        returns the stamp of its first signal (-inf: none)."""
        head = self._head
        for _ in range(READ_TRIES):
            seq = int(head[0])
            if seq & 1 == 0:
                frame.values[idx] = self._values
                frame.quality[idx] = self._quality
                frame.stamp_s[idx] = self._stamps
                if int(head[0]) == seq:
                    return float(frame.stamp_s[idx[0]]) if self.n else -np.inf
        frame.quality[idx] = self._lost  # the writer died mid-sample: never a torn value
        return float(frame.stamp_s[idx[0]]) if self.n else -np.inf


class SharedRegisters:
    """The newest block of up to `n` registers a worker read (or None: not read yet), and
    when; written by one worker, read by anyone. `value` is `(registers | None, stamp)`."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._buf = shared_buffer(8 * 4 + 2 * n)
        # header: sequence number, values published, registers held (-1: none), stamp (f64)
        self._head = np.frombuffer(self._buf, dtype=np.int64, count=3)
        self._stamp = np.frombuffer(self._buf, dtype=np.float64, count=1, offset=24)
        self._regs = np.frombuffer(self._buf, dtype=np.uint16, count=n, offset=32)
        self._head[2] = -1
        self._stamp[0] = -1.0
        self._seen = -1
        self._value: tuple[list[int] | None, float] = (None, -1.0)

    @property
    def count(self) -> int:
        return int(self._head[1])

    def publish(self, value: tuple[Sequence[int] | None, float]) -> None:
        regs, stamp = value
        if regs is not None and len(regs) > self.n:
            raise ValueError(f"{len(regs)} registers do not fit in a block of {self.n}")
        head = self._head
        head[0] += 1
        if regs is None:
            head[2] = -1
        else:
            self._regs[: len(regs)] = regs
            head[2] = len(regs)
        self._stamp[0] = stamp
        head[1] += 1
        head[0] += 1

    @property
    def value(self) -> tuple[list[int] | None, float]:
        """The newest (registers, stamp); the same object until a new one is published."""
        head = self._head
        for _ in range(READ_TRIES):
            seq = int(head[0])
            if seq == self._seen:
                return self._value
            if seq & 1 == 0:
                k = int(head[2])
                regs = None if k < 0 else self._regs[:k].tolist()
                stamp = float(self._stamp[0])
                if int(head[0]) == seq:
                    self._seen, self._value = seq, (regs, stamp)
                    return self._value
        return self._value


class Latest(Generic[T]):
    """The newest value of something a worker thread reads, within one process (keep it
    immutable: a tuple, not a list that is changed later); reading never waits."""

    def __init__(self, value: T) -> None:
        self.value = value
        self.count = 0  # values published

    def publish(self, value: T) -> None:
        self.value = value
        self.count += 1


class Sync:
    """What a device held at each connect of a sink's link (compd.io.modbus_link), in memory
    shared with the link's worker: the connection's epoch, the registers read at its start (the
    held block), and the epoch the sink has taken.

    Worker side: `begin` (a connect: a new epoch, sending stops), `publish` (the held block read).
    Cycle side: `pending` (a held block not yet taken), `accept`, `accepted`. Nothing waits."""

    def __init__(self, ranges: Sequence[tuple[int, int]]) -> None:
        self.ranges = [(int(a), int(n)) for a, n in ranges]
        self._buf = shared_buffer(24)
        # the current epoch (0: none yet), the epoch whose held block is published, the epoch taken
        # (a memoryview of int64: reading one every cycle makes no numpy scalar)
        self._epochs = memoryview(self._buf).cast("q")
        self._held = SharedRegisters(sum(n for _, n in self.ranges))

    def begin(self) -> None:
        """Worker: a new connection; what was taken before no longer counts."""
        self._epochs[0] += 1

    def publish(self, regs: Sequence[int]) -> None:
        """Worker: the current epoch's held block."""
        e = int(self._epochs[0])
        self._held.publish((regs, float(e)))
        self._epochs[1] = e

    def pending(self) -> tuple[int, list[int]] | None:
        """Cycle: (epoch, held block) when the current epoch's block is read and not yet taken."""
        e = int(self._epochs[0])
        if e == 0 or int(self._epochs[1]) != e or int(self._epochs[2]) == e:
            return None
        regs, stamp = self._held.value
        if regs is None or int(stamp) != e or int(self._epochs[0]) != e:
            return None  # a newer connection began meanwhile: its block comes next
        return e, regs

    def accept(self, epoch: int) -> None:
        """Cycle: the sink reckons from `epoch`'s held block; the worker sends from now on."""
        self._epochs[2] = epoch

    def accepted(self) -> bool:
        """Whether the current epoch's block has been taken (what is submitted is sent)."""
        e = int(self._epochs[0])
        return e > 0 and int(self._epochs[2]) == e

    @property
    def epoch(self) -> int:
        return int(self._epochs[0])


class WriteQueue:
    """Register writes from the cycle to a worker: the newest values per address, sent in
    order of first submission. A newer write to an address replaces one not yet sent (it
    keeps the place of the first); a write that failed on the way stays queued unless a
    newer one replaced it meanwhile.

    One record per address (up to `max_addresses`, each up to `max_registers`): the
    cycle writes it and counts it (`written`), the worker counts what the device
    acknowledged (`acked`); the address is pending while the two differ.

    Cycle side (one submitting thread): `submit`, `pending`. Worker side: `take`, `done`.
    Anyone but the cycle: `wait_empty`, `clear` (the worker has stopped).
    """

    max_addresses = 32
    max_registers = 123  # a Modbus write carries at most 123 registers

    def __init__(self, wake: Callable[[], None] | None = None) -> None:
        n, m = self.max_addresses, self.max_registers
        self._buf = shared_buffer(8 * (6 * n + 2) + 2 * m * n)
        # per address: sequence (2 per write), acked sequence, order of first submission,
        # address, register count, queued at (perf_counter ns); then the order counter and
        # the records in use
        self._rec = np.frombuffer(self._buf, dtype=np.int64, count=6 * n).reshape(n, 6)
        self._orders = np.frombuffer(self._buf, dtype=np.int64, count=1, offset=48 * n)
        self._values = np.frombuffer(self._buf, dtype=np.uint16, count=n * m, offset=8 * (6 * n + 2)).reshape(n, m)
        self._slots: dict[int, int] = {}  # the cycle's: address → record
        self._n_used = np.frombuffer(self._buf, dtype=np.int64, count=1, offset=8 * (6 * n + 1))
        self._taken: dict[int, int] = {}  # the worker's: record → sequence on its way
        self.wake = wake  # tells the worker there is something to send

    def submit(self, address: int, values: Sequence[int]) -> None:
        """Queue a write (never waits)."""
        slot = self._slots.get(address)
        if slot is None:
            slot = len(self._slots)
            if slot >= self.max_addresses:
                raise ValueError(f"more than {self.max_addresses} register addresses written through one link")
            self._slots[address] = slot
            self._rec[slot, 3] = address
            self._n_used[0] = slot + 1
        if len(values) > self.max_registers:
            raise ValueError(f"a write of {len(values)} registers (at most {self.max_registers})")
        rec = self._rec[slot]
        seq = int(rec[0])
        if seq == int(rec[1]):  # nothing of this address is pending: it queues behind the others
            self._orders[0] += 1
            rec[2] = self._orders[0]
        rec[0] = seq + 1
        k = len(values)
        self._values[slot, :k] = [v & 0xFFFF for v in values]
        rec[4] = k
        rec[5] = time.perf_counter_ns()
        rec[0] = seq + 2
        if self.wake is not None:
            self.wake()

    def pending(self) -> bool:
        """Whether a write is queued or on its way (not yet acknowledged by the device)."""
        rec = self._rec[: int(self._n_used[0])]
        return bool(np.any(rec[:, 0] != rec[:, 1]))

    def take(self) -> tuple[int, list[int], int, int, int] | None:
        """Worker side: the next write (address, values, queued at ns, record, sequence), or
        None when nothing is queued that is not already on its way."""
        best = -1
        best_order = 0
        rec = self._rec
        for slot in range(int(self._n_used[0])):
            seq = int(rec[slot, 0])
            if seq == int(rec[slot, 1]) or self._taken.get(slot) == seq:
                continue
            order = int(rec[slot, 2])
            if best < 0 or order < best_order:
                best, best_order = slot, order
        if best < 0:
            return None
        r = rec[best]
        for _ in range(READ_TRIES):
            seq = int(r[0])
            if seq & 1:
                continue
            address, k, queued_ns = int(r[3]), int(r[4]), int(r[5])
            values = self._values[best, :k].tolist()
            if int(r[0]) == seq:
                self._taken[best] = seq
                return address, values, queued_ns, best, seq
        return None  # the cycle is writing it this very moment: the next round takes it

    def done(self, write: tuple[int, list[int], int, int, int], sent: bool) -> None:
        """Worker side: `write` (from `take`) was acknowledged (or refused by the device:
        `sent` True all the same), or was lost on the way (`sent` False: it stays queued)."""
        slot, seq = write[3], write[4]
        self._taken.pop(slot, None)
        if sent:
            self._rec[slot, 1] = seq

    def wait_empty(self, timeout_s: float) -> bool:
        """Until every write so far has been acknowledged (True), or `timeout_s` (False)."""
        deadline = time.monotonic() + timeout_s
        while self.pending():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.001)
        return True

    def clear(self) -> None:
        """Drop every write not yet sent (the worker has stopped)."""
        rec = self._rec
        rec[:, 1] = rec[:, 0]
        self._taken.clear()
