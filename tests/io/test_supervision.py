"""`compd run` against `hil_sim serve` (a PT100 module and a FANUC PMC over Modbus TCP): the
sink's link process and the poll process are killed (-9) or stopped (SIGSTOP); the daemon reports
the loss at once (event, pid, why), says the link is down while it is, restarts the process, and
the PMC's applied shift — read over Modbus from the test, not from compd — follows the status
again; SIGTERM then leaves 0 at the PMC and exit 0. Every wait is for a condition."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from pymodbus.client import ModbusTcpClient

from tests.conftest import ROOT

WAIT_S = 90.0
APPLIED_1 = 404  # the PMC's applied shift of axis 1 (µm, signed)


def _wait(pred: Any, what: str, timeout_s: float = WAIT_S) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


@contextlib.contextmanager
def _bench(tmp_path: Path) -> Iterator[dict[str, int]]:
    """`python -m hil_sim serve`: a PT100 module (T_xi 40 °C) and a FANUC PMC; their ports."""
    cfg = {
        "devices": [
            {"kind": "pt100_modbus", "name": "tx", "port": 0, "channels": [{"name": "T_xi", "value_c": 40.0}]},
            {"kind": "fanuc_pmc", "name": "pmc", "port": 0},
        ]
    }
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil_sim", "serve", "--config", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    try:
        lines = []
        while True:
            line = proc.stdout.readline()
            assert line, "hil_sim serve ended"
            lines.append(line)
            if "ready" in line:
                break
        yield {m[0]: int(m[1]) for m in re.findall(r"^(\w+): \w+ on tcp:127\.0\.0\.1:(\d+)", "".join(lines), re.M)}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _config(ports: dict[str, int], observe: bool = False) -> dict:
    return {
        "loop": {"period_s": 0.005},
        "sources": [
            {
                "kind": "modbus",
                "name": "pt",
                "transport": "tcp",
                "host": "127.0.0.1",
                "port": ports["tx"],
                "poll_period_s": 0.02,
                "timeout_s": 0.5,
                "stale_after_s": 1.0,
                "channels": [{"name": "T_xi", "address": 0}],
            }
        ],
        "model": {
            "kind": "xi_spindle",
            "inputs": ["T_xi"],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 30.0},
        },
        "guard": {"max_slew_um_per_s": 20.0, "stale_after_s": 1.0, "signals": {"T_xi": {"min": 0.0, "max": 80.0}}},
        "sink": {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": ports["pmc"]},
        "status": {"path": "status.json", "period_s": 0.1},
        "observe": observe,
    }


def _status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _applied_um(port: int) -> int | None:
    c = ModbusTcpClient("127.0.0.1", port=port, timeout=1, retries=0)
    try:
        rr = c.read_holding_registers(APPLIED_1, count=1, device_id=1)
        if rr.isError():
            return None
        v = rr.registers[0]
        return v - 65536 if v >= 32768 else v
    finally:
        c.close()


def _events(err: Path, event: str) -> list[dict[str, str]]:
    """The daemon's `key=value` event lines of `event`, as dicts of strings."""
    out = []
    for line in err.read_text().splitlines():
        if f"event={event} " not in line:
            continue
        with contextlib.suppress(ValueError):
            out.append(dict(part.split("=", 1) for part in shlex.split(line) if "=" in part))
    return out


def _settled(status: Path, pmc_port: int) -> Any:
    """The status says link up and a steady, real correction (beyond 10 µm, not the 0 it starts from: on a
    loaded machine the first looks can find target and correction both still 0), and the PMC applies it (to
    its 1 µm)."""

    def check() -> dict | None:
        st = _status(status)
        if not st or st["state"] != "running" or st["sink"]["link"] != "up":
            return None
        a = st["axes"]["z"]
        if abs(a["correction_um"] - a["target_um"]) > 0.01 or abs(a["correction_um"]) <= 10.0:
            return None
        applied = _applied_um(pmc_port)
        return st if applied is not None and abs(applied - a["correction_um"]) <= 1.0 else None

    return check


