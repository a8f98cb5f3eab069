"""`loop.io: process` relies on x86-64's store order (the seqlocks between processes): on another
CPU the default is threads, and asking for processes is bad input naming the key."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from compd.config import load_config
from compd.core.errors import BadInput
from tests.conftest import ROOT


def _cfg(tmp_path: Path, io: str | None) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    cfg.setdefault("loop", {}).pop("io", None)
    if io is not None:
        cfg["loop"]["io"] = io
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_on_x86_64_the_default_is_processes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    assert load_config(_cfg(tmp_path, None)).top.loop.io == "process"


def test_elsewhere_the_default_is_threads_and_processes_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert load_config(_cfg(tmp_path, None)).top.loop.io == "thread"
    assert load_config(_cfg(tmp_path, "thread")).top.loop.io == "thread"
    with pytest.raises(BadInput) as e:
        load_config(_cfg(tmp_path, "process"))
    text = str(e.value)
    assert "loop.io" in text and "x86-64" in text and "aarch64" in text


def test_check_config_says_it_in_one_line_with_exit_2(tmp_path: Path) -> None:
    """The refusal through the command line (the CPU faked in a child interpreter)."""
    path = _cfg(tmp_path, "process")
    code = (
        "import platform, sys; platform.machine = lambda: 'riscv64'; "
        "from compd.cli import main; sys.exit(main(['check-config', sys.argv[1]]))"
    )
    r = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "c.yaml" in lines[0] and "loop.io" in lines[0] and "riscv64" in lines[0]
