"""The store-and-forward buffer: order, acknowledgement, the byte limit, restarts, kill -9 and corrupt files."""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from compd.core.errors import BadInput
from compd.plant.buffer import Record, StoreAndForward

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "telemetry.sqlite"


@pytest.fixture
def warnings():
    """The warnings logged on compd.telemetry during the test."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("compd.telemetry")
    logger.addHandler(handler)
    try:
        yield records
    finally:
        logger.removeHandler(handler)


def body(i: int, size: int = 100) -> bytes:
    return f"{i:08d}".encode().ljust(size, b".")


def test_records_come_back_oldest_first_and_go_when_acked(path):
    with StoreAndForward(path, 1 << 20) as buf:
        ids = [buf.put(1000 + i, "sample" if i % 2 else "event", body(i)) for i in range(10)]
        assert ids == sorted(ids) and len(set(ids)) == 10
        assert len(buf) == 10 and buf.bytes == 1000
        first = buf.pending(4)
        assert first == [Record(ids[i], 1000 + i, "sample" if i % 2 else "event", body(i)) for i in range(4)]
        assert [r.id for r in buf.pending(3, after_id=ids[3])] == ids[4:7]
        assert buf.pending(100, after_id=ids[-1]) == []
        buf.ack([ids[0], ids[2], 999_999])  # an unknown id is ignored
        assert [r.id for r in buf.pending(100)] == [ids[1]] + ids[3:]
        assert len(buf) == 8 and buf.bytes == 800
        buf.ack(r.id for r in buf.pending(100))
        assert len(buf) == 0 and buf.bytes == 0 and buf.pending(10) == []
        assert buf.get_status()["oldest_t_ms"] is None
        assert buf.put(1, "sample", b"x") > ids[-1]  # ids never come back


def test_over_the_limit_the_oldest_are_dropped_and_counted(path):
    with StoreAndForward(path, 1000) as buf:
        ids = [buf.put(i, "s", body(i)) for i in range(10)]
        assert buf.bytes == 1000 and buf.dropped == 0
        new = buf.put(10, "s", body(10, 250))  # 250 more bytes: the three oldest go
        assert [r.id for r in buf.pending(100)] == ids[3:] + [new]
        assert (buf.dropped, buf.dropped_bytes) == (3, 300)
        assert (len(buf), buf.bytes) == (8, 950)
        assert buf.put(11, "s", body(11, 1000)) != -1  # exactly the limit: everything else goes
        assert [r.t_ms for r in buf.pending(100)] == [11]
        assert (len(buf), buf.bytes, buf.dropped, buf.dropped_bytes) == (1, 1000, 11, 1250)
        assert buf.put(12, "s", body(12, 1001)) == -1  # alone too large: refused, counted, nothing lost
        assert [r.t_ms for r in buf.pending(100)] == [11]
        assert (buf.dropped, buf.dropped_bytes) == (12, 2251)
        status = buf.get_status()
        assert status == {
            "path": str(path),
            "records": 1,
            "bytes": 1000,
            "max_bytes": 1000,
            "dropped": 12,
            "dropped_bytes": 2251,
            "oldest_t_ms": 11,
        }
    # the counts kept in memory are the ones on disk
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT COUNT(*), SUM(length(body)) FROM records").fetchone() == (1, 1000)
    db.close()


def test_everything_survives_close_and_reopen(path):
    buf = StoreAndForward(path, 500)
    ids = [buf.put(i, "s", body(i)) for i in range(7)]  # 700 bytes: two dropped
    buf.set_meta("bdseq", 41)
    buf.set_meta("sample", 2**40)
    buf.set_meta("bdseq", 42)
    buf.ack([ids[2]])
    buf.close()
    buf.close()  # twice is fine

    with StoreAndForward(path, 500) as buf:
        assert [r.id for r in buf.pending(100)] == ids[3:]
        assert [r.body for r in buf.pending(100)] == [body(i) for i in range(3, 7)]
        assert (len(buf), buf.bytes, buf.dropped, buf.dropped_bytes) == (4, 400, 2, 200)
        assert (buf.get_meta("bdseq"), buf.get_meta("sample"), buf.get_meta("nothing", -1)) == (42, 2**40, -1)
        buf.ack(ids)
        later = buf.put(99, "s", b"after")
        assert later > ids[-1]

    with StoreAndForward(path, 250) as buf:  # a lower limit holds at once
        assert [r.id for r in buf.pending(100)] == [later]
        assert buf.put(100, "s", body(100)) > later


def test_a_lowered_limit_drops_the_oldest_on_open(path):
    with StoreAndForward(path, 10_000) as buf:
        ids = [buf.put(i, "s", body(i)) for i in range(10)]
    with StoreAndForward(path, 450) as buf:
        assert [r.id for r in buf.pending(100)] == ids[6:]
        assert (buf.bytes, buf.dropped, buf.dropped_bytes) == (400, 6, 600)


def test_two_threads_at_once(path):
    with StoreAndForward(path, 1 << 20) as buf:

        def writer(k: int) -> None:
            for i in range(200):
                buf.put(i, f"w{k}", body(i, 10))

        threads = [threading.Thread(target=writer, args=(k,)) for k in range(2)]
        for t in threads:
            t.start()
        acked = 0
        while any(t.is_alive() for t in threads) or buf.pending(1):
            got = buf.pending(50)
            buf.ack(r.id for r in got)
            acked += len(got)
        for t in threads:
            t.join()
        assert acked == 400 and len(buf) == 0 and buf.bytes == 0


def test_a_second_opener_of_the_same_buffer_is_refused(path):
    # another compd started with the same config would send the same samples twice
    with StoreAndForward(path, 1000), pytest.raises(BadInput, match="locked"):
        StoreAndForward(path, 1000)


WRITER = """
import sys
from pathlib import Path
from compd.plant.buffer import StoreAndForward
buf = StoreAndForward(Path(sys.argv[1]), 1 << 30)
i = 0
while True:
    rid = buf.put(i, "sample", str(i).encode().rjust(2000, b"."))
    sys.stdout.write(f"{rid} {i}\\n")  # after the commit: put() returned
    sys.stdout.flush()
    i += 1
