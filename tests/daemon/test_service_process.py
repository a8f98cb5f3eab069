"""The daemon on the wall clock runs no Python beside its cycle: the device I/O and the service (status file,
metrics, event lines, data log, model state, probe socket) run in processes of their own, fed from the cycle
between cycles; a reload hands the files and sockets from one service to the next without losing a row.

`compd run` runs as a child process against a PT100 Modbus TCP module served from the test; every wait is
for a condition, never for a time."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.log import read_log
from compd.service import control
from compd.service.status import render
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from tests.conftest import ROOT

SENSOR = "T_xi"
WAIT_S = 60.0


def _config(port: int, slew_um_per_s: float = 20.0) -> dict:
    return {
        "loop": {"period_s": 0.005},
        "sources": [
            {
                "kind": "modbus",
                "name": "pt",
                "transport": "tcp",
                "host": "127.0.0.1",
                "port": port,
                "poll_period_s": 0.02,
                "timeout_s": 0.5,
                "stale_after_s": 1.0,
                "channels": [{"name": SENSOR, "address": 0}],
            }
        ],
        "model": {
            "kind": "xi_spindle",
            "inputs": [SENSOR],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
        },
        "guard": {
            "max_slew_um_per_s": slew_um_per_s,
            "stale_after_s": 1.0,
            "signals": {SENSOR: {"min": 0.0, "max": 80.0}},
        },
        "sink": {"kind": "pci1756"},
        "status": {"path": "status.json", "period_s": 0.1},
        "log": {"path": "run.csv", "period_s": 0.05, "flush_s": 0.1},
        "state": {"path": "state.json"},
        "metrics": {"enabled": True, "port": 0},
        "adapt": {},
    }


def _wait(pred, what: str, timeout_s: float = WAIT_S):  # noqa: ANN001, ANN202
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _running(path: Path, after_cycles: int = 0):  # noqa: ANN202
    def check() -> dict | None:
        st = _status(path)
        return st if st and st["state"] == "running" and st["loop"]["cycles"] > after_cycles else None

    return check


def _start(cfg: Path, err: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    with open(err, "a") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            cwd=cfg.parent,
            stdout=subprocess.DEVNULL,
            stderr=fh,
            env=env,
        )


def _rows(path: Path) -> int:
    """Rows of the data log so far (0 while it is missing or its last line is half written)."""
    try:
        return len(read_log(path, allow_nan=True))
    except Exception:
        return 0


def _first_t(path: Path) -> list[float] | None:
    """[the data log's first row's time], or None while it has no complete row."""
    try:
        t = read_log(path, allow_nan=True).t_s
    except Exception:
        return None
    return [float(t[0])] if len(t) else None


def _comm(pid: int) -> str:
    return Path(f"/proc/{pid}/comm").read_text().strip()


@contextlib.contextmanager
def _daemon(tmp_path: Path, tx: Pt100Transmitter) -> Iterator[tuple[subprocess.Popen, Path, Path, int]]:
    """`compd run` against a PT100 module served here: (the process, its config, its stderr file,
    the module's port); stopped with SIGTERM at the end, which it must answer with exit 0."""
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(_config(server.port)))
        err = tmp_path / "stderr.txt"
        proc = _start(cfg, err)
        try:
            yield proc, cfg, err, server.port
        finally:
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0


