"""Shared fixtures. Every test must leave no thread, child process or socket behind."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _sockets() -> set[str]:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(target)
    return out


def _children() -> set[int]:
    me = os.getpid()
    kids = set()
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == me and fields[0] != "Z":
            kids.add(int(pid))
    return kids


@pytest.fixture(autouse=True)
def no_leaks():
    """Fail a test that leaves a thread, a child process or a socket open."""
    threads = set(threading.enumerate())
    socks = _sockets()
    kids = _children()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        extra_threads = [t for t in threading.enumerate() if t not in threads and t.is_alive()]
        extra_socks = _sockets() - socks
        extra_kids = _children() - kids
        if not (extra_threads or extra_socks or extra_kids) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    problems = []
    if extra_threads:
        problems.append(f"threads left running: {[t.name for t in extra_threads]}")
    if extra_socks:
        problems.append(f"sockets left open: {len(extra_socks)}")
    if extra_kids:
        problems.append(f"child processes left running: {sorted(extra_kids)}")
    if problems:
        pytest.fail("; ".join(problems))


@pytest.fixture
def root() -> Path:
    return ROOT
