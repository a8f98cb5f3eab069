"""SIGHUP: a bad config is rejected and the old one keeps running; a good one takes over without a step."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from compd.log import read_log

CONFIG = """\
loop: {{clock: sim, period_s: 1.0, speedup: 600}}
sources:
  - kind: sim
    name: spindle
    plant: spindle
    scenario: {{segments: [{{duration_s: 86400, speed_rpm: 12000}}]}}
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {{alpha_per_k: 13.6e-6, length_mm: 165.0}}
guard: {{max_slew_um_per_s: {slew}}}
sink: {{kind: pci1756}}
log: {{path: run.csv, period_s: 1.0, flush_s: 0.2}}
"""


def wait_for(pred, timeout_s: float = 60.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.05)


def logged_t_s(path: Path) -> float:
    """The time of the last complete row of a log being written (0 before the first)."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return 0.0
    for line in reversed(lines[1:]):
        try:
            return float(line.split(",", 1)[0])
        except ValueError:
            continue
    return 0.0


def test_sighup_reload(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(slew=0.05))
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        run_log = tmp_path / "run.csv"
        try:  # each step waits for simulated time in the log, not for wall time
            wait_for(lambda: logged_t_s(run_log) > 600)
            cfg.write_text(CONFIG.format(slew=0.05).replace("max_slew_um_per_s", "max_slew"))
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "reload rejected" in err_path.read_text())
            assert proc.poll() is None  # still running on the old config
            t_rejected = logged_t_s(run_log)
            wait_for(lambda: logged_t_s(run_log) > t_rejected + 600)
            cfg.write_text(CONFIG.format(slew=0.02))
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "reloaded" in err_path.read_text())
            t_reloaded = logged_t_s(run_log)
            wait_for(lambda: logged_t_s(run_log) > max(t_reloaded + 600, 2100))
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = err_path.read_text()
    assert proc.returncode == 0, text
    assert "guard.max_slew" in text and ":12:" in text
    log = read_log(tmp_path / "run.csv", allow_nan=True)
    t = log.col("t_s")
    corr = log.col("corr_z_um")
    assert t[-1] > 2000  # simulated seconds
    dt = np.diff(t)
    steps = np.abs(np.diff(corr))
    ok = dt > 0
    # never faster than the larger of the two slew limits, across both reloads
    assert (steps[ok] <= 0.05 * dt[ok] + 1e-9).all()
    assert corr.min() < -10  # it was compensating a warm spindle throughout


_KV = re.compile(r'(\w+)=("(?:[^"\\]|\\.)*"|\S+)')


def events(text: str) -> list[dict[str, str]]:
    """The key=value log lines of compd's stderr, parsed (quotes removed)."""
    out = []
    for line in text.splitlines():
        if not line.startswith("ts=") and not line.startswith("<"):
            continue
        fields = {k: v[1:-1].replace('\\"', '"') if v.startswith('"') else v for k, v in _KV.findall(line)}
        out.append(fields)
    return out


