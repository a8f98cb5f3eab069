"""The data log's writer: rows from the cycle written, flushed, rotated and repaired by a thread of the service."""

from __future__ import annotations

import contextlib
import os
import queue
from collections.abc import Sequence
from pathlib import Path

from compd.io import activity
from compd.log import Repair, _fmt, _fmt_t, _set_aside_whole, log, repair_log
from compd.service.threads import ServiceThread


class LogWriter:
    """Writes log rows from a background thread so the cycle never waits on the disk.

    The cycle calls `push(row)` with a tuple of floats (allocated only at the log
    period, not every cycle). The thread formats rows into a pending buffer and
    writes, then fsyncs, it at least every `flush_s`, so a `kill -9` loses at most
    the rows of the last `flush_s`. `close()` drains what is queued.

    Rotation: when the file reaches `rotate_bytes`, or has been written for
    `rotate_s`, it is renamed `<name>.1` (older ones shift to `.2` … `.keep`, the
    oldest is deleted) and a new file with the header starts; every file is a
    complete log.

    Disk errors (full disk, file gone) never reach the loop: the rows of a failed
    write are dropped and counted (`rows_dropped`), a partial row is cut off again
    (the file stays a valid CSV), `error` says why, one `event=log_error` line is
    logged when writing starts failing and one `event=log_ok` when it works again.
    A file that a crash or a power cut damaged is repaired when it is opened again
    (`repair_log`: the damage goes to a `<name>.damaged-<time>` side file, the
    complete rows stay); one written with other columns is set aside whole.
    """

    max_pending_rows = 100_000  # while the disk is full, older unwritten rows are dropped

    def __init__(
        self,
        path: str | Path,
        columns: Sequence[str],
        flush_s: float = 1.0,
        *,
        rotate_bytes: int | None = None,
        rotate_s: float | None = None,
        keep: int = 5,
    ) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.flush_s = flush_s
        self.rotate_bytes = rotate_bytes
        self.rotate_s = rotate_s
        self.keep = keep
        self.rows_written = 0
        self.rows_dropped = 0
        self.rotations = 0
        self.flushes = 0  # flush turns of the writer's thread, idle ones included
        self.repaired_bytes = 0  # bytes of crash damage moved to side files (repair_log)
        self.repairs: list[Repair] = []
        self.error: str | None = None
        self._header = (",".join(self.columns) + "\n").encode()
        self._q: queue.SimpleQueue[tuple[float, ...] | None] = queue.SimpleQueue()
        self._pending: list[bytes] = []
        self._fd: int | None = None
        self._size = 0
        self._opened_s = 0.0
        self._open()
        self._thread = ServiceThread("compd-log", self._run)
        self._thread.start()

    def push(self, row: tuple[float, ...]) -> None:
        self._q.put(row)

    # ------------------------------------------------------------------ file
    def _open(self) -> bool:
        """Open (or create) the file for appending, after repairing what a crash left; queue the header."""
        import time

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.exists():
                self._recover()
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        except OSError as e:
            # never append to a file that could not be repaired: rows are dropped, counted, retried
            self._fail(f"cannot open log: {e.strerror or e}", 0)
            return False
        self._fd = fd
        try:
            self._size = os.fstat(fd).st_size
        except OSError:
            self._size = 0
        if self._size == 0:
            self._pending.insert(0, self._header)
        self._opened_s = time.monotonic()
        return True

    def _recover(self) -> None:
        """Repair a crash's damage (`repair_log`); set aside a file written with other columns."""
        r = repair_log(self.path)
        if r.action != "none":
            self.repaired_bytes += r.bytes_set_aside
            self.repairs.append(r)
            r.log_event()
        if r.header is not None and r.header != self._header:
            # written with other columns (the config changed): set it aside whole, start anew
            if self.keep > 0:
                self._shift()
            else:  # no rotated files are kept, but this one is not rotation's to delete
                _set_aside_whole(self.path, "columns")
            if self.path.exists():
                raise OSError(f"cannot set aside {self.path.name} (written with other columns)")

    def _shift(self) -> None:
        """`<name>` → `<name>.1` → `<name>.2` … (at most `keep`; with keep 0 it is deleted)."""
        try:
            for k in range(self.keep - 1, 0, -1):
                older = self.path.with_name(f"{self.path.name}.{k}")
                if older.exists():
                    os.replace(older, self.path.with_name(f"{self.path.name}.{k + 1}"))
            if self.keep > 0:
                os.replace(self.path, self.path.with_name(f"{self.path.name}.1"))
            else:
                self.path.unlink()
        except OSError as e:
            self._fail(f"log rotation failed: {e.strerror or e}", 0)

    def _rotate(self) -> None:
        """Rename the full file away (`.1`, shifting older ones) and start a new one."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        self._shift()
        self.rotations += 1
        self._open()

    def _due_rotation(self, now_s: float) -> bool:
        if self._fd is None or self._size <= len(self._header):
            return False
        if self.rotate_bytes is not None and self._size >= self.rotate_bytes:
            return True
        return self.rotate_s is not None and now_s - self._opened_s >= self.rotate_s

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        import time

        spans = activity.ring("compd-log")  # None unless the bench records who runs when
        last_flush = time.monotonic()
        while True:
            try:
                row = self._q.get(timeout=self.flush_s)
            except queue.Empty:
                row = ()
            if row is None:
                break
            t0 = time.perf_counter_ns()
            if row:
                self._pending.append((_fmt_t(row[0]) + "".join("," + _fmt(v) for v in row[1:]) + "\n").encode())
                if len(self._pending) > self.max_pending_rows:
                    del self._pending[: len(self._pending) // 2]
                    self.rows_dropped += self.max_pending_rows // 2
            now = time.monotonic()
            if now - last_flush >= self.flush_s:
                self._flush(now)
                self.flushes += 1
                last_flush = now
            if spans is not None:
                spans.mark(t0, time.perf_counter_ns())
        self._flush(time.monotonic())

    def _flush(self, now_s: float) -> None:
        """Write the pending rows in one go and fsync; on failure cut any partial write. A file
        due for rotation is rotated when rows are about to be written, never by an idle flush:
        the current file is never left empty of the rows already logged (with `keep: 0` the
        rotated file is deleted, and an idle rotation would have left nothing)."""
        if self._pending and self._due_rotation(now_s):
            self._rotate()
        if self._fd is None and not self._open():
            self._drop_pending()
            return
        if not self._pending:
            return
        assert self._fd is not None
        data = b"".join(self._pending)
        rows = len(self._pending) - (1 if self._pending[0] is self._header else 0)
        try:
            written = 0
            while written < len(data):
                written += os.write(self._fd, data[written:])
            os.fsync(self._fd)
        except OSError as e:
            if written:
                with contextlib.suppress(OSError):  # keep the file a valid CSV: cut the partial write
                    os.ftruncate(self._fd, self._size)
            self._fail(f"log write failed: {e.strerror or e}", rows)
            self._pending.clear()
            return
        self._size += len(data)
        self.rows_written += rows
        self._pending.clear()
        if self.error is not None:
            log.info(
                "data log writes again: %s",
                self.path,
                extra={"event": "log_ok", "path": str(self.path), "rows_dropped": self.rows_dropped},
            )
            self.error = None

    def _drop_pending(self) -> None:
        rows = sum(1 for p in self._pending if p is not self._header)
        self.rows_dropped += rows
        self._pending = [p for p in self._pending if p is self._header]

    def _fail(self, reason: str, rows: int) -> None:
        self.rows_dropped += rows
        if self.error is None:
            log.error(
                "data log: %s (%s); compensation goes on, rows are dropped until it works again",
                reason,
                self.path,
                extra={"event": "log_error", "path": str(self.path), "reason": reason},
            )
        self.error = reason

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(10.0)
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError as e:
                self.error = f"log close failed: {e.strerror or e}"
            self._fd = None

    def get_status(self) -> dict[str, object]:
        return {
            "path": str(self.path),
            "rows_written": self.rows_written,
            "rows_dropped": self.rows_dropped,
            "rotations": self.rotations,
            "error": self.error,
        }
