"""The log CSV: malformed files name row and column; the writer loses nothing on close."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest

from compd.errors import BadInput
from compd.log import LogWriter, is_temperature_column, read_log, write_log


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


def test_writer_rotates_by_time(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    w = LogWriter(path, ["t_s", "T1"], flush_s=0.01, rotate_s=0.05)
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
