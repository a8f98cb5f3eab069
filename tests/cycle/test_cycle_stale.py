"""A cycle that stopped writing its record is `stale` on every channel, and `compd status` exits 1; a reload is not.

The service writes on whatever the cycle does: a cycle stopped (SIGSTOP) or hung must never show
as running. In process (a simulated clock, the service on a thread): a cycle hung in an observer,
and a reload's pause. As a daemon (`compd run` on the wall clock, the service in its own
process): SIGSTOP of the cycle's process seen in the status file, `compd status`, the metrics,
Sparkplug through a real mosquitto and the watchdog; SIGCONT brings it back; a SIGHUP reload is
never reported dead. Every wait is for a condition, never for a time."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from compd.config import load_config
from compd.cycle.statusblock import STALE_MIN_S
from compd.daemon.app import App
from compd.service.notify import socket_address
from compd.service.status import liveness, render
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from tests.conftest import ROOT
from tests.daemon.test_service_process import SENSOR, _config
from tests.plant.broker import Listener, Mosquitto, metric
from tests.service_helpers import sim_config

WAIT_S = 60.0


def _wait(pred: Callable[[], Any], what: str, timeout_s: float = WAIT_S) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def _status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _state(path: Path, state: str, **more: Callable[[dict], bool]) -> Callable[[], dict | None]:
    def check() -> dict | None:
        st = _status(path)
        return st if st and st["state"] == state and all(f(st) for f in more.values()) else None

    return check


def _scrape(url: str) -> dict[str, float]:
    """The metrics endpoint's samples, `name{labels}` → value."""
    with urllib.request.urlopen(url, timeout=10) as r:
        text = r.read().decode()
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.rpartition(" ")
            out[name] = float(value)
    return out


def _compd_status(path: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "compd", "status", "--status", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )


# ------------------------------------------------------------------ in process


class _Hang:
    """A loop observer that holds the cycle's thread at its `at`-th call until `release`
    (a hung cycle: the service's thread goes on), running `while_held` meanwhile."""

    def __init__(self, at: int, while_held: Callable[[], bool]) -> None:
        self.at, self.while_held = at, while_held
        self.calls = 0
        self.released = threading.Event()
        self.failure: BaseException | None = None

    def __call__(self, loop: Any, now: float) -> None:
        self.calls += 1
        if self.calls != self.at:
            return
        try:
            deadline = time.monotonic() + WAIT_S
            while not self.while_held():
                assert time.monotonic() < deadline, "timed out with the cycle held"
                time.sleep(0.01)
        except BaseException as e:  # said by the test after the run, not lost in the loop
            self.failure = e
        self.released.set()


def test_a_hung_cycle_is_stale_in_the_status_and_metrics_and_runs_on_after(tmp_path: Path) -> None:
    """Period 0.05 s: stale after max(5 periods, 1 s) = 1 s without a record."""
    status = tmp_path / "status.json"
    cfg = load_config(
        sim_config(
            tmp_path,
            "status: {path: status.json, period_s: 0.05}\nmetrics: {enabled: true, port: 0}",
            period_s=0.05,
            speedup=20,
            duration_s=3600,
        )
    )
    app = App(cfg, duration_s=None)
    seen: dict[str, Any] = {}

    def stale_seen() -> bool:
        st = _status(status)
        if not st or st["state"] != "stale":
            return False
        seen["snap"] = st
        seen["metrics"] = _scrape(st["metrics_url"])
        return True

    hang = _Hang(at=40, while_held=stale_seen)

    def stop_when_running_again(loop: Any, now: float) -> None:
        if (
            hang.released.is_set()
            and (st := _status(status))
            and st["state"] == "running"
            and st["loop"]["cycles"] > seen["snap"]["loop"]["cycles"]
        ):
            seen["after"] = st
            seen["metrics_after"] = _scrape(st["metrics_url"])
            loop.stop()

    app.loop.observers += [hang, stop_when_running_again]
    guard = threading.Timer(3 * WAIT_S, app.loop.stop)  # a test that fails must not run forever
    guard.start()
    try:
        app.run()
    finally:
        guard.cancel()
        guard.join()
    assert hang.failure is None, hang.failure
    snap = seen["snap"]
    assert snap["stale_after_s"] == STALE_MIN_S and snap["record_age_s"] > STALE_MIN_S
    z = snap["axes"]["z"]
    assert z["state"] == "stale" and z["last_state"] in ("starting", "normal") and z["enable"] is None
    alive, why = liveness(snap)
    assert not alive and why.startswith("stale: the cycle has not run for")
    assert "CYCLE STALE" in render(snap, alive, why)
    m = seen["metrics"]
    assert m['compd_state{state="stale"}'] == 1.0 and m['compd_state{state="running"}'] == 0.0
    assert m["compd_cycle_record_age_seconds"] > STALE_MIN_S
    assert m['compd_axis_state{axis="z",state="stale"}'] == 1.0
    after = seen["after"]
    assert after["record_age_s"] < STALE_MIN_S and after["axes"]["z"]["state"] != "stale"
    assert liveness(after) == (True, "running")
    assert seen["metrics_after"]['compd_state{state="running"}'] == 1.0
    assert json.loads(status.read_text())["state"] == "stopped"


