"""The log CSV (docs/formats.md): read, validate and repair it.

The service's thread that writes it is compd.service.logwriter.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from compd.core.errors import BadInput

# |t_s| and the span of a log stay below this (≈ 317 years; Unix time is 1.8e9 s): float
# time keeps 2 µs resolution there, so every cycle and PLC scan still advances the clock.
MAX_T_S = 1e10
RESERVED_PREFIXES = ("err_", "pos_", "current_")
RESERVED_NAMES = ("t_s", "speed_rpm")
# Columns the loop itself writes into its log (compd.daemon.app.LogObserver): never inputs.
OUTPUT_PREFIXES = ("pred_", "corr_", "applied_", "probe_")
OUTPUT_NAMES = ("word",)

log = logging.getLogger("compd.log")


def is_temperature_column(name: str) -> bool:
    """Any column but t_s, err_*, pos_*, speed_rpm, current_* is a temperature.

    compd's own output columns (pred_*, corr_*, applied_*, probe_*, word) are excluded too, so
    a fit on a log that compd wrote does not take its own predictions as inputs.
    """
    return (
        name not in RESERVED_NAMES
        and name not in OUTPUT_NAMES
        and not name.startswith(RESERVED_PREFIXES)
        and not name.startswith(OUTPUT_PREFIXES)
    )


def error_axis(name: str) -> str | None:
    """`err_x1_um` → `x1`; a share of an axis's error measured on its own, `err_<axis>_um_<part>`
    (`err_z_um_spindle`: what a mandrel test measures of the spindle alone) → its axis, `z`; None
    for other columns."""
    if not name.startswith("err_"):
        return None
    body = name[4:]
    if body.endswith("_um") and len(body) > 3:
        return body[:-3]
    cut = body.find("_um_")
    if cut > 0 and cut + 4 < len(body):
        return body[:cut]
    return None


def is_axis_error(name: str) -> bool:
    """`err_<axis>_um`: an axis's whole thermal error (a fit's default target), not one part's share."""
    return name.endswith("_um") and error_axis(name) is not None


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
        """The axes' whole errors, `err_<axis>_um` (a part's share, `err_<axis>_um_<part>`, is a
        target only when named)."""
        return [c for c in self.columns if is_axis_error(c)]

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
                nul = next((i for i, cell in enumerate(row) if "\0" in cell), None)
                if nul is not None:
                    raise BadInput(
                        "NUL bytes in the row (a power cut during a write?); compd run repairs"
                        " its own log when it opens it again",
                        file=file,
                        line=lineno,
                        path=header[nul] if nul < ncol else None,
                    )
                if len(row) != ncol:
                    raise BadInput(f"row has {len(row)} cells, the header has {ncol}", file=file, line=lineno)
                values = []
                for name, cell in zip(header, row, strict=True):
                    cell = cell.strip()
                    if cell == "" and allow_nan:
                        values.append(math.nan)
                        continue
                    try:
                        v = float(cell)
                    except ValueError:
                        raise BadInput(f"not a number: {_short(cell)}", file=file, line=lineno, path=name) from None
                    if not math.isfinite(v) and not allow_nan:
                        raise BadInput(f"not a finite number: {cell!r}", file=file, line=lineno, path=name)
                    values.append(v)
                t = values[0]
                if not math.isfinite(t):
                    raise BadInput("t_s must be a finite number", file=file, line=lineno, path="t_s")
                if abs(t) > MAX_T_S:
                    raise BadInput(
                        f"t_s {cell_t(row)} is beyond ±{MAX_T_S:.0e} s (three centuries): not a time",
                        file=file,
                        line=lineno,
                        path="t_s",
                    )
                if rows and t - rows[0][0] > MAX_T_S:
                    raise BadInput(
                        f"t_s {cell_t(row)} is {t - rows[0][0]:.3g} s after the first row: the log spans"
                        f" more than {MAX_T_S:.0e} s",
                        file=file,
                        line=lineno,
                        path="t_s",
                    )
                if t < prev_t:
                    raise BadInput(f"time goes backwards ({t} after {prev_t})", file=file, line=lineno, path="t_s")
                prev_t = t
                rows.append(values)
        except csv.Error as e:
            raise BadInput(f"CSV: {e}", file=file, line=reader.line_num) from None
        except UnicodeDecodeError:
            raise BadInput("not a UTF-8 text file", file=file) from None
    data = np.asarray(rows, dtype=float).reshape(len(rows), ncol)
    return Log(file, header, data)


def _short(cell: str, limit: int = 40) -> str:
    """repr of a cell, cut to `limit` characters (a garbage cell can be megabytes)."""
    return repr(cell) if len(cell) <= limit else repr(cell[:limit]) + f"… ({len(cell)} characters)"


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


