"""Walks docs/commissioning.md as written, in an empty folder, from wired sensors to enabled output.

Every fenced block of the page is taken in order: a ```yaml block after `<!-- file: NAME -->`
is written to NAME, every ```console block is run line by line (`$ COMMAND`, then the output
the page shows), except those after `<!-- not run by the test: WHY -->`. A block after
`<!-- run by the test while the command before it runs -->` runs while the last command of
the block before it (a `compd run`) is still running. `compd` and `python` are this
checkout's; the one change to the page's text is the metrics port (9105 → a free port).

The output the page shows is checked line by line: each shown line must be printed, with the
same words and numbers, except times (a number followed by `us` or `s`), which depend on the
computer, and `…`, which the page writes for a number that depends on timing. Every command
must exit 0, except one followed by `$ echo $?`: its exit code must be the one shown, and its
shown lines are looked for in what it printed on stdout and stderr (an error's one line).
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.service_helpers import wait_running

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "commissioning.md"
README = ROOT / "README.md"
CONCURRENT = "run by the test while the command before it runs"
NOT_RUN = "not run by the test:"
BLOCK = re.compile(r"(?:<!-- (?P<marker>[^\n]*?) -->\n)?```(?P<lang>[\w-]*)\n(?P<body>.*?)```", re.S)
NUMBER = re.compile(r"-?\d+(?:\.\d+)?")
SHOWN_NUMBER = re.compile(r"…|-?\d+(?:\.\d+)?")  # on the page, `…` stands for a number that depends on timing
EXIT_STATUS = "echo $?"
TIME_UNIT = re.compile(r"\s*(us|s)\b")


@dataclass
class Block:
    marker: str
    lang: str
    body: str
    commands: list[tuple[str, list[str]]] = field(default_factory=list)  # (command, shown output lines)


def blocks(path: Path) -> list[Block]:
    out = []
    for m in BLOCK.finditer(path.read_text(encoding="utf-8")):
        b = Block(m["marker"] or "", m["lang"], m["body"])
        if b.lang == "console":
            for line in b.body.splitlines():
                if line.startswith("$ "):
                    b.commands.append((line[2:], []))
                elif line.strip():
                    assert b.commands, f"output before any command in {path.name}: {line}"
                    b.commands[-1][1].append(line)
        out.append(b)
    return out


def same_line(shown: str, printed: str) -> bool:
    """The same words and numbers (to the digits shown); times are the computer's."""
    if SHOWN_NUMBER.sub("#", shown).split() != NUMBER.sub("#", printed).split():
        return False
    for m, p in zip(SHOWN_NUMBER.finditer(shown), NUMBER.finditer(printed), strict=True):
        if m[0] == "…" or TIME_UNIT.match(shown, m.end()):
            continue
        digits = len(m[0].partition(".")[2])
        if abs(float(m[0]) - float(p[0])) > 1.01 * 10.0**-digits:
            return False
    return True


def check_shown(command: str, shown: list[str], printed: str) -> None:
    lines = printed.splitlines()
    for s in shown:
        assert any(same_line(s, p) for p in lines), f"`{command}`: the page shows\n  {s}\nit printed:\n{printed}"


