"""Fits show a progress bar only when stderr is a terminal (issue 40): into a file or a pipe its redraws are noise."""

from __future__ import annotations

import io
import sys

from compd.identify.data import progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_no_bar_when_stderr_is_not_a_terminal(monkeypatch):
    sink = io.StringIO()  # a log file or a pipe: isatty() is False
    monkeypatch.setattr(sys, "stderr", sink)
    items = [1, 2, 3]
    assert progress(items, desc="fitting") is items  # the iterable itself, no tqdm around it
    assert list(progress(iter(items), desc="fitting", total=3)) == items
    assert sink.getvalue() == ""


def test_bar_when_stderr_is_a_terminal(monkeypatch):
    tty = _Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    items = [1, 2, 3]
    bar = progress(items, desc="fitting")
    assert bar is not items
    assert list(bar) == items