# ------------------------------------------------------------------ repair
# What a crash or a power cut leaves at the end of a log that was being appended to:
# a row cut in the middle (kill -9 mid-write), and after a power cut with delayed
# allocation a run of NUL bytes (the file's size was committed, its data was not),
# possibly hundreds of KiB long and with no newline in it. Repair keeps every
# complete, parseable row and moves everything else, byte for byte, to a side file.

_CHUNK = 65536


def _row_ok(line: bytes, ncol: int) -> bool:
    """True if `line` (with its newline) is a whole row read_log(allow_nan=True) accepts."""
    if not line.endswith(b"\n") or b"\0" in line:
        return False
    try:
        cells = line.decode("utf-8").rstrip("\r\n").split(",")
    except UnicodeDecodeError:
        return False
    if len(cells) != ncol:
        return False
    try:
        values = [float(c) if c.strip() else math.nan for c in cells]
    except ValueError:
        return False
    return math.isfinite(values[0])


def _max_row_bytes(ncol: int) -> int:
    """A longer line is damage whatever it holds (bounds the memory a repair uses)."""
    return max(_CHUNK, 64 * ncol)


def _newlines_backward(fh: BinaryIO, start: int, end: int) -> Iterator[int]:
    """Offsets of the newline bytes in [start, end), last first, reading one chunk at a time."""
    pos = end
    while pos > start:
        lo = max(start, pos - _CHUNK)
        fh.seek(lo)
        buf = fh.read(pos - lo)
        i = len(buf)
        while (i := buf.rfind(b"\n", 0, i)) >= 0:
            yield lo + i
        pos = lo


def _last_good_end(fh: BinaryIO, start: int, end: int, ncol: int) -> int:
    """Offset just past the last complete, parseable row in [start, end) (`start` if none)."""

    def ok(a: int, b: int) -> bool:
        if b - a > _max_row_bytes(ncol):
            return False
        fh.seek(a)
        return _row_ok(fh.read(b - a), ncol)

    line_end: int | None = None
    for nl in _newlines_backward(fh, start, end):
        if line_end is not None and ok(nl + 1, line_end):
            return line_end
        line_end = nl + 1
    if line_end is not None and ok(start, line_end):
        return line_end
    return start


def _chunks(fh: BinaryIO, start: int, end: int) -> Iterator[bytes]:
    """[start, end) of `fh` in reads of at most _CHUNK bytes (bounded memory)."""
    fh.seek(start)
    pos = start
    while pos < end:
        buf = fh.read(min(_CHUNK, end - pos))
        if not buf:
            return
        yield buf
        pos += len(buf)


def _has_nul(fh: BinaryIO, start: int, end: int) -> bool:
    return any(b"\0" in buf for buf in _chunks(fh, start, end))


def _count_lines(fh: BinaryIO, start: int, end: int) -> int:
    return sum(buf.count(b"\n") for buf in _chunks(fh, start, end))


def _split_body(fh: BinaryIO, start: int, end: int, ncol: int, good: BinaryIO, bad: BinaryIO) -> tuple[int, int]:
    """Copy the lines of [start, end) to `good` (parseable rows) or `bad` (the rest).

    [start, end) ends on a newline. A line longer than a row can be streams to `bad`
    without being held in memory. Returns (rows kept, lines set aside).
    """
    limit = _max_row_bytes(ncol)
    kept = set_aside = 0
    cur = bytearray()
    overflow = False  # the current line is too long to be a row: it streams to `bad`
    for chunk in _chunks(fh, start, end):
        i = 0
        while i < len(chunk):
            j = chunk.find(b"\n", i)
            piece = chunk[i:] if j < 0 else chunk[i : j + 1]
            i += len(piece)
            if overflow:
                bad.write(piece)
            else:
                cur += piece
                if len(cur) > limit:
                    bad.write(cur)
                    cur.clear()
                    overflow = True
            if j < 0:
                continue
            if overflow:
                set_aside += 1
                overflow = False
            elif _row_ok(bytes(cur), ncol):
                good.write(cur)
                kept += 1
            else:
                bad.write(cur)
                set_aside += 1
            cur.clear()
    if cur or overflow:  # cannot happen when `end` is a line end; never lose it anyway
        bad.write(cur)
        set_aside += 1
    return kept, set_aside


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _side_file(path: Path, what: str) -> tuple[int, Path]:
    """Create `<log>.<what>-<UTC time>[-N]` exclusively (never over an earlier one)."""
    import time

    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    for n in range(1, 10_000):
        side = path.with_name(f"{path.name}.{what}-{stamp}" + (f"-{n}" if n > 1 else ""))
        try:
            return os.open(side, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644), side
        except FileExistsError:
            continue
    raise FileExistsError(f"no free side-file name for {path}")