def test_a_reload_s_pause_is_reloading_never_stale(tmp_path: Path) -> None:
    """The loop paused for a reload, longer than a running cycle may pause: `reloading`, alive."""
    status = tmp_path / "status.json"
    cfg = load_config(
        sim_config(tmp_path, "status: {path: status.json, period_s: 0.05}", period_s=0.05, speedup=20, duration_s=3600)
    )
    app = App(cfg, duration_s=None)
    states: list[str] = []

    def paused_long() -> bool:
        st = _status(status)
        if st:
            states.append(st["state"])
        return bool(st and st["state"] == "reloading" and st["record_age_s"] > 1.5 * STALE_MIN_S)

    hang = _Hang(at=40, while_held=paused_long)

    def reloading(loop: Any, now: float) -> None:
        if hang.calls == 39:  # as `compd run` does when the loop has returned for a SIGHUP
            app.service.reloading()
        if hang.released.is_set():
            app.service.resume()  # ... and when the reload was refused: the old pipeline runs on
            if (st := _status(status)) and st["state"] == "running" and st["record_age_s"] < STALE_MIN_S:
                loop.stop()

    app.loop.observers += [reloading, hang]
    guard = threading.Timer(3 * WAIT_S, app.loop.stop)
    guard.start()
    try:
        app.run()
    finally:
        guard.cancel()
        guard.join()
    assert hang.failure is None, hang.failure
    assert "reloading" in states and "stale" not in states, states
    snap = json.loads(status.read_text())
    assert snap["state"] == "stopped"


# ------------------------------------------------------------------ a daemon


@contextlib.contextmanager
def _notify_socket() -> Any:
    name = f"@compd-test-stale-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(socket_address(name))
    sock.setblocking(False)
    try:
        yield name, sock
    finally:
        sock.close()


def _received(sock: socket.socket) -> list[str]:
    """The notify messages waiting on the socket."""
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def _state_metric(listener: Listener) -> list[str]:
    """The device's State in every DDATA that carries it, in order."""
    out = []
    for m in listener.of("DDATA"):
        with contextlib.suppress(KeyError):
            out.append(metric(m.payload, "State").value)
    return out


def _event_kinds(listener: Listener) -> list[str]:
    out = []
    for m in listener.of("DDATA"):
        with contextlib.suppress(KeyError):
            out.append(metric(m.payload, "Event/kind").value)
    return out


