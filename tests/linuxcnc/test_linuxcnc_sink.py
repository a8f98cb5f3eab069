"""The linuxcnc sink against a real (headless) LinuxCNC: compd's HAL component offsets Z by the correction,
a restarted compd moves nothing, the safe output leaves 0, and a machine that is not on is a link down.

Every wait is a condition with a generous deadline (these run in `make test`, beside other load)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from compd.sinks.linuxcnc import LinuxcncConfig, LinuxcncSink
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from tests.conftest import ROOT
from tests.daemon.test_service_process import SENSOR, _config, _start
from tests.linuxcnc.sim import Sim, require, wait_for
from tests.service_helpers import wait_running

pytestmark = pytest.mark.slow  # minutes of CPU: make test starts it first (tests/conftest.py)

UM = 1e-3  # mm


class _Model:
    outputs = ["z"]


def _sink(**kw) -> LinuxcncSink:
    sink = LinuxcncSink(LinuxcncConfig(kind="linuxcnc", axes=["z"], **kw))
    sink.bind(["z"], 1.0)
    sink.bind_model(_Model())
    return sink


def _synced(sink: LinuxcncSink) -> None:
    """Open, then cycle by hand until the sink has read back what LinuxCNC applies (as the loop does)."""
    sink.open(time.monotonic())
    wait_for(
        lambda: sink.sync(time.monotonic()) or sink.synced() and sink.syncs, "the sink's read-back", timeout_s=90.0
    )
    wait_for(lambda: sink.link_state() == "up", "the link up", timeout_s=60.0)


def _write(sink: LinuxcncSink, um: float) -> None:
    sink.write(0, np.array([um]), np.array([True]), True, time.monotonic())
    sink.settle(time.monotonic())


def _applied(sink: LinuxcncSink) -> float:
    out = np.zeros(1)
    sink.applied_um(out)
    return float(out[0])


def _daemon_config(tmp_path: Path, port: int, **guard: object) -> Path:
    """The service tests' daemon (a PT100 module's ξ sensor, t0 20 °C) with the linuxcnc sink on Z."""
    cfg = _config(port)
    cfg["sink"] = {"kind": "linuxcnc", "axes": ["z"], "count_um": 0.1}
    cfg["model"]["params"]["t0_c"] = 20.0
    cfg["guard"].update(guard)
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_the_offset_follows_the_correction_a_restart_moves_nothing_and_safe_leaves_zero():
    require()
    with Sim() as sim:
        sink = _sink(count_um=0.1)
        try:
            _synced(sink)
            assert sink.held_um() == {"z": pytest.approx(0.0, abs=1e-9)}
            assert sim.getp("axis.z.eoffset-enable") is True
            _write(sink, 12.34)
            wait_for(lambda: abs(sim.getp("axis.z.eoffset") - 12.3 * UM) < 1e-6, "axis.z.eoffset at 12.3 um")
            wait_for(lambda: abs(_applied(sink) - 12.3) < 1e-3, "the sink's read-back at 12.3 um")
            _write(sink, -4.0)
            wait_for(lambda: abs(sim.getp("axis.z.eoffset") + 4.0 * UM) < 1e-6, "axis.z.eoffset at -4 um")
        finally:
            sink.close()  # the component leaves HAL; LinuxCNC keeps the offset its counts left
        assert sim.getp("axis.z.eoffset") == pytest.approx(-4.0 * UM, abs=1e-6)
        counts_left = sim.getp("axis.z.eoffset-counts")
        # a compd started again: its counts pin starts at 0, the signal carries the old counts
        again = _sink(count_um=0.1)
        try:
            _synced(again)
            assert again.held_um() == {"z": pytest.approx(-4.0, abs=1e-3)}
            assert sim.getp("axis.z.eoffset-counts") == counts_left
            assert sim.getp("axis.z.eoffset") == pytest.approx(-4.0 * UM, abs=1e-6)  # nothing moved
            _write(again, -3.0)
            wait_for(lambda: abs(sim.getp("axis.z.eoffset") + 3.0 * UM) < 1e-6, "axis.z.eoffset at -3 um")
            assert again.safe()
            assert abs(sim.getp("axis.z.eoffset")) < 0.1 * UM
        finally:
            again.close()
        assert "compd" not in sim.halcmd("show", "comp")


def test_a_machine_that_is_off_is_a_link_down_that_says_why():
    _, linuxcnc = require()
    with Sim() as sim:
        sink = _sink()
        try:
            _synced(sink)
            linuxcnc.command().state(linuxcnc.STATE_OFF)  # the operator turns the machine off
            wait_for(lambda: sink.link_state() == "down", "the link down with the machine off", timeout_s=60.0)
            assert "machine is off" in (sink.link.get_status()["last_error"] or "")
            assert sim.getp("motion.motion-enabled") is False
        finally:
            sink.close()


def test_the_daemon_compensates_through_linuxcnc_and_sigterm_leaves_zero(tmp_path: Path) -> None:
    """`compd run` (wall clock: its I/O, the HAL component with it, in a process of its own) on a PT100
    module: the offset LinuxCNC applies follows the status's correction within 1 µm; SIGTERM leaves 0."""
    require()
    tx = Pt100Transmitter([SENSOR], [20.0])
    with Sim() as sim, ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        path = _daemon_config(tmp_path, server.port)
        err = tmp_path / "stderr.txt"
        proc = _start(path, err)
        try:
            status = tmp_path / "status.json"
            wait_running(status, proc)
            tx.set(SENSOR, 25.0)  # 5 K: α L ΔT = 11.2 µm of growth, the correction its opposite

            def steady() -> dict | None:
                st = json.loads(status.read_text())
                z = st["axes"]["z"]
                return st if z["correction_um"] is not None and abs(z["correction_um"] + 11.22) < 0.5 else None

            wait_for(steady, "the correction at -11.2 um")
            for _ in range(5):  # LinuxCNC's offset between two of compd's statuses, within 1 µm
                before = json.loads(status.read_text())["axes"]["z"]["correction_um"]
                applied_um = sim.getp("axis.z.eoffset") * 1000.0
                after = json.loads(status.read_text())["axes"]["z"]["correction_um"]
                assert min(before, after) - 1.0 <= applied_um <= max(before, after) + 1.0
            z = json.loads(status.read_text())["axes"]["z"]
            assert z["applied_um"] == pytest.approx(sim.getp("axis.z.eoffset") * 1000.0, abs=1.0)
        finally:
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(60)
        assert code == 0, err.read_text()
        assert abs(sim.getp("axis.z.eoffset")) < 0.15 * UM  # the safe state: 0, then compd left
        assert "compd" not in sim.halcmd("show", "comp")


