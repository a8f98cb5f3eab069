"""An I/O worker in a process of its own: it publishes to the cycle through shared memory (its
samples, its counts and its status), answers requests over its pipe, writes its own log lines to
the stderr it inherited, raises its open error in the parent, ignores SIGTERM (the parent still
sends the safe state through it), keeps off the cycle's CPUs and ends with its parent. Every wait
is for a condition."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from typing import Any

import numpy as np
import pytest

from compd.core.errors import BadInput
from compd.core.frame import Frame, Quality
from compd.io.mailbox import Snapshot, WriteQueue
from compd.io.worker import DeviceWork, IoWorker, LinkDown

WAIT_S = 20.0


class Counter(DeviceWork):
    """Publishes its process id and a round count; sends the queued writes into a second
    snapshot; fails its first connect (a logged device error)."""

    def __init__(self, snap: Snapshot, writes: WriteQueue, echo: Snapshot, fail_open: bool = False) -> None:
        super().__init__()
        self.snap, self.writes, self.echo = snap, writes, echo
        self.fail_open = fail_open
        self.n = 0
        self.connects = 0

    def open(self) -> None:
        if self.fail_open:
            raise BadInput("no serial device '/dev/ttyUSB9'", path=("sources", 0, "serial_port"))

    def connect(self) -> None:
        self.connects += 1
        if self.connects == 1:
            raise LinkDown("connect to 127.0.0.1:1: [Errno 111] Connection refused")

    def round(self, request: Any) -> Any:
        self.n += 1
        q = np.full(2, Quality.GOOD, dtype=np.uint8)
        self.snap.publish(np.array([float(os.getpid()), float(self.n)]), q, self.now())
        while (w := self.writes.take()) is not None:
            self.echo.publish(np.array([float(w[0]), float(w[1][0])]), q, 0.0)
            self.writes.done(w, sent=True)
        return None if request is None else ("pid", os.getpid(), request)

    def counters(self) -> dict[str, Any]:
        return {"my_rounds": self.n, "pid": os.getpid()}


def _worker(fail_open: bool = False) -> tuple[IoWorker, Snapshot, WriteQueue, Snapshot]:
    snap, echo = Snapshot(2), Snapshot(2)
    writes = WriteQueue()
    w = IoWorker(
        Counter(snap, writes, echo, fail_open),
        name="counter",
        period_s=0.01,
        reconnect_min_s=0.01,
        reconnect_max_s=0.02,
    )
    writes.wake = w.wake
    return w, snap, writes, echo


def test_a_worker_in_its_own_process_publishes_answers_and_logs_its_own_lines(
    capfd: pytest.CaptureFixture[str],
) -> None:
    from compd.service.logsetup import setup_logging

    setup_logging("info", journal=False)
    w, snap, writes, echo = _worker()
    w.start(process=True, clock=time.monotonic)
    try:
        assert w.in_process and w.running
        assert w.wait_for(lambda: snap.count >= 3 and w.state == "up", WAIT_S)
        frame = Frame(["pid", "n"])
        snap.copy_to(frame, frame.indices(["pid", "n"], what="signal"))
        child_pid = int(frame.values[0])
        assert child_pid != os.getpid() and frame.values[1] >= 1  # polled in another process
        assert w.rounds >= 3 and w.connects == 1 and w.errors == 1  # the accounts are shared
        # a write from the cycle reaches the child, which acknowledges it
        writes.submit(40, [7])
        assert writes.wait_empty(WAIT_S)
        assert w.wait_for(lambda: echo.count >= 1, WAIT_S)
        assert echo.sample()[0].tolist() == [40.0, 7.0]
        # a request goes over the pipe, answered by the child; the status is what the
        # child's thread published in shared memory (read without asking the child)
        assert w.request("x", WAIT_S) == ("pid", child_pid, "x")
        assert w.wait_for(lambda: w.get_status().get("my_rounds", 0) >= 3, WAIT_S)
        status = w.get_status()
        assert status["pid"] == child_pid and status["state"] == "up"
        # the child wrote its device error to stderr itself, once, in the daemon's format
        err = capfd.readouterr().err
        lines = [ln for ln in err.splitlines() if "event=device_error" in ln]
        assert len(lines) == 1 and "Connection refused" in lines[0] and "level=warning" in lines[0], err
    finally:
        assert w.stop(WAIT_S)
    assert not w.running and w.state == "closed"
    with pytest.raises(ProcessLookupError):
        os.kill(child_pid, 0)  # gone, and reaped
    after = w.get_status()  # the counts its process had at the end
    assert after["pid"] == child_pid and after["my_rounds"] >= 3 and after["state"] == "closed"


def test_the_child_does_not_hold_the_parents_listening_socket() -> None:
    """A port the parent listened on when it forked (a metrics server) can be bound again
    once the parent closes it: the child closed its inherited copy."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    w, snap, *_ = _worker()
    w.start(process=True, clock=time.monotonic)
    try:
        assert w.wait_for(lambda: snap.count >= 1, WAIT_S)
        listener.close()
        again = socket.socket()
        again.bind(("127.0.0.1", port))  # EADDRINUSE if the child still held it
        again.close()
    finally:
        assert w.stop(WAIT_S)


