"""The log CSV of CONTRACT.md: read and validate it, and write it from a background thread."""

from __future__ import annotations

import csv
import math
import os
import queue
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from compd.errors import BadInput

RESERVED_PREFIXES = ("err_", "pos_", "current_")
RESERVED_NAMES = ("t_s", "speed_rpm")
# Columns the loop itself writes into its log (compd.app.LogObserver): never inputs.
OUTPUT_PREFIXES = ("pred_", "corr_", "applied_")
OUTPUT_NAMES = ("word",)


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


class LogWriter:
    """Writes log rows from a background thread so the cycle never waits on the disk.

    The cycle calls `push(row)` with a tuple of floats (allocated only at the log
    period, not every cycle). The thread writes and flushes at least every
    `flush_s`; `close()` drains what is queued. Disk errors (full disk) are counted
    and reported through `error`, never raised into the loop.
    """

    def __init__(self, path: str | Path, columns: Sequence[str], flush_s: float = 1.0) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.flush_s = flush_s
        self.rows_written = 0
        self.rows_dropped = 0
        self.error: str | None = None
        self._q: queue.SimpleQueue[tuple[float, ...] | None] = queue.SimpleQueue()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._fh = open(self.path, "a", newline="", encoding="utf-8")  # noqa: SIM115
        if new:
            self._fh.write(",".join(self.columns) + "\n")
            self._fh.flush()
        self._thread = threading.Thread(target=self._run, name="compd-log", daemon=True)
        self._thread.start()

    def push(self, row: tuple[float, ...]) -> None:
        self._q.put(row)

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
                try:
                    self._fh.write(",".join(_fmt(v) for v in row) + "\n")
                    self.rows_written += 1
                except OSError as e:
                    self.rows_dropped += 1
                    self.error = f"log write failed: {e.strerror or e}"
            now = time.monotonic()
            if now - last_flush >= self.flush_s:
                self._flush()
                last_flush = now
        self._flush()

    def _flush(self) -> None:
        try:
            self._fh.flush()
            os.fsync(self._fh.fileno())
        except OSError as e:
            self.error = f"log flush failed: {e.strerror or e}"

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(timeout=10)
        try:
            self._fh.close()
        except OSError as e:
            self.error = f"log close failed: {e.strerror or e}"