def doc_folder(tmp_path: Path, tools: dict[str, str] | None = None) -> tuple[Path, dict[str, str]]:
    """An empty folder to walk a page in, and the environment whose `compd` and `python` (and
    `tools`: name → the command it runs) are this checkout's."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    commands = {"compd": f'"{sys.executable}" -m compd', "python": f'"{sys.executable}"', **(tools or {})}
    for name, cmd in commands.items():
        (bin_dir / name).write_text(f'#!/bin/sh\nexec {cmd} "$@"\n')
        (bin_dir / name).chmod(0o755)
    work = tmp_path / "work"
    work.mkdir()
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '/usr/bin:/bin')}",
        "PYTHONPATH": str(ROOT),
    }
    env.pop("RUNTIME_DIRECTORY", None)
    return work, env


@pytest.fixture()
def shell(tmp_path: Path) -> Callable[..., Any]:
    """A shell whose `compd` and `python` are this checkout's, working in an empty folder."""
    work, env = doc_folder(tmp_path)

    def run(command: str, background: bool = False) -> Any:
        argv = ["bash", "-o", "pipefail", "-c", command]
        if background:
            return subprocess.Popen(argv, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        return subprocess.run(argv, cwd=work, env=env, capture_output=True, text=True, timeout=300)

    run.work = work  # type: ignore[attr-defined]
    return run


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_csv(path: Path) -> dict[str, list[float]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return {name: [float(r[i]) for r in rows[1:]] for i, name in enumerate(rows[0])}


def read_csv_nan(path: Path) -> dict[str, list[float]]:
    """read_csv with empty cells as NaN (a daemon's log: a probe column between probes)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return {name: [float(r[i]) if r[i] else math.nan for r in rows[1:]] for i, name in enumerate(rows[0])}


# What the walk checks beyond the output the page shows, by the command's start.
def _warmup(r: subprocess.CompletedProcess, work: Path) -> None:
    assert "level=info event=start" in r.stderr and "observe=True" in r.stderr
    assert "level=warning" not in r.stderr, r.stderr  # no sensor_bad no_data at the start
    log = read_csv(work / "warmup.csv")
    assert {"t_s", "T_xi", "T_amb", "speed_rpm", "err_z_um", "pred_z_um", "applied_z_um", "word"} <= set(log)
    assert set(log["applied_z_um"]) == {0.0}, "observe mode applied a correction"
    assert max(log["pred_z_um"]) > 10.0 and max(log["err_z_um"]) > 10.0 and max(log["word"]) > 0
    assert log["t_s"][-1] >= 14000


def _fit(r: subprocess.CompletedProcess, work: Path) -> None:
    model = yaml.safe_load((work / "model.yaml").read_text())
    assert model["kind"] == "xi_spindle" and model["inputs"] == ["T_xi", "speed_rpm"] and model["outputs"] == ["z"]
    report = json.loads((work / "fit.json").read_text())
    assert report["axes"]["z"]["rmse_um"] == pytest.approx(model["fit"]["rmse_um"]["z"])
    assert "baseline_mlr" in report
    # the page's figure for the fit without the speed (no lift)
    from compd.commissioning import fitting

    quoted = re.search(r"without it, ([\d.]+) µm here", " ".join(GUIDE.read_text(encoding="utf-8").split()))
    oc = fitting.fit_model(
        "xi_spindle", fitting.read_fit_log(work / "warmup.csv"), ["T_xi"], ["err_z_um"], {}, baseline=False
    )
    assert quoted and abs(oc.report["axes"]["z"]["rmse_um"] - float(quoted[1])) <= 0.0051, quoted


def _score(r: subprocess.CompletedProcess, work: Path) -> None:
    rep = json.loads((work / "score.json").read_text())
    z = rep["axes"]["z"]
    assert z["rows"] == len(read_csv(work / "day2.csv")["t_s"])
    assert f"RMS {z['rms_before_um']:.2f} -> {z['rms_after_um']:.2f} um" in r.stdout
    b = rep["baseline_mlr"]["axes"]["z"]
    assert b["model_rmse_um"] < b["mlr_held_out_rmse_um"]  # the physics model beats the baseline
    assert "warning" not in r.stderr


def _recommended(r: subprocess.CompletedProcess, work: Path) -> None:
    """The recommended model file holds its statement, and the unseen day lands inside [0.5x, 2x] of it."""
    from compd.commissioning import fitting

    model = yaml.safe_load((work / "recommended.yaml").read_text())
    stated = model["fit"]["expected_unseen"]["z"]
    assert stated["range_um"][0] <= stated["rms_um"] <= stated["range_um"][1]
    assert (work / "recommended.candidates").is_dir()
    assert "fitting:" not in r.stderr  # no progress bar into a pipe
    day2 = fitting.score_model(fitting.load_model(work / "recommended.yaml"), fitting.read_fit_log(work / "day2.csv"))
    assert 0.5 * stated["rms_um"] <= day2["axes"]["z"]["rms_after_um"] <= 2.0 * stated["rms_um"], (stated, day2)


def _replay(r: subprocess.CompletedProcess, work: Path) -> None:
    rep = json.loads((work / "replay.json").read_text())
    day2 = read_csv(work / "day2.csv")
    assert rep["rows"] == len(day2["t_s"]) and rep["codes_sent"] > 5
    assert rep["axes"]["z"]["reduction_pct"] > 90 and rep["saturated"] == 0
    assert not any(k.startswith(("fault", "bad")) for k in rep["faults"]), rep["faults"]


def _compensate(r: subprocess.CompletedProcess, work: Path) -> None:
    before, after = map(float, re.search(r"without compensation ([\d.]+) um, with ([\d.]+) um", r.stdout).groups())
    assert after < 0.2 * before, r.stdout
    assert "level=warning" not in r.stderr, r.stderr
    assert min(read_csv(work / "compensated.csv")["applied_z_um"]) < -10.0  # corrections reached the card


def _status_observe(r: subprocess.CompletedProcess, work: Path) -> None:
    assert "OBSERVE MODE" in r.stdout and "(on the output: 0x0000)" in r.stdout


def _status(r: subprocess.CompletedProcess, work: Path) -> None:
    if r.stdout.startswith("{"):
        status = json.loads(r.stdout)
        assert status["alive"] is True and status["observe"] is False and status["sink"]["kind"] == "pci1756"
    else:
        assert r.stdout.startswith("compd running") and "OBSERVE" not in r.stdout
        assert re.search(r"^z .* (starting|normal) +hold", r.stdout, re.M)
        assert re.search(r"^T_xi +[\d.]+ good", r.stdout, re.M)


def _metrics(r: subprocess.CompletedProcess, work: Path) -> None:
    assert 'compd_correction_meters{axis="z"}' in r.stdout


def _typo(r: subprocess.CompletedProcess, work: Path) -> None:
    """Step 1's mistakes: one line on stderr naming file, line and key path, nothing on stdout, exit 2."""
    assert r.returncode == 2 and r.stdout == "", (r.returncode, r.stdout)
    assert len(r.stderr.splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert re.match(r"compd: typo\.yaml:\d+: (guard\.max_slew_per_s|sources\[0\]\.(plnat|plant)): ", r.stderr), r.stderr


def _report(r: subprocess.CompletedProcess, work: Path) -> None:
    """The record: what the options gave, and no value left blank or printed as null."""
    text = (work / "report.html").read_text(encoding="utf-8")
    for given in (
        "simulated spindle (hil_sim, paper 003)",
        "A. Tester",
        "20.0 °C (as stated, --ambient-c)",
        "the simulator&#x27;s true error (no instrument)",
        "warmup.csv</code>, 1491 rows, t_s 0.0 s to",
        "day2.csv</code>, 481 rows",
        "Sign-off",
        "Commissioning engineer",
        "Plant owner",
    ):
        assert given in text, given
    assert "T_amb read" in text  # the logs' air column beside the stated ambient
    assert "The thermal test: drift per axis (ISO 230-3)" in text and '<table class="measure">' in text
    before_signoff = text.split('<section class="signoff">')[0]
    assert not re.search(r"<td[^>]*>\s*(null|None|nan|inf|-)?\s*</td>", before_signoff)  # blank or null cells
    assert re.search(r'<td class="name"></td>', text)  # the sign-off's lines, blank to sign by hand
    assert "not used: no radial output" in text  # the model's empty `radial`, explained
    assert "not given" not in text and r.stderr == ""  # every record option was given


def _probing(r: subprocess.CompletedProcess, work: Path) -> None:
    summary = json.loads((work / "probing.json").read_text())
    assert summary["adaptation"]["z"]["accepted"] >= 1, summary.get("adaptation")
    assert summary["adaptation"]["z"]["applied"] is False  # apply: false, observed only
    log = read_csv_nan(work / "probed.csv")
    rows = [(v, log["applied_z_um"][i]) for i, v in enumerate(log["probe_z_um"]) if v == v]
    assert rows, "no probe in the log"
    # the whole thermal error (the 0.5 um deviation less the correction then applied), not the
    # deviation itself: how large depends on when the probe came (the box's load), so compared
    # with the row's applied correction (1 um steps, one slew step apart at most)
    assert all(v > 1.0 and abs(v - (0.5 - applied)) <= 1.5 for v, applied in rows), rows


def _probe(r: subprocess.CompletedProcess, work: Path) -> None:
    assert " accepted at t=" in r.stdout, r.stdout


def _status_probing(r: subprocess.CompletedProcess, work: Path) -> None:
    assert re.search(r"^adapt +offset", r.stdout, re.M), r.stdout
    assert re.search(r"^z .*\(observe: not applied\)", r.stdout, re.M), r.stdout


CHECKS: dict[str, Callable[[subprocess.CompletedProcess, Path], None]] = {
    "compd check-config typo.yaml": _typo,
    "compd report ": _report,
    "compd run probing.yaml": _probing,
    "compd probe ": _probe,
    "compd status --config probing.yaml": _status_probing,
    "compd run machine.yaml": _warmup,
    "compd status --config machine.yaml": _status_observe,
    "compd fit --kind xi_spindle": _fit,
    "compd score model.yaml": _score,
    "compd fit --kind all": _recommended,
    "compd replay compensate.yaml": _replay,
    "compd run compensate.yaml": _compensate,
    "compd status --config compensate.yaml": _status,
    "curl ": _metrics,
}


def extra_check(command: str, r: subprocess.CompletedProcess, work: Path, done: set[str]) -> None:
    for start, check in CHECKS.items():
        if command.startswith(start):
            check(r, work)
            done.add(start)


@pytest.mark.slow
def test_commissioning_guide_runs_as_written(shell) -> None:
    work: Path = shell.work
    assert list(work.iterdir()) == []
    port = free_port()
    page = blocks(GUIDE)
    done: set[str] = set()
    skipped = [b.marker for b in page if b.lang == "console" and b.marker.startswith(NOT_RUN)]
    assert len(skipped) <= 3, skipped  # few, and each says why
    background: tuple[str, list[str], subprocess.Popen] | None = None
    t0 = time.monotonic()
    for i, b in enumerate(page):
        if b.marker.startswith("file: "):
            (work / b.marker[6:]).write_text(b.body.replace("port: 9105", f"port: {port}"))
            continue
        if b.lang != "console" or b.marker.startswith(NOT_RUN):
            continue
        assert b.marker in ("", CONCURRENT), f"unknown marker: {b.marker}"
        nxt = next((n for n in page[i + 1 :] if n.lang == "console"), None)
        r = None
        for k, (command, shown) in enumerate(b.commands):
            command = command.replace("9105", str(port))
            last = k == len(b.commands) - 1
            if command == EXIT_STATUS:  # the exit code of the command before it, as the page shows it
                assert r is not None, f"`{EXIT_STATUS}` first in a block"
                assert shown == [str(r.returncode)], f"`{r.args[-1]}` exited {r.returncode}, the page shows {shown}"
                continue
            if last and nxt is not None and nxt.marker == CONCURRENT:
                assert command.startswith("compd run "), command
                proc = shell(command, background=True)
                cfg = yaml.safe_load((work / command.split()[2]).read_text())
                wait_running(work / cfg["status"]["path"], proc)
                background = (command, shown, proc)
                continue
            r = shell(command)
            if k + 1 < len(b.commands) and b.commands[k + 1][0] == EXIT_STATUS:
                check_shown(command, shown, r.stdout + r.stderr)
            else:
                assert r.returncode == 0, f"`{command}` exited {r.returncode}:\n{r.stdout}\n{r.stderr}"
                check_shown(command, shown, r.stdout)
            extra_check(command, r, work, done)
        if b.marker == CONCURRENT:
            assert background is not None
            command, shown, proc = background
            try:
                out, err = proc.communicate(timeout=300)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.communicate()
            r = subprocess.CompletedProcess(command, proc.returncode, out, err)
            assert r.returncode == 0, f"`{command}` exited {r.returncode}:\n{out}\n{err}"
            check_shown(command, shown, out)
            extra_check(command, r, work, done)
            background = None
    assert done == set(CHECKS), set(CHECKS) - done  # every command the walk checks is on the page
    print(f"the guide's commands ran in {time.monotonic() - t0:.1f} s")


SYNOPSIS = "synopsis:"
SHELL_START = ("compd ", "python -m ", "make ", "sudo ", "$ ")


def test_page_marks_are_known() -> None:
    """Every block of commands in the guide and in the README is run (or checked, for a
    synopsis), or marked with why not."""
    for path in (GUIDE, README):
        for b in blocks(path):
            commands = any(line.startswith(SHELL_START) for line in b.body.splitlines())
            if b.lang == "console" or (commands and b.lang == ""):
                known = b.marker in ("", CONCURRENT) if b.lang == "console" else b.marker.startswith(SYNOPSIS)
                assert known or b.marker.startswith(NOT_RUN), (path.name, b.marker, b.body[:80])
            if b.marker.startswith(NOT_RUN):
                assert len(b.marker) > len(NOT_RUN) + 5, f"{path.name}: say why the test does not run it"


def synopsis_commands(body: str) -> list[tuple[str, str]]:
    """(command with its continuation lines, its comment) of a synopsis block."""
    out: list[tuple[str, str]] = []
    for raw in body.splitlines():
        text, _, comment = raw.partition("#")
        if raw.startswith(("compd ", "python -m ")):
            out.append((text.strip(), comment.strip()))
        elif out and raw.strip():
            out[-1] = (f"{out[-1][0]} {text.strip()}".strip(), f"{out[-1][1]} {comment.strip()}".strip())
    return [(c.replace("\\", " "), m) for c, m in out]


def test_readme_synopses_match_the_commands(shell) -> None:
    """The README's command lists: every command exists with every flag shown, every "e.g."
    example runs and prints what the README says (after `->`)."""
    checked = 0
    for b in blocks(README):
        if not b.marker.startswith(SYNOPSIS):
            continue
        for command, comment in synopsis_commands(b.body):
            words = command.split()
            sub = words[:4] if words[0] == "python" else words[:2]
            r = shell(" ".join([*sub, "--help"]))
            assert r.returncode == 0, (command, r.stderr)
            for flag in re.findall(r"(?<![\w-])--[a-z][a-z-]*", command):
                assert flag in r.stdout, f"README: `{' '.join(sub)}` has no {flag}"
            for example in re.findall(r"e\.g\. ((?:compd|python -m) [^;]*?)(?=$|;|\s+e\.g\.)", comment):
                cmd, _, expect = example.partition("->")
                r = shell(cmd.strip())
                assert r.returncode == 0, (cmd, r.stderr)
                if expect.strip():
                    assert " ".join(r.stdout.split()).startswith(" ".join(expect.split())), (example, r.stdout)
                checked += 1
            checked += 1
    assert checked >= 14, checked  # the Commands list and the simulator's log command
