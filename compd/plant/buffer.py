"""The store-and-forward buffer: telemetry waits on disk (SQLite) while the broker is away, oldest sent first.

A sample is appended with `put`, read back oldest first with `pending`, and deleted with
`ack` only once the broker acknowledged it, so nothing is lost between a send and its
acknowledgement (a sample may be sent twice, never dropped silently). The buffer is bounded
by the bytes of the record bodies: over `max_bytes`, the oldest records are dropped and
counted (the counts persist), never the new one and never with an exception to the caller;
the caller watches `dropped` and says so in its log (this module logs only a file set aside).

Durability: the database is in WAL mode with synchronous=NORMAL. Every `put` is committed
before it returns, so a crash of the process (kill -9, an exception, the OOM killer) loses
nothing that `put` returned; a power cut or a kernel crash may lose the last transactions
committed since the WAL was last synced (at a checkpoint, about every 4 MB of writes), but
never leaves the file inconsistent.

A file that is not a database compd can use (SQLite says it is not a database or is
malformed, or it holds tables that are not ours) is never repaired by deleting: it is renamed
aside to `<name>.corrupt-<UTC time>` (with its -wal and -shm files), kept, logged, and a new
buffer is started; ids then start again at 1 in the new file.

While the file cannot be written (its disk full, an I/O error) or opened at all, the telemetry
keeps its records in a `MemoryBuffer` instead (the same calls, bounded, gone with the process)
and hands them to the file when it can be written again; what the file held stays in it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compd.core.errors import BadInput

log = logging.getLogger("compd.telemetry")

SCHEMA_VERSION = 1
_SCHEMA = f"""
BEGIN IMMEDIATE;
CREATE TABLE IF NOT EXISTS records (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t_ms INTEGER NOT NULL,
    kind TEXT NOT NULL,
    body BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS counters (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
PRAGMA user_version = {SCHEMA_VERSION};
COMMIT;
"""
_COLUMNS = {
    "records": ["id", "t_ms", "kind", "body"],
    "meta": ["key", "value"],
    "counters": ["key", "value"],
}
_CHUNK = 500  # ids per statement (SQLite's variable limit is 32766; keep statements small)


class _Unusable(Exception):
    """The file is not a buffer we can use (corrupt, or another program's database)."""


@dataclass(frozen=True)
class Record:
    """One buffered sample: its id (increasing forever), sample time, kind and encoded body."""

    id: int
    t_ms: int
    kind: str
    body: bytes


class StoreAndForward:
    """A bounded, persistent FIFO of records in one SQLite file; safe to call from two threads."""

    def __init__(self, path: Path, max_bytes: int) -> None:
        """Open (or start) the buffer at `path`; BadInput when its folder does not exist or the
        file cannot be opened or written. `max_bytes` bounds the sum of the record bodies."""
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1:
            raise ValueError(f"max_bytes must be a positive integer, not {max_bytes!r}")
        self.path = Path(path)
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        if not self.path.parent.is_dir():
            raise BadInput(f"the folder {self.path.parent} does not exist", file=str(self.path))
        try:
            try:
                self._db = self._open()
            except _Unusable as e:
                self._set_aside(str(e))
                self._db = self._open()
        except _Unusable as e:  # a fresh file that is still unusable: not ours to fix
            raise BadInput(f"cannot use the telemetry buffer: {e}", file=str(self.path)) from None
        except (sqlite3.Error, OSError) as e:
            raise BadInput(f"cannot open the telemetry buffer: {e}", file=str(self.path)) from None
        self._count, self._bytes = self._db.execute(
            "SELECT COUNT(*), COALESCE(SUM(length(body)), 0) FROM records"
        ).fetchone()
        self._dropped = self._counter("dropped")
        self._dropped_bytes = self._counter("dropped_bytes")
        if self._bytes > self.max_bytes:  # the limit was lowered since: honour it at once
            with self._lock:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    self._drop_oldest()
                    self._db.execute("COMMIT")
                except BaseException:
                    self._rollback()
                    raise

    # --- opening ----------------------------------------------------------------------------

    def _open(self) -> sqlite3.Connection:
        """Connect, lock, check the file is ours (or new) and writable, create the tables.

        sqlite3.OperationalError (cannot open, read-only, locked, I/O) passes through for the
        caller to turn into BadInput; any other DatabaseError and a foreign schema raise _Unusable.
        """
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=1.0)
        try:
            try:
                # held until close: a second process (another compd with the same config) cannot
                # open the buffer and send the same samples; and WAL needs no -shm file then
                db.execute("PRAGMA locking_mode=EXCLUSIVE")
                # only reads until the file is known to be ours (or new): another program's
                # database is set aside exactly as it was, not switched to WAL first
                version = db.execute("PRAGMA user_version").fetchone()[0]
                tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")} - {
                    "sqlite_sequence"
                }
                if version > SCHEMA_VERSION:  # valid, only not for us: left as it is
                    raise BadInput(
                        f"the telemetry buffer has schema version {version}, from a newer compd"
                        f" (this one reads {SCHEMA_VERSION}): move it away or point telemetry.buffer.path elsewhere",
                        file=str(self.path),
                    )
                if tables - set(_COLUMNS) or (tables and version != SCHEMA_VERSION):
                    raise _Unusable(f"not a telemetry buffer (tables: {', '.join(sorted(tables))})")
                check = db.execute("PRAGMA quick_check").fetchall()
                if check != [("ok",)]:
                    raise _Unusable(f"integrity check: {'; '.join(str(r[0]) for r in check[:3])}")
                db.execute("PRAGMA journal_mode=WAL").fetchone()
                db.execute("PRAGMA synchronous=NORMAL")
                db.execute("PRAGMA journal_size_limit=8388608")  # a checkpointed WAL shrinks back to 8 MB
                db.executescript(_SCHEMA)  # a write, always: proves the file is writable
                for table, columns in _COLUMNS.items():
                    have = [row[1] for row in db.execute(f"PRAGMA table_info({table})")]
                    if have != columns:
                        raise _Unusable(f"table {table} has columns {have}, not {columns}")
            except sqlite3.OperationalError:
                raise
            except sqlite3.DatabaseError as e:
                raise _Unusable(str(e)) from None
        except BaseException:
            db.close()
            raise
        return db

    def _set_aside(self, reason: str) -> None:
        """Rename the unusable file (and its WAL and shared-memory files) to `<name>.corrupt-<UTC>`."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while target.exists():
            target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
            n += 1
        try:
            self.path.rename(target)
            for suffix in ("-wal", "-shm"):
                side = self.path.with_name(self.path.name + suffix)
                if side.exists():
                    side.rename(target.with_name(target.name + suffix))
        except OSError as e:
            raise BadInput(
                f"the telemetry buffer is unusable ({reason}) and cannot be moved aside: {e}",
                file=str(self.path),
            ) from None
        log.warning(
            "telemetry buffer %s unusable (%s): moved to %s, starting a new one",
            self.path,
            reason,
            target,
            extra={
                "event": "telemetry_buffer_corrupt",
                "path": str(self.path),
                "moved_to": str(target),
                "reason": reason,
            },
        )

    def _counter(self, key: str) -> int:
        row = self._db.execute("SELECT value FROM counters WHERE key = ?", (key,)).fetchone()
        return 0 if row is None else int(row[0])

    # --- writing ----------------------------------------------------------------------------

    def put(self, t_ms: int, kind: str, body: bytes) -> int:
        """Append one record and commit; its id, or -1 when the body alone exceeds max_bytes
        (refused and counted as dropped). Drops the oldest records while over max_bytes."""
        t_ms, kind, body = int(t_ms), str(kind), bytes(body)
        size = len(body)
        with self._lock:
            if size > self.max_bytes:
                self._count_dropped(1, size)
                return -1
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                record_id = db.execute(
                    "INSERT INTO records (t_ms, kind, body) VALUES (?, ?, ?)", (t_ms, kind, body)
                ).lastrowid
                self._count += 1
                self._bytes += size
                if self._bytes > self.max_bytes:
                    self._drop_oldest()
                db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
            return int(record_id)

    def _drop_oldest(self) -> None:
        """Inside a transaction: delete the oldest records until the bodies fit, and count them."""
        excess = self._bytes - self.max_bytes
        freed = n = 0
        last_id = None
        # stepped row by row: usually the first row or two are enough
        rows = self._db.execute("SELECT id, length(body) FROM records ORDER BY id")
        try:
            for record_id, length in rows:
                last_id = record_id
                freed += length
                n += 1
                if freed >= excess:
                    break
        finally:
            rows.close()
        if last_id is None:
            return
        self._db.execute("DELETE FROM records WHERE id <= ?", (last_id,))
        self._count -= n
        self._bytes -= freed
        self._count_dropped(n, freed, in_transaction=True)

    def _count_dropped(self, n: int, size: int, *, in_transaction: bool = False) -> None:
        sql = (
            "INSERT INTO counters (key, value) VALUES (?, ?)"
            " ON CONFLICT(key) DO UPDATE SET value = value + excluded.value"
        )
        if in_transaction:
            self._db.execute(sql, ("dropped", n))
            self._db.execute(sql, ("dropped_bytes", size))
        else:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute(sql, ("dropped", n))
                self._db.execute(sql, ("dropped_bytes", size))
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
        self._dropped += n
        self._dropped_bytes += size

    def _rollback(self) -> None:
        """After a failed transaction: undo what is left of it, and take the counts from the file
        (quietly: the caller re-raises the error that failed the transaction)."""
        with contextlib.suppress(sqlite3.Error):
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            self._count, self._bytes = self._db.execute(
                "SELECT COUNT(*), COALESCE(SUM(length(body)), 0) FROM records"
            ).fetchone()
            self._dropped = self._counter("dropped")
            self._dropped_bytes = self._counter("dropped_bytes")

    def ack(self, ids: Iterable[int]) -> None:
        """Delete these records: sent and acknowledged by the broker. Unknown ids are ignored."""
        wanted = sorted({int(i) for i in ids})
        if not wanted:
            return
        with self._lock:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                for start in range(0, len(wanted), _CHUNK):
                    chunk = wanted[start : start + _CHUNK]
                    marks = ",".join("?" * len(chunk))
                    n, size = db.execute(
                        f"SELECT COUNT(*), COALESCE(SUM(length(body)), 0) FROM records WHERE id IN ({marks})",
                        chunk,
                    ).fetchone()
                    db.execute(f"DELETE FROM records WHERE id IN ({marks})", chunk)
                    self._count -= n
                    self._bytes -= size
                db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def set_meta(self, key: str, value: int) -> None:
        """Store a small persistent integer (the Sparkplug bdSeq, the sample number…)."""
        with self._lock:
            self._db.execute(
                "INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, int(value)),
            )

    # --- reading ----------------------------------------------------------------------------

    def pending(self, limit: int, after_id: int = 0) -> list[Record]:
        """Up to `limit` records with id > after_id, oldest first."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, t_ms, kind, body FROM records WHERE id > ? ORDER BY id LIMIT ?",
                (after_id, limit),
            ).fetchall()
        return [Record(int(i), int(t), str(k), bytes(b)) for i, t, k, b in rows]

    def get_meta(self, key: str, default: int = 0) -> int:
        """A persistent integer stored with set_meta, or `default`."""
        with self._lock:
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return default if row is None else int(row[0])

    def __len__(self) -> int:
        return self._count

    @property
    def last_id(self) -> int:
        """The id of the newest record ever put (acknowledged or not; 0 before the first)."""
        with self._lock:
            row = self._db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'records'").fetchone()
        return 0 if row is None else int(row[0])

    @property
    def bytes(self) -> int:
        """The sum of the stored record bodies (what max_bytes bounds; not the file's size)."""
        return self._bytes

    @property
    def dropped(self) -> int:
        """Records dropped (oldest when full, or refused as too large) over the file's life."""
        return self._dropped

    @property
    def dropped_bytes(self) -> int:
        """The bytes of the dropped records' bodies, over the file's life."""
        return self._dropped_bytes

    def get_status(self) -> dict[str, Any]:
        """For the status and metrics: path, records, bytes, max_bytes, dropped, dropped_bytes, oldest_t_ms."""
        with self._lock:
            row = self._db.execute("SELECT t_ms FROM records ORDER BY id LIMIT 1").fetchone()
            return {
                "path": str(self.path),
                "records": self._count,
                "bytes": self._bytes,
                "max_bytes": self.max_bytes,
                "dropped": self._dropped,
                "dropped_bytes": self._dropped_bytes,
                "oldest_t_ms": None if row is None else int(row[0]),
            }

    def close(self) -> None:
        """Close the file (a checkpoint folds the WAL back in); calling it again does nothing."""
        with self._lock:
            self._db.close()

    def __enter__(self) -> StoreAndForward:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


