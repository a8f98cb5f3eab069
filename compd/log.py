"""The log CSV of CONTRACT.md: read and validate it, and write it from a background thread."""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
import queue
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from compd.errors import BadInput

# |t_s| and the span of a log stay below this (≈ 317 years; Unix time is 1.8e9 s): float
# time keeps 2 µs resolution there, so every cycle and PLC scan still advances the clock.
MAX_T_S = 1e10
RESERVED_PREFIXES = ("err_", "pos_", "current_")
RESERVED_NAMES = ("t_s", "speed_rpm")
# Columns the loop itself writes into its log (compd.app.LogObserver): never inputs.
OUTPUT_PREFIXES = ("pred_", "corr_", "applied_")
OUTPUT_NAMES = ("word",)

log = logging.getLogger("compd.log")


def is_temperature_column(name: str) -> bool:
    """CONTRACT: any column but t_s, err_*, pos_*, speed_rpm, current_* is a temperature.

    compd's own output columns (pred_*, corr_*, applied_*, word) are excluded too, so
    a fit on a log that compd wrote does not take its own predictions as inputs.
    """
    return (
        name not in RESERVED_NAMES
        and name not in OUTPUT_NAMES
        and not name.startswith(RESERVED_PREFIXES)
        and not name.startswith(OUTPUT_PREFIXES)
    )


def error_axis(name: str) -> str | None:
    """`err_x1_um` → `x1`; None for other columns."""
    if name.startswith("err_") and name.endswith("_um") and len(name) > 7:
        return name[4:-3]
    return None


@dataclass
class Log:
    """A log in memory: column names and an (n × columns) float array; t_s is column 0."""

    file: str
    columns: list[str]
    data: np.ndarray

    @property
    def t_s(self) -> np.ndarray:
        return self.data[:, 0]

    def __len__(self) -> int:
        return self.data.shape[0]

    def col(self, name: str) -> np.ndarray:
        return self.data[:, self.index(name)]

    def index(self, name: str) -> int:
        try:
            return self.columns.index(name)
        except ValueError:
            raise BadInput(
                f"column {name!r} is not in the log (columns: {', '.join(self.columns)})",
                file=self.file,
            ) from None

    def matrix(self, names: Sequence[str]) -> np.ndarray:
        """Columns `names` as an (n × len(names)) array; a missing name is BadInput."""
        idx = [self.index(n) for n in names]
        return self.data[:, idx]

    def error_columns(self) -> list[str]:
        return [c for c in self.columns if error_axis(c)]

    def temperature_columns(self) -> list[str]:
        return [c for c in self.columns if is_temperature_column(c)]


def read_log(file: str | Path, *, allow_nan: bool = False) -> Log:
    """Read a log CSV; a malformed file is BadInput naming the row and column.

    Rows are numbered as a text editor shows them (the header is line 1). Empty
    cells are NaN only when `allow_nan`; otherwise they are errors.
    """
    file = str(file)
    try:
        fh = open(file, newline="", encoding="utf-8")  # noqa: SIM115
    except OSError as e:
        raise BadInput(f"cannot read log: {e.strerror or e}", file=file) from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise BadInput("the log is empty (no header row)", file=file) from None
        except (csv.Error, UnicodeDecodeError) as e:
            raise BadInput(f"not a CSV file: {e}", file=file, line=1) from None
        header = [h.strip() for h in header]
        if not header or header[0] != "t_s":
            raise BadInput("the first column must be 't_s'", file=file, line=1, path=header[0] if header else None)
        if len(set(header)) != len(header):
            dup = next(h for h in header if header.count(h) > 1)
            raise BadInput("column named twice", file=file, line=1, path=dup)
        if any(not h for h in header):
            raise BadInput("empty column name", file=file, line=1)
        rows: list[list[float]] = []
        ncol = len(header)
        prev_t = -math.inf
        try:
            for lineno, row in enumerate(reader, start=2):
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue
                if len(row) != ncol:
                    raise BadInput(
                        f"row has {len(row)} cells, the header has {ncol}", file=file, line=lineno
                    )
                values = []
                for name, cell in zip(header, row, strict=True):
                    cell = cell.strip()
                    if cell == "" and allow_nan:
                        values.append(math.nan)
                        continue
                    try:
                        v = float(cell)
                    except ValueError:
                        raise BadInput(
                            f"not a number: {cell!r}", file=file, line=lineno, path=name
                        ) from None
                    if not math.isfinite(v) and not allow_nan:
                        raise BadInput(f"not a finite number: {cell!r}", file=file, line=lineno, path=name)
                    values.append(v)
                t = values[0]
                if not math.isfinite(t):
                    raise BadInput("t_s must be a finite number", file=file, line=lineno, path="t_s")
                if abs(t) > MAX_T_S:
                    raise BadInput(
                        f"t_s {cell_t(row)} is beyond ±{MAX_T_S:.0e} s (three centuries): not a time",
                        file=file, line=lineno, path="t_s",
                    )
                if rows and t - rows[0][0] > MAX_T_S:
                    raise BadInput(
                        f"t_s {cell_t(row)} is {t - rows[0][0]:.3g} s after the first row: the log spans"
                        f" more than {MAX_T_S:.0e} s", file=file, line=lineno, path="t_s",
                    )
                if t < prev_t:
                    raise BadInput(
                        f"time goes backwards ({t} after {prev_t})", file=file, line=lineno, path="t_s"
                    )
                prev_t = t
                rows.append(values)
        except csv.Error as e:
            raise BadInput(f"CSV: {e}", file=file, line=reader.line_num) from None
        except UnicodeDecodeError:
            raise BadInput("not a UTF-8 text file", file=file) from None
    data = np.asarray(rows, dtype=float).reshape(len(rows), ncol)
    return Log(file, header, data)