@contextlib.contextmanager
def _compd(
    tmp_path: Path, ports: dict[str, int], observe: bool = False
) -> Iterator[tuple[subprocess.Popen, Path, Path]]:
    """`compd run` against the bench: (the process, its stderr file, its status file); SIGTERM at
    the end, which it must answer with exit 0, leaving 0 applied at the PMC (read over Modbus)."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(_config(ports, observe)))
    err = tmp_path / "stderr.txt"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    with open(err, "w") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg), "--log-level", "info"],
            cwd=tmp_path,
            stdout=subprocess.DEVNULL,
            stderr=fh,
            env=env,
        )
    try:
        yield proc, err, tmp_path / "status.json"
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(60)
    assert code == 0, err.read_text()[-3000:]
    assert _applied_um(ports["pmc"]) == 0  # the safe state reached the PMC


@pytest.mark.parametrize(("child", "how"), [("link", "kill"), ("link", "stop"), ("poll", "kill"), ("poll", "stop")])
def test_a_lost_child_is_reported_restarted_and_the_pmc_follows_again(tmp_path: Path, child: str, how: str) -> None:
    with _bench(tmp_path) as ports, _compd(tmp_path, ports) as (proc, err, status):
        st = _wait(_settled(status, ports["pmc"]), "the PMC applying the status's correction")
        assert abs(st["axes"]["z"]["correction_um"]) > 10.0  # a real correction, not 0
        pid = (
            st["sink"]["link_stats"]["pid"]
            if child == "link"
            else next(s["io_pid"] for s in st["sources"] if s["name"] == "pt")
        )
        assert pid not in (None, proc.pid)
        os.kill(pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
        lost = _wait(lambda: _events(err, "io_process_lost"), "the loss reported")[0]
        assert lost["pid"] == str(pid)
        assert lost["reason"] == "killed by SIGKILL" if how == "kill" else lost["reason"].startswith("stopped beating")
        restarted = _wait(lambda: _events(err, "io_process_restarted"), "the restart")[0]
        assert restarted["old_pid"] == str(pid) and restarted["pid"] != str(pid)
        st = _wait(_settled(status, ports["pmc"]), "the PMC following the status again")
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
        # the status says it too: the process, its new pid, one restart and why
        name = restarted["worker"]
        proc_st = _wait(
            lambda: next(
                (p for p in (_status(status) or {}).get("processes") or [] if p["name"] == name and p["restarts"] == 1),
                None,
            ),
            "the restart in the status",
        )
        assert proc_st["up"] and proc_st["pid"] == int(restarted["pid"]) and proc_st["lost"] == lost["reason"]


def test_sigterm_with_a_stopped_link_delivers_the_safe_state_through_a_fresh_one(tmp_path: Path) -> None:
    with _bench(tmp_path) as ports, _compd(tmp_path, ports) as (_, err, status):
        st = _wait(_settled(status, ports["pmc"]), "the PMC applying the status's correction")
        applied = _applied_um(ports["pmc"])
        assert applied is not None and abs(applied) > 10
        os.kill(st["sink"]["link_stats"]["pid"], signal.SIGSTOP)  # stopped: no beat, no write; then SIGTERM


def test_observe_mode_says_disabled_where_the_pmc_holds_nothing(tmp_path: Path) -> None:
    with _bench(tmp_path) as ports, _compd(tmp_path, ports, observe=True) as (_, _, status):
        st = _wait(
            lambda: (
                (s := _status(status))
                and s["state"] == "running"
                and s["sink"]["link"] == "up"
                and abs(s["axes"]["z"]["correction_um"]) > 10.0
                and s
            ),
            "a computed correction",
        )
        a = st["axes"]["z"]
        assert a["enable"] is False and a["guard_enable"] is True and st["word_at_machine"] == "0x0000"
        assert _applied_um(ports["pmc"]) == 0
