"""Signals in the first second of `compd run`, while it reads its config and builds its pipeline: a SIGHUP
is a reload served once the loop runs (it killed compd with exit 129 and no line), a SIGTERM ends it
cleanly (exit 0) with nothing opened."""

from __future__ import annotations

import ctypes
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.daemon.test_reload import CONFIG, wait_for

IN_OPEN = 0x20  # <sys/inotify.h>


class OpenWatch:
    """Tells when a process opens a file (inotify IN_OPEN): `compd run` opens its config once it
    reads it, after its signal handlers are in place and before its pipeline is built."""

    def __init__(self, path: Path) -> None:
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self.libc.inotify_init1(os.O_CLOEXEC | os.O_NONBLOCK)
        if self.fd < 0:
            pytest.fail(f"inotify_init1: {os.strerror(ctypes.get_errno())}")
        if self.libc.inotify_add_watch(self.fd, os.fsencode(path), IN_OPEN) < 0:
            os.close(self.fd)
            pytest.fail(f"inotify_add_watch {path}: {os.strerror(ctypes.get_errno())}")

    def wait(self, proc: subprocess.Popen[bytes], timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                pytest.fail(f"compd ended (exit {proc.returncode}) before it opened its config")
            if select.select([self.fd], [], [], 0.05)[0]:
                os.read(self.fd, 4096)
                return
        pytest.fail("compd did not open its config in time")

    def close(self) -> None:
        os.close(self.fd)


def _start(tmp_path: Path, err_path: Path) -> tuple[subprocess.Popen[bytes], OpenWatch]:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(slew=0.05))
    watch = OpenWatch(cfg)
    with open(err_path, "wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    return proc, watch


def _stop(proc: subprocess.Popen[bytes]) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise


@pytest.mark.parametrize("attempt", range(3))
def test_a_sighup_while_compd_starts_is_a_reload(tmp_path: Path, attempt: int) -> None:
    err_path = tmp_path / "stderr.txt"
    proc, watch = _start(tmp_path, err_path)
    try:
        watch.wait(proc)
        proc.send_signal(signal.SIGHUP)  # while it reads the config: before its pipeline exists
        wait_for(lambda: "reloaded" in err_path.read_text() or proc.poll() is not None)
        assert proc.poll() is None, f"compd ended with {proc.returncode}: {err_path.read_text()}"
        assert err_path.read_text().count("compd: reloaded ") == 1
        assert _stop(proc) == 0, err_path.read_text()
    finally:
        watch.close()
        if proc.poll() is None:
            _stop(proc)
    assert "Traceback" not in err_path.read_text()


def test_a_sigterm_while_compd_starts_ends_it_cleanly(tmp_path: Path) -> None:
    err_path = tmp_path / "stderr.txt"
    proc, watch = _start(tmp_path, err_path)
    try:
        watch.wait(proc)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, err_path.read_text()
    finally:
        watch.close()
        if proc.poll() is None:
            _stop(proc)
    err = err_path.read_text()
    assert "stopped before the loop started: nothing was opened" in err and "Traceback" not in err
    assert not (tmp_path / "run.csv").exists()  # nothing was opened
