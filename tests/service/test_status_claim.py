"""Two instances on one status file: check-config and run refuse the second while the first is alive."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from compd.cli import main
from compd.service import status as status_mod
from tests.core.test_config import GOOD

CONFIG = GOOD + "status: {path: shared.json}\n"


def _other_daemon(path: Path, state: str = "running") -> None:
    """The status file of another compd: a live process (our parent), updated just now."""
    status_mod.write_atomic(
        path,
        {
            "schema": status_mod.SCHEMA,
            "pid": os.getppid(),
            "state": state,
            "written_unix_s": time.time(),
            "status_period_s": 1.0,
            "config": "/elsewhere/other.yaml",
        },
    )


def test_a_live_daemons_status_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    _other_daemon(tmp_path / "shared.json")
    line = CONFIG.splitlines().index("status: {path: shared.json}") + 1
    for argv in (["check-config", str(cfg)], ["run", str(cfg), "--duration", "1"]):
        assert main(argv) == 2
        out, err = capsys.readouterr()
        assert "cycles" not in out
        assert err.startswith(
            f"compd: {cfg}:{line}: status.path: {tmp_path / 'shared.json'} is the status file"
            f" of a running compd (pid {os.getppid()}, config /elsewhere/other.yaml)"
        ), err
        assert len(err.splitlines()) == 1


def test_a_stale_daemons_status_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Its cycle stopped or hung, its service writing on: it may run again, the file is not free."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    _other_daemon(tmp_path / "shared.json", state="stale")
    assert main(["check-config", str(cfg)]) == 2
    assert "is the status file of a running compd" in capsys.readouterr().err


def test_a_stopped_daemons_status_file_is_taken_over(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    _other_daemon(tmp_path / "shared.json", state="stopped")
    assert main(["check-config", str(cfg)]) == 0
    assert main(["run", str(cfg), "--duration", "1"]) == 0
    assert status_mod.read_status(tmp_path / "shared.json")["pid"] == os.getpid()
    capsys.readouterr()