def test_linuxcnc_stopping_under_the_daemon_is_a_link_down_and_its_return_is_compensated(tmp_path: Path) -> None:
    """LinuxCNC's shutdown ends the process of every userspace component (compd's I/O process): the daemon
    runs on, its status says the sink's link is down and why; a LinuxCNC started again is compensated from
    what it applies (0), with a program running."""
    require()
    tx = Pt100Transmitter([SENSOR], [22.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        path = _daemon_config(tmp_path, server.port)
        err = tmp_path / "stderr.txt"
        status = tmp_path / "status.json"

        def sink_status() -> dict:
            return json.loads(status.read_text())["sink"]

        def compensating(sim: Sim) -> bool:
            return abs(sim.getp("axis.z.eoffset") * 1000.0 + 4.49) < 0.5  # 2 K: −4.49 µm

        proc = None
        try:
            with Sim() as sim:
                proc = _start(path, err)
                wait_running(status, proc)
                wait_for(lambda: compensating(sim), "LinuxCNC's offset at -4.5 um")
            wait_for(lambda: sink_status()["link"] == "down", "the sink's link down without LinuxCNC")
            assert proc.poll() is None, err.read_text()
            assert "LinuxCNC" in (sink_status()["link_stats"]["last_error"] or "")
            with Sim() as sim:
                program = sim.folder / "spin.ngc"
                program.write_text("G21 G90\nS3000 M3\nG4 P5\nM5\nM2\n")
                sim.run_program(program)
                wait_for(lambda: compensating(sim), "the new LinuxCNC's offset at -4.5 um")
                assert sim.getp("spindle.0.speed-out") == pytest.approx(3000.0) or sim.stat().interp_state
                proc.send_signal(signal.SIGTERM)
                assert proc.wait(60) == 0, err.read_text()
                assert abs(sim.getp("axis.z.eoffset")) < 0.15 * UM
        finally:
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(30)


def test_output_test_reads_back_what_linuxcnc_applies(tmp_path: Path) -> None:
    """`compd output-test` through the linuxcnc sink: +5 µm commanded, LinuxCNC's axis.z.eoffset read back
    +5 µm, then 0 after the safe state."""
    require()
    tx = Pt100Transmitter([SENSOR], [20.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server, Sim() as sim:
        cfg = _config(server.port)
        cfg["sink"] = {"kind": "linuxcnc", "axes": ["z"]}
        path = tmp_path / "c.yaml"
        path.write_text(yaml.safe_dump(cfg))
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "compd",
                "output-test",
                str(path),
                "--axis",
                "z",
                "--um",
                "5",
                "--hold-s",
                "1",
                "--yes",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stderr
        assert "commanded +5.000 um, applied +5.000 um" in done.stdout
        assert "safe state: applied +0.000 um" in done.stdout
        assert abs(sim.getp("axis.z.eoffset")) < 0.15 * UM
        assert "compd" not in sim.halcmd("show", "comp")


def test_without_linuxcnc_check_config_refuses_the_sink_and_the_source_in_one_line(tmp_path: Path) -> None:
    """A machine without LinuxCNC's Python modules (here: $COMPD_LINUXCNC_PYTHON an empty folder) runs
    everything else; a config that needs them is refused at check-config, exit 2, one line naming what is missing."""
    cfgs = {
        "sink": "loop: {clock: sim, period_s: 1.0}\nsources: [{kind: replay, name: log, path: day.csv}]\n"
        "model: {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 1.3e-5, length_mm: 165}}\n"
        "sink: {kind: linuxcnc, axes: [z]}\n",
        "sources[1]": "loop: {clock: sim, period_s: 1.0}\nsources:\n  - {kind: replay, name: log, path: day.csv}\n"
        "  - {kind: hal, name: cnc, signals: [{name: speed_rpm, pin: spindle.0.speed-out}]}\n"
        "model: {kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 1.3e-5,"
        " length_mm: 165}}\nsink: {kind: pci1756}\n",
    }
    (tmp_path / "day.csv").write_text("t_s,T_xi\n0,20\n1,20\n")
    empty = tmp_path / "no-linuxcnc"
    empty.mkdir()
    for key, text in cfgs.items():
        path = tmp_path / f"{key[:4]}.yaml"
        path.write_text(text)
        done = subprocess.run(
            [sys.executable, "-m", "compd", "check-config", str(path)],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT), "COMPD_LINUXCNC_PYTHON": str(empty)},
            timeout=120,
        )
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1, done.stderr
        assert f"{path.name}:" in lines[0] and f"{key}:" in lines[0] and "make sysdeps" in lines[0], lines[0]


@pytest.mark.parametrize("policy", ["ramp_to_zero", "disable"])
def test_a_sensor_fault_takes_linuxcnc_s_offset_to_zero_through_counts(tmp_path: Path, policy: str) -> None:
    """The ξ sensor burns out under a running daemon: with fault_policy ramp_to_zero the correction ramps to 0, with
    disable it is dropped; either way LinuxCNC's applied offset goes to 0 through compd's counts (the link stays up)."""
    require()
    tx = Pt100Transmitter([SENSOR], [25.0])
    with Sim() as sim, ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        path = _daemon_config(tmp_path, server.port, fault_policy=policy)
        err = tmp_path / "stderr.txt"
        proc = _start(path, err)
        try:
            wait_running(tmp_path / "status.json", proc)
            wait_for(lambda: abs(sim.getp("axis.z.eoffset") * 1000.0 + 11.22) < 0.5, "the offset at -11.2 um")
            tx.set_fault(SENSOR, "burnout")
            wait_for(lambda: abs(sim.getp("axis.z.eoffset")) < 0.15 * UM, f"the offset at 0 ({policy})")
            assert json.loads((tmp_path / "status.json").read_text())["sink"]["link"] == "up"
        finally:
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(60)
        assert code == 0, err.read_text()
        assert abs(sim.getp("axis.z.eoffset")) < 0.15 * UM
