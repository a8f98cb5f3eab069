"""The log CSV: malformed files name row and column; the writer loses nothing on close."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest

from compd.core.errors import BadInput
from compd.log import is_temperature_column, read_log, write_log
from compd.service.logwriter import LogWriter


def csv(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "log.csv"
    p.write_text(text)
    return p


def test_reads_a_good_log(tmp_path: Path) -> None:
    log = read_log(csv(tmp_path, "t_s,T1,err_x_um\n0,20.0,0\n1,20.5,1.5\n1,20.6,1.6\n"))
    assert log.columns == ["t_s", "T1", "err_x_um"]
    assert log.data.shape == (3, 3)
    assert log.temperature_columns() == ["T1"]
    assert log.error_columns() == ["err_x_um"]


@pytest.mark.parametrize(
    ("text", "line", "path", "what"),
    [
        ("time,T1\n0,1\n", 1, "time", "first column must be 't_s'"),
        ("t_s,T1\n0,20\n1,abc\n", 3, "T1", "not a number"),
        ("t_s,T1\n0,20\n2,20\n1,20\n", 4, "t_s", "backwards"),
        ("t_s,T1\n0,20,5\n", 2, None, "cells"),
        ("t_s,T1\n0,\n", 2, "T1", "not a number"),
        ("t_s,T1,T1\n0,1,2\n", 1, "T1", "twice"),
    ],
)
def test_malformed_log_names_row_and_column(tmp_path, text, line, path, what) -> None:  # noqa: ANN001
    with pytest.raises(BadInput) as ei:
        read_log(csv(tmp_path, text))
    e = ei.value
    assert e.line == line and e.path == path and what in e.message
    assert str(e).startswith(str(tmp_path / "log.csv"))


def test_empty_and_missing(tmp_path: Path) -> None:
    with pytest.raises(BadInput, match="empty"):
        read_log(csv(tmp_path, ""))
    with pytest.raises(BadInput, match="cannot read"):
        read_log(tmp_path / "missing.csv")


def test_temperature_columns_follow_contract() -> None:
    for name in ("t_s", "err_x_um", "pos_y_mm", "speed_rpm", "current_y_a"):
        assert not is_temperature_column(name)
    assert is_temperature_column("T_xi")


def test_writer_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "w.csv"
    w = LogWriter(path, ["t_s", "T1", "err_z_um"], flush_s=0.05)
    rows = [(float(i), 20.0 + i / 10, i / 3) for i in range(500)]
    for r in rows:
        w.push(r)
    w.close()
    log = read_log(path)
    assert len(log) == 500 and w.rows_written == 500 and w.error is None
    np.testing.assert_allclose(log.data, np.array(rows), rtol=1e-5)


def test_write_log_and_read_back(tmp_path: Path) -> None:
    data = np.array([[0.0, 21.25, -0.5], [60.0, 22.0, 1.25]])
    write_log(tmp_path / "a.csv", ["t_s", "T", "err_z_um"], data)
    np.testing.assert_allclose(read_log(tmp_path / "a.csv").data, data)


def test_writer_rotates_by_size_and_every_file_is_a_log(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    w = LogWriter(path, ["t_s", "T1"], flush_s=0.01, rotate_bytes=1024, keep=3)
    for i in range(400):
        w.push((float(i), 20.0 + i / 100))
        if i % 20 == 19:
            time.sleep(0.03)  # let the writer flush (rotation is checked at a flush)
    w.close()
    files = sorted(tmp_path.glob("run.csv*"))
    assert w.rotations >= 2 and len(files) <= 4  # the live file and at most keep=3 old ones
    assert not tmp_path.joinpath("run.csv.4").exists()
    t_all = []
    for f in files:
        log = read_log(f)
        assert log.columns == ["t_s", "T1"]
        t_all.extend(log.t_s.tolist())
    # the kept files hold the newest rows, none twice, the last one included
    assert len(set(t_all)) == len(t_all) and max(t_all) == 399.0


def test_an_idle_flush_never_rotates_the_logged_rows_away(tmp_path: Path) -> None:
    """With keep 0 a rotated file is deleted: a rotation must come with rows to write, or a
    file over rotate_bytes that an idle flush rotated would leave the log empty at the end.
    The writer's own thread does the idle flushes (the test never calls into it: two threads
    flushing one pending buffer would write its rows twice)."""
    path = tmp_path / "run.csv"
    w = LogWriter(path, ["t_s", "T1"], flush_s=0.01, rotate_bytes=100, keep=0)
    try:
        for i in range(20):
            w.push((float(i), 20.0))
        deadline = time.monotonic() + 60
        while not (path.exists() and path.stat().st_size >= 100 and w._q.empty()):  # all handed over
            assert time.monotonic() < deadline, path.read_text() if path.exists() else "no file"
            time.sleep(0.01)
        idle_from = w.flushes + 1  # the turn that took the last row may still be writing it
        while w.flushes < idle_from + 5:  # five idle flushes of the writer's thread
            assert time.monotonic() < deadline, f"{w.flushes} flushes"
            time.sleep(0.01)
    finally:
        w.close()
    assert len(read_log(path)) >= 1


def test_writer_rotates_by_time(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    # keep enough files for every rotation a slow machine may make (the oldest beyond `keep`
    # is dropped by design, so a small keep would make the row count depend on timing)
    w = LogWriter(path, ["t_s", "T1"], flush_s=0.01, rotate_s=0.05, keep=100)
    for i in range(10):
        w.push((float(i), 20.0))
        time.sleep(0.03)
    w.close()
    assert w.rotations >= 1
    assert sum(len(read_log(f)) for f in tmp_path.glob("run.csv*")) == 10


def test_writer_survives_a_full_disk(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # /dev/full answers every write with ENOSPC
    with caplog.at_level(logging.ERROR, logger="compd"):
        w = LogWriter("/dev/full", ["t_s", "T1"], flush_s=0.01)
        for i in range(5):
            w.push((float(i), 20.0))
        w.close()
    assert w.rows_written == 0 and w.rows_dropped == 5
    assert "No space left on device" in (w.error or "")
    errs = [r for r in caplog.records if getattr(r, "event", None) == "log_error"]
    assert len(errs) == 1 and "No space left" in errs[0].reason  # one line, not one per row


def test_writer_repairs_a_row_cut_by_a_crash(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t_s,T1\n0,20\n1,20.5\n2,2")  # kill -9 in the middle of a row
    w = LogWriter(path, ["t_s", "T1"], flush_s=0.01)
    w.push((3.0, 21.0))
    w.close()
    log = read_log(path)
    assert log.t_s.tolist() == [0.0, 1.0, 3.0] and w.repaired_bytes == 3


def test_writer_sets_aside_a_log_with_other_columns(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("t_s,T_old\n0,20\n")  # the config changed between runs
    w = LogWriter(path, ["t_s", "T1", "T2"], flush_s=0.01)
    w.push((1.0, 21.0, 22.0))
    w.close()
    assert read_log(path).columns == ["t_s", "T1", "T2"] and len(read_log(path)) == 1
    assert read_log(tmp_path / "run.csv.1").columns == ["t_s", "T_old"]


# ------------------------------------------------------------ crash and power-cut repair
def _rows(n: int, t0: int = 0) -> bytes:
    return b"".join(f"{t0 + i},{20 + i / 100:.2f},{i / 3:.4f}\n".encode() for i in range(n))


HEADER = b"t_s,T1,err_z_um\n"
COLUMNS = ["t_s", "T1", "err_z_um"]


def _reopen(path: Path, caplog: pytest.LogCaptureFixture, rows: int = 1, t0: float = 1e6) -> LogWriter:
    with caplog.at_level(logging.INFO, logger="compd"):
        w = LogWriter(path, COLUMNS, flush_s=0.01)
        for i in range(rows):
            w.push((t0 + i, 30.0, 1.0))
        w.close()
    return w


def _side_files(path: Path) -> list[Path]:
    return sorted(path.parent.glob(path.name + ".damaged-*"))


def _repaired_events(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if getattr(r, "event", None) == "log_repaired"]


def test_power_cut_nul_tail_keeps_every_row_and_sets_the_tail_aside(tmp_path, caplog) -> None:  # noqa: ANN001
    # 478 rows, then 100 KiB of NULs (size committed, data not): no newline in the last 64 KiB
    path = tmp_path / "run.csv"
    tail = b"\0" * 100 * 1024
    path.write_bytes(HEADER + _rows(478) + tail)
    w = _reopen(path, caplog)
    log = read_log(path)
    assert len(log) == 479 and log.t_s[:478].tolist() == list(range(478)) and log.t_s[-1] == 1e6
    [side] = _side_files(path)
    assert side.read_bytes() == tail
    assert w.repaired_bytes == len(tail) and w.error is None
    [ev] = _repaired_events(caplog)
    assert ev.rows_kept == 478 and ev.bytes_set_aside == len(tail) and ev.side_file == str(side)


def test_cut_row_then_nuls_then_garbage_and_bad_rows(tmp_path, caplog) -> None:  # noqa: ANN001
    # before the end: a row with a cell too few, a non-number, a cut row, NULs, binary garbage
    path = tmp_path / "run.csv"
    tail = b"478,20.5\n479,abc,1\n480,20.9,1." + b"\0" * 5000 + b"\xff\xfe garbage \x01"
    path.write_bytes(HEADER + _rows(478) + tail)
    _reopen(path, caplog)
    assert len(read_log(path)) == 479
    [side] = _side_files(path)
    assert side.read_bytes() == tail
    [ev] = _repaired_events(caplog)
    assert ev.lines_set_aside == 3 and ev.rows_kept == 478


def test_repair_never_overwrites_an_earlier_side_file(tmp_path, caplog) -> None:  # noqa: ANN001
    path = tmp_path / "run.csv"
    path.write_bytes(HEADER + _rows(5) + b"5,2")
    _reopen(path, caplog)
    path.write_bytes(path.read_bytes() + b"\0" * 10)  # a second crash, within the same second
    _reopen(path, caplog, t0=2e6)
    sides = _side_files(path)
    assert sorted(s.read_bytes() for s in sides) == [b"\0" * 10, b"5,2"]
    assert len(read_log(path)) == 7


def test_a_file_of_nuls_only_is_set_aside_whole(tmp_path, caplog) -> None:  # noqa: ANN001
    path = tmp_path / "run.csv"
    path.write_bytes(b"\0" * 200_000)
    _reopen(path, caplog)
    assert read_log(path).columns == COLUMNS and len(read_log(path)) == 1
    [side] = _side_files(path)
    assert side.read_bytes() == b"\0" * 200_000
    [ev] = _repaired_events(caplog)
    assert ev.action == "whole" and ev.rows_kept == 0


def test_a_damaged_header_sets_the_file_aside_whole(tmp_path, caplog) -> None:  # noqa: ANN001
    path = tmp_path / "run.csv"
    text = b"t_s,T1,err\0\0\0\n0,20,1\n"
    path.write_bytes(text)
    _reopen(path, caplog)
    assert read_log(path).columns == COLUMNS
    [side] = _side_files(path)
    assert side.read_bytes() == text


def test_a_nul_block_inside_is_moved_aside_and_the_rows_after_it_stay(tmp_path, caplog) -> None:  # noqa: ANN001
    # delayed allocation: a page of the middle never reached the disk, later rows did
    path = tmp_path / "run.csv"
    before, after = _rows(100), _rows(100, t0=200)
    hole = b"100,20.1" + b"\0" * 8192 + b"9,0.3333\n"  # the page boundary cuts rows on both sides
    path.write_bytes(HEADER + before + hole + after + b"300,2")
    _reopen(path, caplog)
    log = read_log(path)
    assert log.t_s.tolist() == [*range(100), *range(200, 300), 1e6]
    [side] = _side_files(path)
    assert side.read_bytes() == hole + b"300,2"
    [ev] = _repaired_events(caplog)
    assert ev.action == "body" and ev.rows_kept == 200 and ev.lines_set_aside == 2


def test_a_good_log_is_left_alone(tmp_path, caplog) -> None:  # noqa: ANN001
    path = tmp_path / "run.csv"
    path.write_bytes(HEADER + _rows(10))
    w = _reopen(path, caplog)
    assert len(read_log(path)) == 11 and w.repaired_bytes == 0
    assert _side_files(path) == [] and _repaired_events(caplog) == []


def test_other_columns_are_set_aside_even_when_no_rotated_file_is_kept(tmp_path, caplog) -> None:  # noqa: ANN001
    path = tmp_path / "run.csv"
    path.write_text("t_s,T_old\n0,20\n")
    with caplog.at_level(logging.INFO, logger="compd"):
        w = LogWriter(path, COLUMNS, flush_s=0.01, keep=0)
        w.close()
    [old] = sorted(tmp_path.glob("run.csv.columns-*"))
    assert old.read_text() == "t_s,T_old\n0,20\n" and read_log(path).columns == COLUMNS


def test_reader_names_row_and_column_of_nul_bytes(tmp_path: Path) -> None:
    path = tmp_path / "log.csv"
    path.write_bytes(HEADER + _rows(3) + b"\0" * 100_000)
    with pytest.raises(BadInput) as ei:
        read_log(path)
    assert ei.value.line == 5 and ei.value.path == "t_s" and "NUL" in ei.value.message
    assert len(str(ei.value)) < 300
    path.write_bytes(HEADER + b"0,20.0,1" + b"\0" * 500 + b"\n")
    with pytest.raises(BadInput) as ei:
        read_log(path)
    assert ei.value.line == 2 and ei.value.path == "err_z_um" and "NUL" in ei.value.message


def test_reader_cuts_a_long_garbage_cell(tmp_path: Path) -> None:
    path = tmp_path / "log.csv"
    path.write_bytes(HEADER + b"0,20," + b"x" * 10_000 + b"\n")
    with pytest.raises(BadInput) as ei:
        read_log(path)
    assert ei.value.path == "err_z_um" and len(str(ei.value)) < 300


def test_repair_reads_a_long_nul_tail_in_bounded_memory(tmp_path: Path) -> None:
    import tracemalloc

    from compd.log import repair_log

    path = tmp_path / "run.csv"
    with open(path, "wb") as fh:
        fh.write(HEADER + _rows(50))
        for _ in range(32):
            fh.write(b"\0" * (1 << 20))  # 32 MiB, not a newline in it
    tracemalloc.start()
    try:
        r = repair_log(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert r.action == "tail" and r.rows_kept == 50 and r.bytes_set_aside == 32 << 20
    assert peak < 2 << 20  # chunks, not the file
    assert len(read_log(path)) == 50


def test_a_repair_that_fails_leaves_the_log_alone_and_drops_rows(tmp_path, caplog, monkeypatch) -> None:  # noqa: ANN001
    import errno

    import compd.log

    def no_space(path: Path, what: str) -> tuple[int, Path]:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(compd.log, "_side_file", no_space)
    path = tmp_path / "run.csv"
    damaged = HEADER + _rows(5) + b"\0" * 100
    path.write_bytes(damaged)
    with caplog.at_level(logging.ERROR, logger="compd"):
        w = LogWriter(path, COLUMNS, flush_s=0.01)
        w.push((9.0, 1.0, 2.0))
        w.close()
    assert path.read_bytes() == damaged  # nothing appended after the NULs, nothing cut
    assert w.rows_dropped == 1 and "No space left" in (w.error or "")