MEMORY_MAX_BYTES = 4_000_000  # the memory buffer's bound (about an hour of the demo's samples at 1 s)


class MemoryBuffer:
    """The buffer's stand-in while the file cannot take records: `put`, `pending`, `ack`, the
    meta integers and the counts as `StoreAndForward` has them, in memory. Bounded by `max_bytes`
    of record bodies like the file (the oldest dropped and counted, never the new one); lost
    with the process, so `take` hands what it holds to the file as soon as that can be written.
    Ids increase from 1 for its own life. Used by the telemetry's thread alone."""

    path = None  # no file

    def __init__(self, max_bytes: int) -> None:
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 1:
            raise ValueError(f"max_bytes must be a positive integer, not {max_bytes!r}")
        self.max_bytes = max_bytes
        self._records: dict[int, Record] = {}  # insertion order is id order
        self._meta: dict[str, int] = {}
        self._next_id = 1
        self._bytes = 0
        self.dropped = 0  # records dropped (the oldest when full, or one too large) over its life
        self.dropped_bytes = 0

    def put(self, t_ms: int, kind: str, body: bytes) -> int:
        """Append one record; its id, or -1 when the body alone exceeds max_bytes (dropped)."""
        size = len(body)
        if size > self.max_bytes:
            self.dropped += 1
            self.dropped_bytes += size
            return -1
        record_id = self._next_id
        self._next_id += 1
        self._records[record_id] = Record(record_id, int(t_ms), str(kind), bytes(body))
        self._bytes += size
        while self._bytes > self.max_bytes:
            old = self._records.pop(next(iter(self._records)))
            self._bytes -= len(old.body)
            self.dropped += 1
            self.dropped_bytes += len(old.body)
        return record_id

    def pending(self, limit: int, after_id: int = 0) -> list[Record]:
        """Up to `limit` records with id > after_id, oldest first."""
        out: list[Record] = []
        for record_id, rec in self._records.items():
            if len(out) >= limit:
                break
            if record_id > after_id:
                out.append(rec)
        return out

    def ack(self, ids: Iterable[int]) -> None:
        """Forget these records (the broker has them); unknown ids are ignored."""
        for i in ids:
            rec = self._records.pop(int(i), None)
            if rec is not None:
                self._bytes -= len(rec.body)

    def take(self) -> list[Record]:
        """Every record, oldest first; they are forgotten (the caller has put them in the file)."""
        out = list(self._records.values())
        self._records.clear()
        self._bytes = 0
        return out

    def set_meta(self, key: str, value: int) -> None:
        self._meta[key] = int(value)

    def get_meta(self, key: str, default: int = 0) -> int:
        return self._meta.get(key, default)

    def __len__(self) -> int:
        return len(self._records)

    @property
    def bytes(self) -> int:
        return self._bytes

    def get_status(self) -> dict[str, Any]:
        """As `StoreAndForward.get_status`, with path None."""
        first = next(iter(self._records.values()), None)
        return {
            "path": None,
            "records": len(self._records),
            "bytes": self._bytes,
            "max_bytes": self.max_bytes,
            "dropped": self.dropped,
            "dropped_bytes": self.dropped_bytes,
            "oldest_t_ms": None if first is None else first.t_ms,
        }

    def close(self) -> None:
        """Nothing to close (what it holds stays for `take`)."""


