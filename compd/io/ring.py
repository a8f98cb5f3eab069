"""Messages between processes in shared memory: a ring that never makes its writer wait, and a blob of the newest bytes.

`MessageRing` carries plain Python values (pickled) from one writer to one reader:
the cycle hands its events, log rows and status snapshots to the service process
this way, and the service hands back the probes `compd probe` sent. The writer
copies the message into the ring and then moves the ring's head; the reader takes
everything up to the head and then moves the tail. Neither takes a lock or makes a
system call. A message that does not fit (the reader is behind, or gone) is dropped
and counted, never waited for. Made before a fork, the ring is shared with the
child; it works the same between two threads of one process.

`SharedBlob` holds the newest bytes one writer published (an I/O worker's status as
JSON), read by anyone through a seqlock like the mailboxes of compd.io.mailbox.

Both rely on stores reaching the other CPU in program order (x86-64).
"""

from __future__ import annotations

import pickle
from typing import Any

import numpy as np

from compd.io.mailbox import READ_TRIES, shared_buffer

_LEN = 4  # bytes of a message's length prefix


class MessageRing:
    """One writer, one reader; `capacity_bytes` of messages in flight at most."""

    def __init__(self, capacity_bytes: int = 1 << 20) -> None:
        self.capacity = capacity_bytes
        self._buf = shared_buffer(64 + capacity_bytes)
        # head (bytes written, ever), tail (bytes read, ever), messages put, messages dropped
        self._ctr = np.frombuffer(self._buf, dtype=np.int64, count=4)
        self._data = memoryview(self._buf)[64:]

    @property
    def put_count(self) -> int:
        return int(self._ctr[2])

    @property
    def dropped(self) -> int:
        """Messages the writer dropped because the ring was full."""
        return int(self._ctr[3])

    def pending(self) -> bool:
        """Whether a message waits to be taken (cheap: two numbers compared)."""
        return int(self._ctr[0]) != int(self._ctr[1])

    def put(self, value: Any) -> bool:
        """Writer: append `value` (pickled); False (and counted) when it does not fit. Never waits."""
        payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        need = _LEN + len(payload)
        ctr = self._ctr
        head = int(ctr[0])
        if need > self.capacity - (head - int(ctr[1])):
            ctr[3] += 1
            return False
        self._copy_in(head, len(payload).to_bytes(_LEN, "little"))
        self._copy_in(head + _LEN, payload)
        ctr[0] = head + need  # publish: the reader sees the whole message or none of it
        ctr[2] += 1
        return True

    def take(self, limit: int | None = None) -> list[Any]:
        """Reader: the messages put since the last call, oldest first (at most `limit`)."""
        ctr = self._ctr
        head, tail = int(ctr[0]), int(ctr[1])
        out: list[Any] = []
        while tail < head and (limit is None or len(out) < limit):
            n = int.from_bytes(self._copy_out(tail, _LEN), "little")
            if n < 0 or tail + _LEN + n > head:  # cannot happen with one writer: never read past the head
                raise RuntimeError("message ring corrupted")
            raw = self._copy_out(tail + _LEN, n)
            tail += _LEN + n
            ctr[1] = tail  # free the space before unpickling (which may be slow)
            out.append(pickle.loads(raw))
        return out

    def _copy_in(self, pos: int, data: bytes) -> None:
        i = pos % self.capacity
        k = min(len(data), self.capacity - i)
        self._data[i : i + k] = data[:k]
        if k < len(data):
            self._data[: len(data) - k] = data[k:]

    def _copy_out(self, pos: int, n: int) -> bytes:
        i = pos % self.capacity
        k = min(n, self.capacity - i)
        if k == n:
            return bytes(self._data[i : i + n])
        return bytes(self._data[i : i + k]) + bytes(self._data[: n - k])


class SharedBlob:
    """The newest bytes (up to `capacity`) one writer published; read by anyone, never waiting."""

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._buf = shared_buffer(16 + capacity)
        self._head = np.frombuffer(self._buf, dtype=np.int64, count=2)  # sequence number, length
        self._data = memoryview(self._buf)[16:]

    @property
    def version(self) -> int:
        """Changes with every publish (even: no write under way)."""
        return int(self._head[0])

    def publish(self, data: bytes) -> None:
        if len(data) > self.capacity:
            raise ValueError(f"{len(data)} bytes do not fit in a blob of {self.capacity}")
        head = self._head
        head[0] += 1
        self._data[: len(data)] = data
        head[1] = len(data)
        head[0] += 1

    def read(self) -> bytes | None:
        """The newest bytes, or None when nothing was published (or the writer died mid-write)."""
        head = self._head
        for _ in range(READ_TRIES):
            seq = int(head[0])
            if seq & 1:
                continue
            n = int(head[1])
            data = bytes(self._data[:n])
            if int(head[0]) == seq:
                return data if seq else None
        return None