def test_an_open_error_in_the_child_is_raised_in_the_parent_whole() -> None:
    w, *_ = _worker(fail_open=True)
    with pytest.raises(BadInput) as e:
        w.start(process=True, clock=time.monotonic)
    assert e.value.keys == ("sources", 0, "serial_port") and "ttyUSB9" in str(e.value)
    assert not w.running and not w.in_process


def test_the_child_ignores_sigterm_and_keeps_off_the_cycles_cpus() -> None:
    """systemd stops the whole group with SIGTERM: the device's process stays up until the
    parent has sent the safe state through it and stops it."""
    w, snap, *_ = _worker()
    cpus = sorted(os.sched_getaffinity(0))
    avoid = frozenset(cpus[:1]) if len(cpus) > 1 else frozenset()
    w.start(process=True, clock=time.monotonic, avoid_cpus=avoid)
    try:
        pid = w.get_status()["pid"]
        if avoid:
            assert not (os.sched_getaffinity(pid) & avoid)
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        os.kill(pid, signal.SIGTERM)
        n = snap.count
        assert w.wait_for(lambda: snap.count >= n + 3, WAIT_S)
        assert w.running
    finally:
        assert w.stop(WAIT_S)


def test_the_child_ends_when_its_parent_dies() -> None:
    script = textwrap.dedent(
        """
        import os, sys, time
        sys.path.insert(0, sys.argv[1])
        from tests.io.test_io_process import _worker
        w, snap, *_ = _worker()
        w.start(process=True, clock=time.monotonic)
        w.wait_for(lambda: snap.count >= 1, 20.0)
        print(w.get_status()["pid"], flush=True)
        os._exit(0)  # no stop: as if killed
        """
    )
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = subprocess.run([sys.executable, "-c", script, root], capture_output=True, text=True, timeout=60)
    pid = int(out.stdout.split()[0])
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        try:
            with open(f"/proc/{pid}/stat") as fh:  # re-parented and exited, not yet reaped: a zombie
                if fh.read().split(") ")[1].startswith("Z"):
                    break
        except FileNotFoundError:
            break
        time.sleep(0.05)
    else:
        os.kill(pid, signal.SIGKILL)
        pytest.fail("the I/O process outlived its parent")


@pytest.mark.parametrize("io", ["process", "thread"])
def test_a_daemon_on_the_wall_clock_polls_its_devices_from_processes_of_their_own(tmp_path, io: str) -> None:  # noqa: ANN001
    """`loop.io: process` (the default): the PT100 module's poller runs in a child, and the
    loop compensates from its samples; `loop.io: thread`: in the daemon's process."""
    import yaml

    from compd.config import load_config
    from compd.daemon.app import App
    from hil_sim.devices.modbus_server import ModbusServerThread
    from hil_sim.devices.pt100 import Pt100Transmitter
    from hil_sim.devices.pt100_modbus import Pt100ModbusDevice

    with ModbusServerThread(Pt100ModbusDevice(Pt100Transmitter(["T_xi"], [24.0])), port=0) as server:
        cfg = {
            "loop": {"period_s": 0.002, **({} if io == "process" else {"io": "thread"})},
            "sources": [
                {
                    "kind": "modbus",
                    "name": "pt",
                    "transport": "tcp",
                    "host": "127.0.0.1",
                    "port": server.port,
                    "poll_period_s": 0.02,
                    "timeout_s": 0.5,
                    "channels": [{"name": "T_xi", "address": 0}],
                }
            ],
            "model": {
                "kind": "xi_spindle",
                "inputs": ["T_xi"],
                "outputs": ["z"],
                "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": 20.0},
            },
            "guard": {"max_slew_um_per_s": 1000.0},
            "sink": {"kind": "pci1756"},
            "status": {"period_s": 0.1},
        }
        path = tmp_path / "c.yaml"
        path.write_text(yaml.safe_dump(cfg))
        app = App(load_config(path))
        app.open()
        try:
            source = app.sources[0]
            assert source.worker.in_process is (io == "process")
            pid = source.io_status()["pid"]
            assert (pid != os.getpid()) is (io == "process")
            assert source.worker.wait_for(source.sampled, WAIT_S)
            app.loop.run(max_cycles=200)
            assert app.frame.values[app.frame.index["T_xi"]] == pytest.approx(24.0, abs=0.1)
            assert app.loop.pred_um[0] == pytest.approx(13.6e-6 * 165.0 * 1000.0 * 4.0, rel=0.01)  # 24 °C: +8.98 µm
        finally:
            app.close()
        if io == "process":
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)
