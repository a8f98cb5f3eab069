"""Matrix rows for the daemon process itself: `kill -9` and restart, a bad config on SIGHUP.

`compd run` runs as a child process on the wall clock against a PT100 Modbus TCP module
served from the test; what it did is read back from its data log (t_s is the monotonic
clock, the same clock this test reads) and its key=value lines on stderr.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from compd.log import read_log
from hil_sim.devices.modbus_server import ModbusServerThread
from hil_sim.devices.pt100 import Pt100Transmitter
from hil_sim.devices.pt100_modbus import Pt100ModbusDevice
from tests.conftest import ROOT
from tests.faults.harness import SENSOR, SLEW_UM_PER_S, Measured, modbus_tcp_source, record

LOG_PERIOD_S = 0.05
PERIOD_S = 0.01
FLUSH_S = 0.2
T_RESOLUTION_S = 1e-4  # the log's t_s: four decimals
ALPHA_L_UM_PER_K = 13.6e-6 * 165.0 * 1000.0


def _config(port: int, **top) -> dict:  # noqa: ANN003
    return {
        "loop": {"period_s": PERIOD_S},
        "sources": [modbus_tcp_source(port)],
        "model": {
            "kind": "xi_spindle",
            "inputs": [SENSOR],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": None},
        },
        "guard": {"max_slew_um_per_s": SLEW_UM_PER_S, "recovery_s": 0.3, "stale_after_s": 0.3},
        "sink": {"kind": "pci1756", "heartbeat_bit": 16},
        "log": {"path": "run.csv", "period_s": LOG_PERIOD_S, "flush_s": FLUSH_S},
        "state": {"path": "state.json"},
        **top,
    }


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


def _rows(path: Path) -> np.ndarray:
    if not path.exists():
        return np.zeros((0, 0))
    try:
        return read_log(path, allow_nan=True).data
    except Exception:  # noqa: BLE001  (a row being written right now)
        return np.zeros((0, 0))


def _wait(pred, timeout_s: float = 20.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _steps(data: np.ndarray, corr: int) -> tuple[float, float]:
    """Largest change of the correction between log rows, and the largest ratio to slew × Δt.

    The log keeps t_s to 0.1 ms, so a Δt read from it is short by up to that much (two
    roundings of 0.05 ms); rows come at every change of the word, one cycle (10 ms) apart at
    the least, where 0.1 ms is 1 %: Δt gets its resolution back before the ratio is taken."""
    d = np.abs(np.diff(data[:, corr]))
    dt = np.diff(data[:, 0])
    ok = dt > 0
    ratio = float(np.max(d[ok] / (SLEW_UM_PER_S * (dt[ok] + T_RESOLUTION_S)), initial=0.0))
    return float(d.max(initial=0.0)), ratio


def _word(data: np.ndarray, columns: list[str]) -> dict[str, float]:
    """The word's promises read from the log (a row is written on every change of the word,
    so consecutive changes are consecutive rows): one LSB at a time; every LSB paid from the
    licensed time, a settled word banking at most one LSB plus a row's refill (the rows are
    not every cycle, so this replay is the most the codec can have had); and never further
    from the guarded correction than the band (LSB = dead-band = 1 µm here), two cycles of
    slew, and what a stall (a reload's pause) licensed beyond one LSB a cycle while the word
    catches up. Keys as in `Measured`."""
    word = data[:, columns.index("word")].astype(int)
    corr = data[:, columns.index("corr_z_um")]
    t = data[:, 0]
    code = np.array([(1 if w & 0x8000 else -1) * ((w >> 8) & 0x3F) if w & 0x4000 else 0 for w in word])
    allowed_um = 1.0 + 2 * SLEW_UM_PER_S * PERIOD_S
    budget, behind, pace, over = 0.0, 0.0, 0.0, -math.inf
    for k in range(1, len(code)):
        gap_s = t[k] - t[k - 1]
        gain = gap_s * SLEW_UM_PER_S / 1.0  # LSB = 1 µm
        budget += gain
        behind = max(0.0, behind + gain - 1.0)  # as if the gap were one (stalled) cycle
        step = abs(int(code[k]) - int(code[k - 1]))
        if step and not (code[k] == 0 and step > 1):  # not the safe output (0x0000 at once)
            pace = max(pace, step / budget if budget > 0 else math.inf)
            budget = max(0.0, budget - step)
        c = corr[k]
        goal = 0 if abs(c) <= 1.0 else int(math.floor(abs(c) + 0.5)) * (1 if c > 0 else -1)
        if code[k] == goal:
            budget = min(budget, 1.0 + gain)
        over = max(over, abs(code[k] - c) - (allowed_um + behind))
    return {
        "word_max_step_lsb": int(np.abs(np.diff(code)).max(initial=0)),
        "word_pace_ratio": pace,
        "word_max_error_um": allowed_um + over if over > -math.inf else 0.0,
        "word_band_um": allowed_um,
    }


def _check_word(m: Measured) -> None:
    assert m.word_max_step_lsb <= 1 and m.word_pace_ratio <= 1.0 + 1e-6, m
    assert m.word_max_error_um <= m.word_band_um + 1e-6, m


def test_kill9_and_restart(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [22.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(_config(server.port)))
        log_path, err = tmp_path / "run.csv", tmp_path / "stderr.txt"
        proc = _start(cfg, err)
        try:
            _wait(lambda: (tmp_path / "state.json").exists() and len(_rows(log_path)) > 5)
            tx.set(SENSOR, 26.0)  # T0 = 22 °C was taken from the first reading: 4 K of warm-up
            want_um = -ALPHA_L_UM_PER_K * 4.0
            cols = read_log(log_path, allow_nan=True).columns
            corr = cols.index("corr_z_um")
            _wait(lambda: abs(_rows(log_path)[-1, corr] - want_um) < 0.5)
            time.sleep(0.3)
            t_kill = time.monotonic()
            proc.kill()  # SIGKILL: no safe output, no last flush
            proc.wait(10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        before = read_log(log_path, allow_nan=True)  # the log is a valid CSV after kill -9
        lost_s = t_kill - before.t_s[-1]
        state = json.loads((tmp_path / "state.json").read_text())
        assert state["state"]["t0_c"] == 22.0

        # restart at 26 °C: a fresh start would take T0 = 26 (no correction); resumed, T0 = 22
        proc = _start(cfg, err)
        try:
            _wait(lambda: len(_rows(log_path)) > len(before) + 2 and abs(_rows(log_path)[-1, corr] - want_um) < 0.5)
        finally:
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(10) == 0
        after = read_log(log_path, allow_nan=True)
        text = err.read_text()
    assert "event=state_restored" in text
    step, ratio = _steps(after.data[len(before) :], corr)  # the restarted run slews from 0
    rows_lost = max(0, math.floor(lost_s / LOG_PERIOD_S))
    m = Measured(
        max_step_um=step,
        allowed_step_um=SLEW_UM_PER_S * LOG_PERIOD_S,
        max_step_ratio=ratio,
        time_to_safe_s=None,
        recovered=True,
        samples_lost=rows_lost,
        event="state_restored (T0 22 °C kept)",
        logged=True,
        word_valid=True,
        policy_ok=True,
        running=True,
        cycles=len(after),
        fault_t_s=None,
        extra={"lost_s": lost_s, "flush_s": FLUSH_S},
        **_word(after.data[len(before) :], after.columns),
    )
    record("kill9_restart", m, tmp_path)
    _check_word(m)
    # rows lost: at most the flush interval plus one log period (and the scheduler's slack)
    assert lost_s <= FLUSH_S + LOG_PERIOD_S + 0.3, lost_s
    assert ratio <= 1.01  # the log keeps 6 significant digits of the correction


def test_bad_config_on_reload(tmp_path: Path) -> None:
    tx = Pt100Transmitter([SENSOR], [22.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        good = _config(server.port)
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(good))
        log_path, err = tmp_path / "run.csv", tmp_path / "stderr.txt"
        proc = _start(cfg, err)
        try:
            _wait(lambda: len(_rows(log_path)) > 5)
            tx.set(SENSOR, 26.0)
            time.sleep(0.2)  # the correction is slewing towards −8.98 µm
            bad = yaml.safe_dump(good).replace("max_slew_um_per_s", "max_slew")
            cfg.write_text(bad)
            t_hup = time.monotonic()
            proc.send_signal(signal.SIGHUP)
            _wait(lambda: "reload rejected" in err.read_text())
            time.sleep(0.8)
            assert proc.poll() is None  # still running on the old config
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(10) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    data = read_log(log_path, allow_nan=True)
    corr = data.columns.index("corr_z_um")
    step, ratio = _steps(data.data, corr)
    lines = [ln for ln in err.read_text().splitlines() if "reload rejected" in ln and "compd:" in ln]
    assert len(lines) == 1 and "max_slew" in lines[0] and "c.yaml" in lines[0]
    after_hup = data.data[data.t_s > t_hup]
    assert len(after_hup) > 5  # kept logging (and compensating) on the old config
    m = Measured(
        max_step_um=step,
        allowed_step_um=SLEW_UM_PER_S * LOG_PERIOD_S,
        max_step_ratio=ratio,
        time_to_safe_s=None,
        recovered=True,
        samples_lost=0,
        event="reload_rejected: " + lines[0].split("still running the old config: ", 1)[-1].replace(f"{tmp_path}/", ""),
        logged="event=reload_rejected" in err.read_text(),
        word_valid=True,
        policy_ok=True,
        running=True,
        cycles=len(data),
        fault_t_s=None,
        **_word(data.data, data.columns),
    )
    record("bad_config_reload", m, tmp_path)
    _check_word(m)
    assert ratio <= 1.01 and m.logged  # 1 %: the log keeps 6 significant digits


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_reload_to_an_unopenable_config(tmp_path: Path) -> None:
    """The new config validates but its metrics port is taken: the old pipeline runs on."""
    import socket

    tx = Pt100Transmitter([SENSOR], [22.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server, socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        good = _config(server.port)
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(good))
        log_path, err = tmp_path / "run.csv", tmp_path / "stderr.txt"
        proc = _start(cfg, err)
        try:
            _wait(lambda: len(_rows(log_path)) > 5)
            tx.set(SENSOR, 26.0)
            time.sleep(0.2)  # the correction is slewing towards −8.98 µm
            cfg.write_text(yaml.safe_dump({**good, "metrics": {"enabled": True, "port": taken.getsockname()[1]}}))
            t_hup = time.monotonic()
            proc.send_signal(signal.SIGHUP)
            _wait(lambda: "reload failed" in err.read_text() or proc.poll() is not None)
            time.sleep(0.8)
            assert proc.poll() is None, err.read_text()  # still running on the old pipeline
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(10) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    data = read_log(log_path, allow_nan=True)
    corr = data.columns.index("corr_z_um")
    step, ratio = _steps(data.data, corr)
    text = err.read_text()
    lines = [ln for ln in text.splitlines() if "event=reload_failed" in ln]
    after_hup = data.data[data.t_s > t_hup]
    m = Measured(
        max_step_um=step,
        allowed_step_um=SLEW_UM_PER_S * LOG_PERIOD_S,
        max_step_ratio=ratio,
        time_to_safe_s=None,
        recovered=True,
        samples_lost=0,
        event="reload_failed: " + (lines[0].split('reason="', 1)[-1].rstrip('"') if lines else "none"),
        logged=len(lines) == 1,
        word_valid=True,
        policy_ok=True,
        running=len(after_hup) > 5,
        cycles=len(data),
        fault_t_s=None,
        extra={"rows_after_hup": len(after_hup)},
        **_word(data.data, data.columns),
    )
    record("reload_unopenable", m, tmp_path)
    _check_word(m)
    assert m.logged and "cannot serve metrics" in lines[0], text
    assert m.running  # kept logging (and compensating) on the old config
    assert ratio <= 1.01  # 1 %: the log keeps 6 significant digits
    assert abs(after_hup[-1, corr] + ALPHA_L_UM_PER_K * 4.0) < 0.5  # it reached the correction


def test_reload_to_an_unreachable_sink(tmp_path: Path) -> None:
    """A reload to a FANUC PMC nothing answers for: status says link down, axis not enabled."""
    from compd.service.status import read_status, render

    tx = Pt100Transmitter([SENSOR], [22.0])
    with ModbusServerThread(Pt100ModbusDevice(tx), port=0) as server:
        good = {
            **_config(server.port),
            "status": {"path": "status.json", "period_s": 0.1},
            "metrics": {"enabled": True, "port": _free_port()},
        }
        cfg = tmp_path / "c.yaml"
        cfg.write_text(yaml.safe_dump(good))
        log_path, err, status = tmp_path / "run.csv", tmp_path / "stderr.txt", tmp_path / "status.json"
        proc = _start(cfg, err)
        try:
            _wait(lambda: len(_rows(log_path)) > 5 and status.exists())
            tx.set(SENSOR, 26.0)
            _wait(lambda: read_status(status)["axes"]["z"]["enable"] and read_status(status)["sink"]["link"] == "up")
            before = read_status(status)
            sink = {"kind": "fanuc_pmc", "host": "127.0.0.1", "port": _free_port(), "timeout_s": 0.1}
            cfg.write_text(yaml.safe_dump({**good, "sink": sink}))
            t_hup = time.monotonic()
            proc.send_signal(signal.SIGHUP)
            _wait(lambda: "compd: reloaded" in err.read_text())
            _wait(lambda: read_status(status)["sink"]["link"] == "down", timeout_s=30)
            snap = read_status(status)
            t_down = time.monotonic() - t_hup
            import urllib.request

            with urllib.request.urlopen(snap["metrics_url"], timeout=10) as r:
                metrics = r.read().decode()
            assert proc.poll() is None
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(60) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    z = snap["axes"]["z"]
    m = Measured(
        max_step_um=0.0,
        allowed_step_um=SLEW_UM_PER_S * LOG_PERIOD_S,
        max_step_ratio=0.0,
        time_to_safe_s=None,
        recovered=False,
        samples_lost=0,
        event=f"status: state {snap['state']}, sink link {snap['sink']['link']}, z enable {z['enable']}",
        logged="compd_sink_link_up 0.0" in metrics,
        word_valid=True,
        policy_ok=True,
        running=True,
        cycles=snap["loop"]["cycles"],
        fault_t_s=None,
        extra={"link_down_after_s": round(t_down, 2), "enable_before": before["axes"]["z"]["enable"]},
    )
    record("reload_unreachable_sink", m, tmp_path)
    assert before["axes"]["z"]["enable"] is True and before["sink"]["link"] == "up"
    assert snap["sink"]["link"] == "down" and z["enable"] is None  # not confirmed at the machine
    assert 'compd_axis_enabled{axis="z"} NaN' in metrics and m.logged
    assert "NOT REACHING THE MACHINE" in render(snap, True, "running")
