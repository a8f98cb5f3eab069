"""A restart after an unclean end never moves the axis: compd killed (SIGKILL, or SIGABRT as
systemd's watchdog sends it) while the CNC applies a correction starts again from what the CNC
applies, read back before anything is written.

The CNCs are `python -m hil_sim serve`'s (a FANUC PMC, a Siemens NC) over Modbus TCP; what they
apply is read by the test's own pymodbus client, not compd's, every few ms through the whole run:
the kill, the restart, the first writes of the new daemon. The model's T0 is fixed, so the
correction is the same before and after the restart: the axis must not move at all (one LSB of
the word), and never by more than the sink's step between two reads.
"""

from __future__ import annotations

import json
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from pymodbus.client import ModbusTcpClient

from tests.conftest import ROOT
from tests.faults.harness import SENSOR, modbus_tcp_source

WAIT_S = 60.0
T0_C, T_C = 22.0, 26.0  # the model's fixed T0 and the served temperature: a −8.98 µm correction
WANT_UM = -13.6e-6 * 165.0 * 1000.0 * (T_C - T0_C)
MAX_STEP_UM = 5.0  # the PMC sink's step (its PMC alarms above 10 µm)


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}


class Bench:
    """`hil_sim serve` with a PT100 module, a FANUC PMC and a Siemens NC on Modbus TCP."""

    def __init__(self, tmp: Path) -> None:
        cfg = {
            "devices": [
                {"kind": "pt100_modbus", "name": "tx", "port": 0, "channels": [{"name": SENSOR, "value_c": T_C}]},
                {"kind": "fanuc_pmc", "name": "pmc", "port": 0, "step_limit_um": 10},
                {"kind": "siemens_nc", "name": "nc", "port": 0, "axes": 2, "velo_factor": 1e-3},
            ]
        }
        path = tmp / "bench.yaml"
        path.write_text(yaml.safe_dump(cfg))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil_sim", "serve", "--config", str(path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        lines = []
        while True:
            line = self.proc.stdout.readline() if self.proc.stdout else ""
            assert line, self.proc.stderr.read() if self.proc.stderr else "hil_sim serve ended"
            lines.append(line)
            if "ready" in line:
                break
        self.ports = {
            m[0]: int(m[1]) for m in re.findall(r"^(\w+): \w+ on tcp:127\.0\.0\.1:(\d+)", "".join(lines), re.M)
        }

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()


class Watch(threading.Thread):
    """Reads what the CNC applies (µm) every few ms with a client of the test's own."""

    def __init__(self, port: int, address: int, decode: Any) -> None:
        super().__init__(name="watch", daemon=True)
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=1, retries=0)
        self.address, self.decode = address, decode
        self.reads: list[tuple[float, float]] = []
        self._halt = threading.Event()

    def run(self) -> None:
        self.client.connect()
        try:
            while not self._halt.is_set():
                rr = self.client.read_holding_registers(self.address, count=2, device_id=1)
                if not rr.isError() and len(rr.registers) == 2:
                    self.reads.append((time.monotonic(), self.decode(rr.registers)))
                time.sleep(0.003)
        finally:
            self.client.close()

    def last(self) -> float:
        return self.reads[-1][1] if self.reads else float("nan")

    def stop(self) -> None:
        self._halt.set()
        self.join(10)


def _pmc_um(regs: list[int]) -> float:  # register 404: axis 1's applied shift, µm, signed
    v = regs[0]
    return float(v - 0x10000 if v & 0x8000 else v)


def _nc_um(regs: list[int]) -> float:  # axis block +11: the applied ΔK, float32 mm
    return 1000.0 * struct.unpack(">f", struct.pack(">HH", regs[0], regs[1]))[0]


SINKS = {
    # sink section, the CNC device, the register of axis z's applied correction, its decoding, and
    # how fast the applied correction may move: `step_um` per `every_s` at most (the PMC sink's
    # step per min_update_s; the word's LSB at the guard's slew, 20 µm/s; the NC following K0,
    # sent every min_update_s, 0.05 s, at the guard's slew)
    "fanuc_pmc": (
        lambda p: {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": p, "max_step_um": MAX_STEP_UM},
        "pmc",
        404,
        _pmc_um,
        MAX_STEP_UM,
        0.02,
    ),
    "fanuc_pmc_shift": (
        lambda p: {"kind": "fanuc_pmc", "mode": "shift", "host": "127.0.0.1", "port": p, "max_step_um": MAX_STEP_UM},
        "pmc",
        404,
        _pmc_um,
        MAX_STEP_UM,
        0.02,
    ),
    "pci1756": (
        lambda p: {
            "kind": "pci1756",
            "device": "modbus",
            "host": "127.0.0.1",
            "port": p,
            "strobe_bit": 16,
            "heartbeat_bit": 24,
        },
        "pmc",
        404,
        _pmc_um,
        1.0,
        0.05,
    ),
    "siemens": (
        lambda p: {"kind": "siemens", "host": "127.0.0.1", "port": p, "axes": {"z": 0}},
        "nc",
        11,
        _nc_um,
        1.0,
        0.05,
    ),
}
# a K0 sent after a late cycle carries the slew of the time since the last (one send more)
SLACK = {"siemens": 2.0}


def _config(tmp: Path, bench: Bench, sink: dict[str, Any]) -> Path:
    cfg = {
        "loop": {"period_s": 0.005, "io": "process"},
        "sources": [modbus_tcp_source(bench.ports["tx"])],
        "model": {
            "kind": "xi_spindle",
            "inputs": [SENSOR],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": T0_C},
        },
        "guard": {"max_slew_um_per_s": 20.0},
        "sink": sink,
        "status": {"path": "status.json"},
    }
    path = tmp / "compd.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _start(cfg: Path, err: Path) -> subprocess.Popen:
    with open(err, "a") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            cwd=cfg.parent,
            stdout=subprocess.DEVNULL,
            stderr=fh,
            env=_env(),
        )