class Counters:
    """The numbers a historian keys on (the Sparkplug `Sample`, `bdSeq`), in a small file of
    their own beside the buffer (`<buffer>.counters`, JSON, written through a temp file, a
    sync and a rename): a buffer set aside, emptied or lost does not take them with it, so
    a sample number is never given twice. A counter is the larger of the file's and the
    buffer's (an older compd kept them in the buffer only). A counters file that cannot be
    read is set aside like a buffer (`.corrupt-<UTC>`), never deleted."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.values: dict[str, int] = {}
        self.error: str | None = None  # the last write that failed (the status shows it)
        try:
            raw = json.loads(self.path.read_text(encoding="utf-8"))
            if not isinstance(raw, dict) or not all(
                isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in raw.values()
            ):
                raise ValueError("not a mapping of counters to non-negative integers")
            self.values = {str(k): int(v) for k, v in raw.items()}
        except FileNotFoundError:
            pass
        except (OSError, ValueError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
            target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
            with contextlib.suppress(OSError):
                self.path.rename(target)
            log.warning(
                "telemetry counters %s unusable (%s): moved to %s; counting on from the buffer",
                self.path,
                e,
                target,
                extra={
                    "event": "telemetry_counters_corrupt",
                    "path": str(self.path),
                    "moved_to": str(target),
                    "reason": str(e),
                },
            )

    def get(self, key: str, floor: int = 0) -> int:
        """The counter, at least `floor` (the buffer's own copy); `floor` when it was never set."""
        return max(self.values[key], floor) if key in self.values else floor

    def set(self, key: str, value: int) -> None:
        """Store a counter now (it survives a crash of the process once this returns)."""
        self.values[key] = int(value)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(self.values, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
            self.error = None
        except OSError as e:  # a full disk: counted on in memory, said in the status, tried again next time
            self.error = f"{self.path}: {e.strerror or e}"
            with contextlib.suppress(OSError):
                tmp.unlink()