def test_the_cycle_s_process_runs_no_other_python_and_the_service_does_the_rest(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    with _daemon(tmp_path, tx) as (proc, _, err, _):
        st = _wait(_running(tmp_path / "status.json", 50), "a running status")
        daemon, service = st["pid"], st["service_pid"]
        assert daemon == proc.pid and service != daemon
        assert st["threads"] == ["MainThread"]  # the cycle's thread is its process's only Python
        assert _comm(service) == "compd:service" and os.getppid() != service
        assert _comm(st["sources"][0]["io_pid"]) == "compd:poll-pt"
        shown = render(st, True, "running")  # what `compd status` prints
        assert f"processes: cycle {daemon} (1 thread of Python), service {service}" in shown
        assert f"device I/O: pt {st['sources'][0]['io_pid']}" in shown
        # the metrics endpoint the daemon bound is served by the service
        with urllib.request.urlopen(st["metrics_url"], timeout=10) as r:
            assert b"compd_cycles_total" in r.read()
        # a probe goes through the service to the cycle and its verdict comes back
        answer = control.send_probe(tmp_path / "status.sock", {"op": "probe", "axis": "z", "error_um": 1.0})
        assert answer["ok"] and answer["outcome"] in ("accepted", "rejected"), answer
        assert answer["pid"] == daemon and answer["t_s"] > 0  # stamped by the cycle
        # a sensor fault: the guard's events become the service's log lines
        tx.set_fault(SENSOR, "burnout")
        _wait(lambda: "event=sensor_bad" in err.read_text(), "the sensor_bad line")
        tx.set_fault(SENSOR, "none")
        _wait(lambda: "event=sensor_good" in err.read_text(), "the sensor_good line")
        st = _wait(_running(tmp_path / "status.json", st["loop"]["cycles"] + 20), "a newer status")
        assert st["publisher"]["messages_dropped"] == 0
    text = err.read_text()
    for line in ("sensor=T_xi reason=burnout", "event=probe_", "event=stop"):
        assert line in text, f"no {line!r} in the event log:\n{text}"
    final = _status(tmp_path / "status.json")
    assert final is not None and final["state"] == "stopped" and final["threads"] == ["MainThread"]
    for pid in (service, st["sources"][0]["io_pid"]):
        assert not Path(f"/proc/{pid}").exists()  # the daemon stopped its children
    log = read_log(tmp_path / "run.csv", allow_nan=True)
    assert len(log) > 10 and np.all(np.diff(log.t_s) > 0)
    saved = json.loads((tmp_path / "state.json").read_text())
    assert saved["kind"] == "xi_spindle" and "adapt" in saved


def test_a_reload_hands_the_files_and_sockets_to_the_new_service_without_losing_a_row(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    with _daemon(tmp_path, tx) as (proc, cfg, err, port):
        st = _wait(_running(tmp_path / "status.json", 20), "a running status")
        old_service, url = st["service_pid"], st["metrics_url"]
        cfg.write_text(yaml.safe_dump(_config(port, slew_um_per_s=10.0)))
        proc.send_signal(signal.SIGHUP)
        _wait(lambda: "event=reloaded" in err.read_text(), "the reload")
        st = _wait(
            lambda: (
                (s := _status(tmp_path / "status.json"))
                and s["service_pid"] != old_service
                and s["state"] == "running"
                and s
            ),
            "the new service's status",
        )
        assert st["pid"] == proc.pid and st["metrics_url"] == url and st["threads"] == ["MainThread"]
        assert not Path(f"/proc/{old_service}").exists()
        with urllib.request.urlopen(url, timeout=10) as r:  # the same port, served by the new service
            assert b"compd_cycles_total" in r.read()
        n = len(read_log(tmp_path / "run.csv", allow_nan=True))
        _wait(lambda: len(read_log(tmp_path / "run.csv", allow_nan=True)) > n + 10, "rows after the reload")
    log = read_log(tmp_path / "run.csv", allow_nan=True)
    gaps = np.diff(log.t_s)
    assert np.all(gaps > 0)  # in order, none twice
    # every 0.05 s a row (and one at each change of the word): no gap but the reload's own pause
    assert np.count_nonzero(gaps > 0.5) <= 1, gaps.max()
    assert "level=error" not in err.read_text()


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP])
def test_a_service_that_dies_or_stalls_is_reported_once_restarted_and_the_cycle_goes_on(
    tmp_path: Path,
    how: signal.Signals,
) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    status = tmp_path / "status.json"
    with _daemon(tmp_path, tx) as (proc, _, err, _):
        st = _wait(_running(status, 20), "a running status")
        first_t = _wait(lambda: _first_t(tmp_path / "run.csv"), "the first data-log rows")[0]
        old = st["service_pid"]
        os.kill(old, how)  # as the OOM killer would; or a service that hangs
        _wait(lambda: "event=service_lost" in err.read_text(), "the service_lost line")
        _wait(lambda: "event=service_restarted" in err.read_text(), "the service_restarted line")
        assert proc.poll() is None  # compensation goes on; SIGTERM still ends it with exit 0
        # the new service writes the status file again, and the data log goes on
        st = _wait(
            lambda: (s := _status(status)) and s["service_pid"] not in (None, old) and s,
            "a status from the new service",
        )
        with pytest.raises(ProcessLookupError):
            os.kill(old, 0)
        rows = _rows(tmp_path / "run.csv")
        _wait(lambda: _rows(tmp_path / "run.csv") > rows, "data-log rows from the new service")
    # the rows the cycle handed over while no service ran were written by the new one: no gap
    t = read_log(tmp_path / "run.csv", allow_nan=True).t_s
    assert len(t) > 10 and float(np.max(np.diff(t))) < 1.0
    assert t[0] == first_t  # the rows from before the loss are still there (the log is appended to)
    text = err.read_text()
    assert text.count("event=service_lost") == 1 and text.count("event=service_restarted") == 1
    assert "event=stop" in text