def _link(status: Path, pid: int) -> str | None:
    """The sink's link as the daemon `pid`'s status file says it (None: not its file yet)."""
    try:
        st = json.loads(status.read_text())
    except (OSError, ValueError):
        return None
    return st["sink"]["link"] if st.get("pid") == pid else None


def _wait(pred: Any, what: str, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGABRT], ids=["SIGKILL", "SIGABRT"])
@pytest.mark.parametrize("sink", list(SINKS))
def test_a_restart_after_an_unclean_end_never_moves_the_axis(tmp_path: Path, sink: str, sig: int) -> None:
    section, device, address, decode, step_um, every_s = SINKS[sink]
    bench = Bench(tmp_path)
    watch = None
    procs: list[subprocess.Popen] = []
    try:
        base = 16 * 0 if device == "nc" else 0
        watch = Watch(bench.ports[device], base + address, decode)
        watch.start()
        cfg = _config(tmp_path, bench, section(bench.ports[device]))
        err = tmp_path / "stderr.txt"
        procs.append(_start(cfg, err))
        # compensating: the CNC applies the correction (within one LSB, the NC within 0.2 µm)
        _wait(lambda: abs(watch.last() - WANT_UM) <= 1.0, "the correction at the CNC")
        time.sleep(0.3)
        held = watch.last()
        procs[0].send_signal(sig)  # no safe output, no last write: the CNC keeps the correction
        assert procs[0].wait(20) == -sig
        n_killed = len(watch.reads)
        _wait(lambda: len(watch.reads) > n_killed + 20, "reads after the kill")
        assert abs(watch.last() - held) < 1e-6  # the CNC holds it while no compd runs
        procs.append(_start(cfg, err))
        status = tmp_path / "status.json"
        _wait(lambda: _link(status, procs[1].pid) == "up", "the restarted daemon's link up")
        n_up = len(watch.reads)
        _wait(lambda: len(watch.reads) > n_up + 200, "reads while the restarted daemon compensates")
        n_term = len(watch.reads)  # what follows is the safe output: word 0 at once on the card, the NC's own ramp
        procs[1].send_signal(signal.SIGTERM)
        assert procs[1].wait(20) == 0, err.read_text()
        text = err.read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
        try:
            if watch is not None:
                watch.stop()
        finally:
            bench.stop()
    um = [v for _, v in watch.reads]
    after_kill = um[n_killed:n_term]
    moved = max(abs(v - held) for v in after_kill)
    # between two reads dt apart, at most `step_um` per `every_s` (and one step), whatever the
    # machine's load does to the reads' spacing
    t = [t for t, _ in watch.reads]
    slack = SLACK.get(sink, 1.0)
    pace = max(abs(um[i + 1] - um[i]) / (step_um * (slack + (t[i + 1] - t[i]) / every_s)) for i in range(n_term - 1))
    largest = max(abs(um[i + 1] - um[i]) for i in range(n_term - 1))
    # the same correction before and after: the restart does not move the axis (within a LSB) ...
    seen = [round(v, 2) for i, v in enumerate(after_kill) if i == 0 or v != after_kill[i - 1]]
    assert moved <= 1.0 + 1e-6, f"the axis moved {moved:.2f} um from {held:.2f} um across the restart: {seen[:40]}"
    # ... and nothing ever moves faster than the sink's step allows between two reads
    assert pace <= 1.0 + 1e-6, f"largest change between two reads {largest:.2f} um, {pace:.2f} x what is allowed"
    assert "event=synced" in text  # the restarted daemon said it read back what the CNC applies
    print(
        f"\n{sink} {signal.Signals(sig).name}: held {held:+.2f} um; across the restart it moved {moved:.2f} um;"
        f" largest change between two reads {largest:.2f} um ({len(um)} reads)"
    )


def test_a_reload_that_changes_the_sink_does_not_move_the_axis(tmp_path: Path) -> None:
    """A reload whose sink section changed (same PMC) hands the PMC over as it is: the new sink
    reads back the shift applied and goes on from there (it was walked to 0 and back before)."""
    bench = Bench(tmp_path)
    watch = Watch(bench.ports["pmc"], 404, _pmc_um)
    watch.start()
    proc = None
    try:
        sink = {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": bench.ports["pmc"], "max_step_um": MAX_STEP_UM}
        cfg = _config(tmp_path, bench, sink)
        err = tmp_path / "stderr.txt"
        proc = _start(cfg, err)
        _wait(lambda: abs(watch.last() - WANT_UM) <= 1.0, "the correction at the PMC")
        time.sleep(0.3)
        held = watch.last()
        n0 = len(watch.reads)
        cfg.write_text(cfg.read_text().replace(f"max_step_um: {MAX_STEP_UM}", "max_step_um: 4.0"))
        proc.send_signal(signal.SIGHUP)
        _wait(lambda: "compd: reloaded" in err.read_text(), "the reload")
        n1 = len(watch.reads)
        _wait(lambda: len(watch.reads) > n1 + 200, "reads after the reload")
        n_term = len(watch.reads)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0, err.read_text()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        try:
            watch.stop()
        finally:
            bench.stop()
    moved = max(abs(v - held) for _, v in watch.reads[n0:n_term])
    assert moved <= 1.0 + 1e-6, f"the axis moved {moved:.2f} um from {held:.2f} um across the reload"