def _start(cfg: Path, err_path: Path) -> subprocess.Popen:
    with open(err_path, "a") as err:
        return subprocess.Popen(
            [sys.executable, "-m", "compd", "run", str(cfg)],
            cwd=cfg.parent,
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def _stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _rows(path: Path) -> int:
    try:
        return len(read_log(path, allow_nan=True))
    except Exception:  # noqa: BLE001  (not there yet, or a row being written)
        return 0


def test_a_reload_that_cannot_open_keeps_the_old_pipeline(tmp_path: Path) -> None:
    """SIGHUP to a config that validates but cannot open (metrics port taken by someone
    else): reload_failed naming why, the old pipeline keeps compensating without a step,
    and compd keeps running (no exit 2). An unchanged metrics endpoint is kept, not re-bound."""
    import socket
    import urllib.request

    cfg = tmp_path / "c.yaml"
    err_path = tmp_path / "stderr.txt"
    with socket.socket() as mine, socket.socket() as taken:
        mine.bind(("127.0.0.1", 0))
        port = mine.getsockname()[1]
        mine.close()  # compd's own port
        taken.bind(("127.0.0.1", 0))
        taken.listen()  # somebody else's
        base = CONFIG.format(slew=0.05)
        cfg.write_text(base + f"metrics: {{enabled: true, port: {port}}}\n")
        proc = _start(cfg, err_path)
        try:
            wait_for(lambda: "event=metrics" in err_path.read_text() and _rows(tmp_path / "run.csv") > 5)
            # 1. same metrics port, another slew: reloads, keeping the bound endpoint
            cfg.write_text(CONFIG.format(slew=0.04) + f"metrics: {{enabled: true, port: {port}}}\n")
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "compd: reloaded" in err_path.read_text())
            # 2. the metrics port is taken: the reload fails, the old pipeline runs on
            cfg.write_text(CONFIG.format(slew=0.03) + f"metrics: {{enabled: true, port: {taken.getsockname()[1]}}}\n")
            proc.send_signal(signal.SIGHUP)
            wait_for(lambda: "reload failed" in err_path.read_text() or proc.poll() is not None)
            assert proc.poll() is None, err_path.read_text()  # still running …
            n = _rows(tmp_path / "run.csv")
            wait_for(lambda: _rows(tmp_path / "run.csv") > n + 20)  # … and compensating
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
                assert b"compd_cycles_total" in r.read()  # the old endpoint still answers
        finally:
            rc = _stop(proc)
    text = err_path.read_text()
    assert rc == 0, text
    failed = [e for e in events(text) if e.get("event") == "reload_failed"]
    assert len(failed) == 1 and "cannot serve metrics" in failed[0]["reason"], failed
    assert not [e for e in events(text) if e.get("event") == "stop"][:-1]  # one stop: at the end
    log = read_log(tmp_path / "run.csv", allow_nan=True)
    t, corr = log.col("t_s"), log.col("corr_z_um")
    dt, steps = np.diff(t), np.abs(np.diff(corr))
    ok = dt > 0
    assert (steps[ok] <= 0.05 * dt[ok] + 1e-9).all()  # never a step, across both reloads
    assert corr.min() < -1  # it was compensating throughout


def test_reload_events_are_their_own_event_key(tmp_path: Path) -> None:
    """reload_rejected / reloading / reloaded are `event=` keys, never `event=compd msg="event=…"`."""
    cfg = tmp_path / "c.yaml"
    err_path = tmp_path / "stderr.txt"
    cfg.write_text(CONFIG.format(slew=0.05))
    proc = _start(cfg, err_path)
    try:
        wait_for(lambda: _rows(tmp_path / "run.csv") > 5)
        cfg.write_text(CONFIG.format(slew=0.05).replace("max_slew_um_per_s", "max_slew"))
        proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "reload rejected" in err_path.read_text())
        cfg.write_text(CONFIG.format(slew=0.04))
        proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "compd: reloaded" in err_path.read_text())
    finally:
        assert _stop(proc) == 0
    evs = events(err_path.read_text())
    assert all("event=" not in e.get("msg", "") for e in evs), evs
    names = [e["event"] for e in evs]
    assert "reload_rejected" in names and "reloaded" in names
    rejected = next(e for e in evs if e["event"] == "reload_rejected")
    assert "guard.max_slew" in rejected["reason"] and rejected["config"] == str(cfg)


FANUC_NOWHERE = "sink: {{kind: fanuc_pmc, host: 127.0.0.1, port: {port}, timeout_s: 0.1, max_step_um: 1.0}}"


def test_a_sighup_during_a_slow_reload_is_not_lost(tmp_path: Path) -> None:
    """Closing a fanuc_pmc sink with no PMC reachable takes seconds; a SIGHUP during that
    reload triggers one more reload of the then-current file (the last request wins)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens there: the PMC is unreachable
    cfg = tmp_path / "c.yaml"
    err_path = tmp_path / "stderr.txt"
    first = CONFIG.format(slew=0.05).replace("sink: {kind: pci1756}", FANUC_NOWHERE.format(port=port))
    cfg.write_text(first)
    proc = _start(cfg, err_path)
    try:
        wait_for(lambda: _rows(tmp_path / "run.csv") > 20)  # a correction to walk back on close
        cfg.write_text(CONFIG.format(slew=0.05))  # pci1756: the fanuc sink is closed (slowly)
        proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "event=reloading" in err_path.read_text())
        cfg.write_text(CONFIG.format(slew=0.05).replace("run.csv", "last.csv"))
        proc.send_signal(signal.SIGHUP)  # while the first reload is still closing the old sink
        wait_for(lambda: _rows(tmp_path / "last.csv") > 5, timeout_s=120)
        assert proc.poll() is None
    finally:
        assert _stop(proc) == 0
    text = err_path.read_text()
    assert text.count("compd: reloaded") == 2, text