"""


def test_kill_9_loses_nothing_committed(path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, env=env, text=True)
    committed = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            committed.append(tuple(map(int, line.split())))
            if len(committed) >= 3000:  # 6 MB: past a WAL checkpoint (every 4 MB)
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        # what it wrote before the kill; a line the kill cut short does not count
        committed += [tuple(map(int, line.split())) for line in proc.stdout if line.endswith("\n")]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert len(committed) >= 3000

    with StoreAndForward(path, 1 << 30) as buf:
        records = buf.pending(100_000)
        ids = [r.id for r in records]
        numbers = [r.t_ms for r in records]
        assert ids == sorted(set(ids))  # in order, no duplicate
        assert numbers == list(range(len(records)))  # every sample once, none missing in between
        assert all(r.body == str(r.t_ms).encode().rjust(2000, b".") for r in records)
        assert set(committed) <= {(r.id, r.t_ms) for r in records}  # everything put() returned is there
        assert buf.put(-1, "sample", b"after") > ids[-1]


def test_a_corrupt_file_is_renamed_aside_and_kept(path, warnings):
    garbage = b"this is not an SQLite database\n" * 200
    path.write_bytes(garbage)
    with StoreAndForward(path, 1000) as buf:
        assert len(buf) == 0 and buf.put(1, "s", b"x") == 1
    aside = [p for p in path.parent.iterdir() if p.name.startswith(path.name + ".corrupt-")]
    assert len(aside) == 1 and aside[0].read_bytes() == garbage
    assert len(warnings) == 1 and warnings[0].event == "telemetry_buffer_corrupt"
    assert warnings[0].moved_to == str(aside[0]) and "\n" not in warnings[0].getMessage()

    path.unlink()
    path.write_bytes(garbage)  # a second one in the same second gets a name of its own
    StoreAndForward(path, 1000).close()
    assert len([p for p in path.parent.iterdir() if ".corrupt-" in p.name]) == 2


def test_a_damaged_page_is_found_and_the_file_set_aside(path, warnings):
    with StoreAndForward(path, 1 << 20) as buf:
        for i in range(200):
            buf.put(i, "s", body(i, 500))
    data = bytearray(path.read_bytes())
    page = 4096
    data[5 * page : 6 * page] = b"\xa5" * page  # one page of the records' tree overwritten
    path.write_bytes(bytes(data))
    with StoreAndForward(path, 1 << 20) as buf:
        assert len(buf) == 0
    (aside,) = [p for p in path.parent.iterdir() if ".corrupt-" in p.name and not p.name.endswith(("-wal", "-shm"))]
    assert aside.read_bytes() == bytes(data)
    assert len(warnings) == 1


def test_another_programs_database_is_not_used(path, warnings):
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE invoices (n INTEGER)")
        db.execute("INSERT INTO invoices VALUES (7)")
    db.close()
    original = path.read_bytes()
    StoreAndForward(path, 1000).close()
    (aside,) = [p for p in path.parent.iterdir() if ".corrupt-" in p.name]
    assert aside.read_bytes() == original
    assert "not a telemetry buffer" in warnings[0].reason


def test_a_buffer_from_a_newer_compd_is_left_alone(path, warnings):
    StoreAndForward(path, 1000).close()
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version = 2")
    db.close()
    original = path.read_bytes()
    with pytest.raises(BadInput, match="schema version 2, from a newer compd"):
        StoreAndForward(path, 1000)
    assert path.read_bytes() == original and not warnings
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_a_missing_folder_is_bad_input(tmp_path):
    missing = tmp_path / "nowhere" / "telemetry.sqlite"
    with pytest.raises(BadInput) as e:
        StoreAndForward(missing, 1000)
    assert str(missing) in str(e.value) and "does not exist" in str(e.value)
    assert "\n" not in str(e.value)
    assert not missing.parent.exists()


def test_a_path_that_cannot_be_opened_is_bad_input(tmp_path):
    folder = tmp_path / "a-folder.sqlite"
    folder.mkdir()
    with pytest.raises(BadInput, match="cannot open the telemetry buffer") as e:
        StoreAndForward(folder, 1000)
    assert str(folder) in str(e.value)
    assert list(tmp_path.iterdir()) == [folder]  # nothing renamed, nothing made


def test_the_memory_buffer_keeps_the_newest_within_its_bound_and_hands_them_over():
    """While the file cannot be written: the same calls in memory, the oldest dropped and counted when full."""
    from compd.plant.buffer import MemoryBuffer

    mem = MemoryBuffer(max_bytes=250)
    ids = [mem.put(i, "D", bytes([i]) * 100) for i in range(4)]
    assert ids == [1, 2, 3, 4] and len(mem) == 2 and mem.bytes == 200  # 1 and 2 dropped for room
    assert (mem.dropped, mem.dropped_bytes) == (2, 200)
    assert mem.put(9, "D", b"x" * 251) == -1 and mem.dropped == 3  # too large alone: refused, counted
    assert [r.id for r in mem.pending(10)] == [3, 4] and [r.id for r in mem.pending(10, after_id=3)] == [4]
    mem.ack([3, 77])
    assert [r.t_ms for r in mem.pending(10)] == [3]
    mem.set_meta("sample", 5)
    assert mem.get_meta("sample") == 5 and mem.get_meta("bdseq", -1) == -1
    assert mem.get_status()["records"] == 1 and mem.get_status()["path"] is None
    assert [r.body for r in mem.take()] == [bytes([3]) * 100] and len(mem) == 0 and mem.bytes == 0
    assert mem.put(0, "D", b"y") == 5  # ids never given twice