def test_a_stopped_cycle_process_is_stale_on_every_channel_and_a_reload_is_never_dead(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [24.0])
    status = tmp_path / "status.json"
    err = tmp_path / "stderr.txt"
    with (
        Mosquitto(tmp_path / "broker") as broker,
        ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server,
        _notify_socket() as (notify_name, notify),
    ):
        c = _config(server.port)
        c["telemetry"] = {
            "port": broker.port,
            "group_id": "hall2",
            "edge_node_id": "cell7",
            "device_id": "lathe",
            "period_s": 0.2,
        }
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(c))
        listener = Listener(broker.port)
        env = {
            **os.environ,
            "PYTHONPATH": str(ROOT),
            "PYTHONUNBUFFERED": "1",
            "NOTIFY_SOCKET": notify_name,
            "WATCHDOG_USEC": "400000",
        }  # a ping every 0.2 s
        with open(err, "a") as fh:
            proc = subprocess.Popen(
                [sys.executable, "-m", "compd", "run", str(cfg)],
                cwd=tmp_path,
                stdout=subprocess.DEVNULL,
                stderr=fh,
                env=env,
            )
        try:
            st = _wait(_state(status, "running", cycles=lambda s: s["loop"]["cycles"] > 20), "a running status")
            assert st["service_pid"] != proc.pid and st["stale_after_s"] == STALE_MIN_S
            pings: list[str] = []
            _wait(lambda: pings.extend(_received(notify)) or "WATCHDOG=1" in pings, "the watchdog's pings")
            listener.wait_for(lambda: "running" in _state_metric(listener), timeout_s=WAIT_S)

            os.kill(proc.pid, signal.SIGSTOP)  # the cycle's process: its service goes on writing
            st = _wait(_state(status, "stale"), "a stale status")
            assert st["record_age_s"] > st["stale_after_s"] == STALE_MIN_S
            assert st["axes"]["z"]["state"] == "stale" and st["axes"]["z"]["enable"] is None
            shown = _compd_status(status)
            assert shown.returncode == 1, shown
            assert shown.stdout.startswith("compd stale: the cycle has not run for") and "CYCLE STALE" in shown.stdout
            assert "stale: the cycle has not run" in shown.stderr
            m = _scrape(st["metrics_url"])
            assert m['compd_state{state="stale"}'] == 1.0 and m["compd_cycle_record_age_seconds"] > STALE_MIN_S
            listener.wait_for(lambda: _state_metric(listener)[-1:] == ["stale"], timeout_s=WAIT_S)
            assert "cycle_stale" in _event_kinds(listener)
            # the watchdog: not one ping from a stopped cycle, while the service writes on
            _received(notify)  # those sent before the stop
            later = st["record_age_s"] + 1.0
            _wait(_state(status, "stale", aged=lambda s: s["record_age_s"] > later), "a later stale status")
            assert not any("WATCHDOG=1" in msg for msg in _received(notify))

            os.kill(proc.pid, signal.SIGCONT)
            st = _wait(_state(status, "running", fresh=lambda s: s["record_age_s"] < STALE_MIN_S), "running again")
            assert _compd_status(status).returncode == 0
            assert _scrape(st["metrics_url"])['compd_state{state="running"}'] == 1.0
            listener.wait_for(lambda: _state_metric(listener)[-1:] == ["running"], timeout_s=WAIT_S)
            pings = []
            _wait(lambda: pings.extend(_received(notify)) or "WATCHDOG=1" in pings, "the watchdog's pings again")

            # a reload: every status written meanwhile is alive, as `compd status` judges it
            old_service = st["service_pid"]
            c["guard"]["max_slew_um_per_s"] = 10.0
            cfg.write_text(yaml.safe_dump(c))
            proc.send_signal(signal.SIGHUP)
            judged: list[tuple[str, bool, str]] = []

            def reloaded() -> bool:
                s = _status(status)
                if s is None:
                    return False
                judged.append((s["state"], *liveness(s)))
                return s["service_pid"] != old_service and s["state"] == "running" and s["loop"]["cycles"] > 5

            _wait(reloaded, "the reloaded pipeline's status")
            assert all(alive for _, alive, _ in judged), [j for j in judged if not j[1]]
            assert _compd_status(status).returncode == 0
            assert "event=reloaded" in err.read_text()
        finally:
            proc.send_signal(signal.SIGCONT)  # a test that failed while it was stopped
            proc.send_signal(signal.SIGTERM)
            try:
                assert proc.wait(60) == 0, err.read_text()
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                listener.stop()
    text = err.read_text()
    assert text.count("event=cycle_stale") == 1 and text.count("event=cycle_resumed") == 1, text