def _set_aside_whole(path: Path, what: str) -> Path:
    """Rename the whole file to a new side file (atomic: nothing is copied, nothing lost)."""
    fd, side = _side_file(path, what)
    os.close(fd)
    os.replace(path, side)
    _fsync_dir(path.parent)
    return side


@dataclass
class Repair:
    """What `repair_log` did: rows kept, what was moved aside and where."""

    path: str
    action: str  # "none", "tail" (damage cut off the end), "body" (damage removed inside), "whole"
    rows_kept: int = 0
    lines_set_aside: int = 0
    bytes_set_aside: int = 0
    side_file: str | None = None
    header: bytes | None = None  # the file's header line, when it has a readable one

    def log_event(self) -> None:
        log.warning(
            "data log repaired: %s kept %d rows; %d bytes (%d lines) of damage moved to %s",
            self.path,
            self.rows_kept,
            self.bytes_set_aside,
            self.lines_set_aside,
            self.side_file,
            extra={
                "event": "log_repaired",
                "path": self.path,
                "action": self.action,
                "rows_kept": self.rows_kept,
                "lines_set_aside": self.lines_set_aside,
                "bytes_set_aside": self.bytes_set_aside,
                "side_file": self.side_file,
            },
        )


def _header_of(fh: BinaryIO) -> bytes | None:
    """The first line if it is a readable log header (t_s first, names, newline), else None."""
    fh.seek(0)
    line = fh.readline(_CHUNK)
    if not line.endswith(b"\n") or b"\0" in line:
        return None
    try:
        names = [n.strip() for n in line.decode("utf-8").rstrip("\r\n").split(",")]
    except UnicodeDecodeError:
        return None
    if names[0] != "t_s" or any(not n for n in names) or len(set(names)) != len(names):
        return None
    return line


def repair_log(path: str | Path) -> Repair:
    """Make the log at `path` a valid CSV again after a crash, losing nothing.

    * The damaged tail (a cut row, NUL bytes, garbage, rows with the wrong number of
      cells or a non-number) after the last complete, parseable row, however far back
      that is, is copied to `<log>.damaged-<UTC time>` and fsynced, and only then is
      the log truncated to that row.
    * NUL bytes before that row (a power cut with delayed allocation, then more rows):
      every line that is not a parseable row goes to the side file too, and the log is
      rewritten (temp file, fsync, rename) with the good rows in their order.
    * No readable header (entirely NULs, a cut header, not a log): the whole file is
      renamed to the side file; the caller starts a new log.
    The log is read in 64 KiB chunks: memory does not grow with the file or the damage
    (the NUL check reads the whole file once, at C speed; the rest reads only the tail).
    A failure on the way (disk full writing the side file) leaves the log untouched.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size == 0:
            return Repair(str(path), "none")
        header = _header_of(fh)
        if header is None:
            side = _set_aside_whole(path, "damaged")
            return Repair(str(path), "whole", 0, 1, size, str(side))
        ncol = header.count(b",") + 1
        start = len(header)
        good_end = _last_good_end(fh, start, size, ncol)
        body_damaged = _has_nul(fh, start, good_end)
        if good_end == size and not body_damaged:
            return Repair(str(path), "none", header=header)
        fd, side = _side_file(path, "damaged")
        tmp = path.with_name(f".{path.name}.repair.tmp")
        with os.fdopen(fd, "wb") as bad, _removed_on_error(tmp):
            if body_damaged:
                with open(tmp, "wb") as good:
                    good.write(header)
                    kept, set_aside = _split_body(fh, start, good_end, ncol, good, bad)
                    good.flush()
                    os.fsync(good.fileno())
            else:
                kept, set_aside = _count_lines(fh, start, good_end), 0
            fh.seek(good_end)
            tail = good_end
            while tail < size:
                buf = fh.read(min(_CHUNK, size - tail))
                if not buf:
                    break
                bad.write(buf)
                tail += len(buf)
            if size > good_end:  # the tail's lines; a last one without its newline counts too
                set_aside += _count_lines(fh, good_end, size) + (0 if _ends_with_newline(fh, size) else 1)
            bad.flush()
            os.fsync(bad.fileno())
            bytes_aside = bad.tell()
        _fsync_dir(path.parent)
    # the damage is safe in the side file: now the log may lose it
    if body_damaged:
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    else:
        with open(path, "r+b") as fh:
            fh.truncate(good_end)
            os.fsync(fh.fileno())
    return Repair(str(path), "body" if body_damaged else "tail", kept, set_aside, bytes_aside, str(side), header)


@contextlib.contextmanager
def _removed_on_error(tmp: Path) -> Iterator[None]:
    """A half-written temp file goes if the repair fails (the log itself is untouched then)."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _ends_with_newline(fh: BinaryIO, size: int) -> bool:
    fh.seek(size - 1)
    return fh.read(1) == b"\n"
