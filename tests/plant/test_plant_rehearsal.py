"""Walks docs/plant.md's rehearsal as written, in an empty dir: a broker, compd with telemetry and OPC UA, two clients.

Every fenced block of the section "Rehearsal" is taken in order: a ```yaml block after
`<!-- file: NAME -->` is written to NAME, every ```console block is run line by line (`$ COMMAND`,
then the output the page shows). A command ending in ` &` is started and left running (the broker,
compd) and stopped at the end; `compd status` is asked again until what the page shows is printed
(compd needs a moment to reach the broker). `compd`, `python` and `uaread` are this checkout's;
the one change to the page's text is the ports (1884, 4841 → free ports).

A shown line must be printed exactly (spacing aside), except `…`, which stands for text that
depends on the time or the machine (a value, a time stamp).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.commissioning.test_commissioning import blocks, doc_folder, free_port
from tests.service_helpers import wait_running

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "plant.md"
SECTION = "## Rehearsal"
MQTT_PORT, OPCUA_PORT = "1884", "4841"
DEADLINE_S = 120.0  # for compd to reach the broker and serve OPC UA: generous, never a speed assertion


def section(text: str) -> str:
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    return text[start:] if end < 0 else text[start:end]


def shown_pattern(line: str) -> re.Pattern[str]:
    """The shown line as a pattern: words and numbers as written, `…` anything, spacing free."""
    parts = [re.escape(p) for p in " ".join(line.split()).split("…")]
    return re.compile(r"\s*" + ".*?".join(parts) + r"\s*")


def missing(shown: list[str], printed: str) -> list[str]:
    lines = [" ".join(p.split()) for p in printed.splitlines()]
    return [s for s in shown if not any(shown_pattern(s).fullmatch(p) for p in lines)]


def test_the_pattern_is_strict() -> None:
    assert shown_pattern("a = … µm  (Double, alias 13)").fullmatch("a = -15.93 µm (Double, alias 13)")
    assert not shown_pattern("a = … µm  (Double, alias 13)").fullmatch("a = -15.93 µm (Double, alias 14)")
    assert not shown_pattern("bdSeq = 0  (UInt64, alias 1)").fullmatch("bdSeq = 10 (UInt64, alias 1)")


@pytest.fixture()
def shell(tmp_path: Path):
    work, env = doc_folder(tmp_path, {"uaread": f'"{Path(sys.executable).parent / "uaread"}"'})
    started: list[subprocess.Popen] = []

    def run(command: str, background: bool = False):
        argv = ["bash", "-o", "pipefail", "-c", command]
        if background:
            p = subprocess.Popen(
                argv,
                cwd=work,
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            started.append(p)
            return p
        return subprocess.run(argv, cwd=work, env=env, capture_output=True, text=True, timeout=300)

    run.work = work  # type: ignore[attr-defined]
    run.started = started  # type: ignore[attr-defined]
    yield run
    for p in reversed(started):  # compd first (it says goodbye to the broker), then the broker
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
            try:
                p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()


def test_the_plant_rehearsal_runs_as_written(shell, tmp_path: Path) -> None:
    work: Path = shell.work
    ports = {MQTT_PORT: str(free_port()), OPCUA_PORT: str(free_port())}

    def localize(text: str) -> str:
        for old, new in ports.items():
            text = text.replace(old, new)
        return text

    page = blocks_of(section(PAGE.read_text(encoding="utf-8")), tmp_path)
    assert any(b.marker.startswith("file: ") for b in page) and sum(b.lang == "console" for b in page) >= 3
    compd_run: subprocess.Popen | None = None
    ran: list[str] = []
    for b in page:
        if b.marker.startswith("file: "):
            (work / b.marker[6:]).write_text(localize(b.body))
            continue
        if b.lang != "console":
            continue
        for command, shown in b.commands:
            command, shown = localize(command), [localize(s) for s in shown]
            ran.append(command)
            if command.endswith(" &"):
                p = shell(command[:-2], background=True)
                if command.startswith("compd run "):
                    compd_run = p
                    wait_running(work / "plant.status.json", p)
                continue
            deadline = time.monotonic() + DEADLINE_S
            while True:
                r = shell(command)
                lost = missing(shown, r.stdout)
                if r.returncode == 0 and not lost:
                    break
                if not command.startswith("compd status") or time.monotonic() > deadline:
                    raise AssertionError(
                        f"`{command}` exited {r.returncode}; the page shows\n  "
                        + "\n  ".join(lost)
                        + f"\nit printed:\n{r.stdout}\n{r.stderr}"
                    )
                time.sleep(0.5)
    assert compd_run is not None and compd_run.poll() is None, "compd ended before the rehearsal did"
    for needed in ("mosquitto ", "compd run plant.yaml", "compd sparkplug-watch ", "uaread "):
        assert any(c.startswith(needed) for c in ran), needed
    os.killpg(compd_run.pid, signal.SIGTERM)
    out, err = compd_run.communicate(timeout=120)
    assert compd_run.returncode == 0, err
    assert "event=opcua " in err and "event=telemetry_rebirth" in err, err
    assert "level=error" not in err and "Traceback" not in err, err


def blocks_of(text: str, tmp_path: Path):
    """`blocks` (the commissioning walk's reader) of a part of a page."""
    part = tmp_path / "section.md"
    part.write_text(text, encoding="utf-8")
    return blocks(part)