def cell_t(row: list[str]) -> str:
    return row[0].strip()


def write_log(file: str | Path, columns: Sequence[str], data: np.ndarray) -> None:
    """Write a whole log (fit tools, simulator)."""
    with open(file, "w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(columns) + "\n")
        for row in np.asarray(data):
            fh.write(",".join(_fmt(v) for v in row) + "\n")


def _fmt(v: float) -> str:
    if v != v:  # NaN
        return ""
    return f"{v:.6g}" if abs(v) < 1e6 else f"{v:.10g}"


def _fmt_t(t_s: float) -> str:
    """t_s to 0.1 ms whatever its size (a daemon's clock reads 10⁵ s after a day of uptime)."""
    return f"{t_s:.4f}" if t_s == t_s else ""


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
    A file whose last row was cut by a crash is repaired (truncated to its last
    whole row) when it is opened again.
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
        self.repaired_bytes = 0
        self.error: str | None = None
        self._header = (",".join(self.columns) + "\n").encode()
        self._q: queue.SimpleQueue[tuple[float, ...] | None] = queue.SimpleQueue()
        self._pending: list[bytes] = []
        self._fd: int | None = None
        self._size = 0
        self._opened_s = 0.0
        self._open()
        self._thread = threading.Thread(target=self._run, name="compd-log", daemon=True)
        self._thread.start()

    def push(self, row: tuple[float, ...]) -> None:
        self._q.put(row)

    # ------------------------------------------------------------------ file
    def _open(self, set_aside: bool = True) -> bool:
        """Open (or create) the file for appending; repair a cut last row; queue the header."""
        import time

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        except OSError as e:
            self._fail(f"cannot open log: {e.strerror or e}", 0)
            return False
        self._fd = fd
        try:
            self._size = os.fstat(fd).st_size
            if self._size > 0:
                self._repair()
            if set_aside and self._size > 0 and not self._same_header():
                # written with other columns (the config changed): set it aside, start anew
                os.close(fd)
                self._fd = None
                self._shift()
                return self._open(set_aside=False)
        except OSError:
            self._size = 0
        if self._size == 0:
            self._pending.insert(0, self._header)
        self._opened_s = time.monotonic()
        return True

    def _repair(self) -> None:
        """Cut a partial last row (a crash mid-write) so appended rows start on a new line."""
        assert self._fd is not None
        with open(self.path, "rb") as fh:
            fh.seek(max(self._size - 65536, 0))
            tail = fh.read()
        if tail.endswith(b"\n"):
            return
        cut = tail.rfind(b"\n")
        keep = self._size - len(tail) + cut + 1 if cut >= 0 else 0
        os.ftruncate(self._fd, keep)
        self.repaired_bytes += self._size - keep
        self._size = keep

    def _same_header(self) -> bool:
        with open(self.path, "rb") as fh:
            return fh.readline() == self._header

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

        last_flush = time.monotonic()
        while True:
            try:
                row = self._q.get(timeout=self.flush_s)
            except queue.Empty:
                row = ()
            if row is None:
                break
            if row:
                self._pending.append((_fmt_t(row[0]) + "".join("," + _fmt(v) for v in row[1:]) + "\n").encode())
                if len(self._pending) > self.max_pending_rows:
                    del self._pending[: len(self._pending) // 2]
                    self.rows_dropped += self.max_pending_rows // 2
            now = time.monotonic()
            if now - last_flush >= self.flush_s:
                self._flush(now)
                last_flush = now
        self._flush(time.monotonic())

    def _flush(self, now_s: float) -> None:
        """Write the pending rows in one go and fsync; on failure cut any partial write."""
        if self._due_rotation(now_s):
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
                "data log writes again: %s", self.path,
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
                reason, self.path,
                extra={"event": "log_error", "path": str(self.path), "reason": reason},
            )
        self.error = reason

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(timeout=10)
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
