"""key=value log lines: one line per event, journald priority prefix, set up once."""

from __future__ import annotations

import logging
import os
import sys

from compd.service.logsetup import KeyValueFormatter, setup_logging, stderr_is_journal


def _record(msg: str, level: int = logging.WARNING, **extra) -> logging.LogRecord:
    rec = logging.LogRecord("compd.service", level, __file__, 1, msg, (), None)
    for k, v in extra.items():
        setattr(rec, k, v)
    return rec


def test_terminal_line():
    line = KeyValueFormatter().format(
        _record("T_xi bad: stale", event="sensor_bad", sensor="T_xi", t_s=812.25, note='say "hi"\nthere')
    )
    assert line.startswith("ts=")
    assert "\n" not in line
    assert ' level=warning event=sensor_bad msg="T_xi bad: stale" sensor=T_xi t_s=812.25' in line
    assert line.endswith('note="say \\"hi\\" there"')


def test_journal_line_has_priority_prefix_and_no_time():
    fmt = KeyValueFormatter(journal=True)
    assert fmt.format(_record("x", logging.WARNING, event="late_cycles")).startswith("<4>level=warning")
    assert fmt.format(_record("x", logging.INFO)).startswith("<6>level=info event=service ")
    assert fmt.format(_record("x", logging.ERROR)).startswith("<3>")


def test_journal_detection(tmp_path, monkeypatch):
    with open(tmp_path / "err", "w") as fh:
        st = os.fstat(fh.fileno())
        monkeypatch.setattr(sys, "stderr", fh)
        assert stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        assert not stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
        assert not stderr_is_journal({})


def test_setup_is_idempotent_and_follows_sys_stderr(tmp_path, monkeypatch):
    logger = logging.getLogger("compd")
    before = list(logger.handlers)
    level = logger.level
    try:
        setup_logging("warning", journal=False)
        setup_logging("info", journal=False)
        ours = [h for h in logger.handlers if h not in before]
        assert len(ours) == 1
        with open(tmp_path / "err", "w") as fh:
            monkeypatch.setattr(sys, "stderr", fh)
            logging.getLogger("compd.guard").info("hello", extra={"event": "test", "axis": "z"})
            logging.getLogger("compd.guard").debug("not shown")
        lines = (tmp_path / "err").read_text().splitlines()
        assert len(lines) == 1 and "event=test" in lines[0] and "axis=z" in lines[0]
    finally:
        for h in list(logger.handlers):
            if h not in before:
                logger.removeHandler(h)
        logger.setLevel(level)
