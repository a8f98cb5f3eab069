"""Status snapshot, atomic file, liveness, the human view and `compd status`."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from compd.cli import main
from compd.config import load_config
from compd.core.errors import BadInput
from compd.cycle.loop import TimingStats
from compd.cycle.statusblock import STALE_MIN_S
from compd.daemon.app import App
from compd.service.status import (
    held,
    liveness,
    mark_stale,
    read_status,
    render,
    snapshot,
    stale_after_s,
    timing,
    write_atomic,
)
from tests.service_helpers import sim_config


@pytest.fixture
def ran_app(tmp_path):
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    app.run()
    return app


def test_snapshot_has_what_the_issue_asks_and_is_json(tmp_path):
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    taken: dict = {}

    def take(loop, now):  # mid-run, from inside the cycle, so nothing moves under us
        if loop.stats.cycles == 3000:
            taken["snap"] = snapshot(loop, state="running", observe=False)
            taken["out"] = float(loop.guard.out_um[0])
            taken["pred"] = float(loop.pred_um[0])
            taken["word"] = loop.word
            taken["now"] = now

    app.loop.observers.append(take)
    app.run()
    snap = taken["snap"]
    text = json.dumps(snap, allow_nan=False)  # NaN would not be JSON
    assert json.loads(text) == snap
    z = snap["axes"]["z"]
    assert z["state"] == "normal" and z["policy"] == "hold" and z["enable"] is True
    assert z["correction_um"] == taken["out"] and z["correction_um"] < -1.0
    assert z["prediction_um"] == taken["pred"]
    assert z["word_byte"] == "high" and z["byte"] == f"0x{taken['word'] >> 8:02X}"
    assert snap["word"] == f"0x{taken['word']:04X}"
    assert snap["model"]["kind"] == "xi_spindle"
    sig = snap["signals"]["T_xi"]
    assert sig["quality"] == "good" and sig["age_s"] >= 0 and sig["value"] > 20
    assert snap["loop"]["cycles"] == 3000
    assert snap["uptime_s"] == pytest.approx(taken["now"] - app.loop.t_start_s)


def test_numpy_percentiles_match_the_loops_own():
    st = TimingStats(0.002)
    rng = np.random.default_rng(1)
    for late in rng.exponential(40e-6, 5000):
        st.record(float(late), int(rng.integers(10_000, 90_000)))
    mine = timing(st)
    theirs = st.as_dict()
    assert mine["lateness_us"] == theirs["lateness_us"]
    assert mine["cycle_compute_us"] == theirs["cycle_compute_us"]


def test_nan_becomes_null_and_an_empty_histogram_reads_zero():
    from compd.service.status import jsonable

    lt = timing(TimingStats(0.002))["lateness_us"]
    assert lt == {"p50": 0.0, "p99": 0.0, "p999": 0.0, "max": 0.0}
    assert jsonable({"a": [float("nan"), np.float64(2.0)]}) == {"a": [None, 2.0]}


def test_write_atomic_and_read_back(tmp_path, ran_app):
    path = tmp_path / "status.json"
    snap = snapshot(ran_app.loop, state="running", observe=True)
    write_atomic(path, snap)
    assert oct(path.stat().st_mode & 0o777) == "0o644"
    assert read_status(path) == snap
    assert os.listdir(tmp_path).count("status.json") == 1 and len(os.listdir(tmp_path)) == 2  # + sim.yaml


def test_read_status_errors(tmp_path):
    with pytest.raises(BadInput, match="no status file"):
        read_status(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(BadInput, match="not a status file"):
        read_status(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text('{"hello": 1}')
    with pytest.raises(BadInput, match="schema"):
        read_status(tmp_path / "other.json")


def test_liveness():
    now = 1000.0
    base = {"pid": os.getpid(), "state": "running", "written_unix_s": now - 1, "status_period_s": 1.0}
    assert liveness(base, now) == (True, "running")
    assert liveness({**base, "written_unix_s": now - 60}, now)[1].startswith("stale")
    assert liveness({**base, "state": "stopped"}, now)[1].startswith("stopped")
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    alive, why = liveness({**base, "pid": child.pid}, now)
    assert not alive and "is gone" in why


def test_a_stale_cycle_is_not_alive_but_held_and_a_reload_is_alive():
    now = 1000.0
    base = {
        "pid": os.getpid(),
        "state": "running",
        "written_unix_s": now - 0.5,
        "status_period_s": 1.0,
        "record_age_s": 0.01,
        "stale_after_s": 1.0,
    }
    alive, why = liveness({**base, "state": "stale", "record_age_s": 3.25}, now)
    assert not alive and why.startswith("stale: the cycle has not run for 3.2 s")
    assert held({**base, "state": "stale"}, now)  # its process and service are there: the file is not free
    assert not held({**base, "written_unix_s": now - 60}, now)
    assert liveness({**base, "state": "reloading", "record_age_s": 2.0}, now) == (
        True,
        "reloading (the loop paused 2.0 s ago)",
    )
    assert stale_after_s(0.002, "running") == STALE_MIN_S and stale_after_s(0.5, "running") == 2.5
    assert stale_after_s(0.002, "reloading") > 10.0
    assert stale_after_s(0.002, "stopping") is None and stale_after_s(0.002, "stopped") is None


def test_mark_stale_keeps_what_each_axis_last_said():
    snap = {
        "state": "running",
        "observe": False,
        "axes": {"z": {"state": "normal", "enable": True, "contributions": {"spindle": {"state": "fault"}}}},
    }
    mark_stale(snap)
    z = snap["axes"]["z"]
    assert snap["state"] == "stale" and z["state"] == "stale" and z["last_state"] == "normal"
    assert z["enable"] is None  # not confirmed at the machine
    assert z["contributions"]["spindle"] == {"state": "stale", "last_state": "fault"}
    observed = {"state": "running", "observe": True, "axes": {"z": {"state": "normal", "enable": False}}}
    mark_stale(observed)
    assert observed["axes"]["z"]["enable"] is False  # observe mode: the word at the machine is 0


def test_render_shows_axes_signals_and_loop(ran_app):
    snap = snapshot(ran_app.loop, state="running", observe=True)
    text = render(snap, True, "running")
    assert "OBSERVE MODE" in text
    assert "lateness p50" in text and "missed" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("z "))
    assert "normal" in line and "hold" in line
    assert any(ln.startswith("T_xi ") and "good" in ln for ln in text.splitlines())


def test_cli_status_exit_codes(tmp_path, ran_app, capsys):
    path = tmp_path / "status.json"
    snap = snapshot(ran_app.loop, state="running", observe=False)
    write_atomic(path, {**snap, "status_period_s": 1.0, "written_unix_s": time.time()})
    assert main(["status", "--status", str(path)]) == 0
    assert "compd running" in capsys.readouterr().out
    assert main(["status", "--status", str(path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["alive"] is True and data["axes"]["z"]["state"] == "normal"
    write_atomic(path, {**snap, "state": "stopped"})
    assert main(["status", "--status", str(path)]) == 1
    assert "stopped" in capsys.readouterr().err
    assert main(["status", "--status", str(tmp_path / "missing.json")]) == 2


def test_cli_status_finds_the_file_from_the_config(tmp_path, ran_app, capsys):
    cfg = sim_config(tmp_path, "status: {path: here.json}")
    write_atomic(tmp_path / "here.json", {**snapshot(ran_app.loop, state="running", observe=False)})
    assert main(["status", "--config", str(cfg), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "running"


def test_a_sink_that_cannot_reach_the_machine_is_shown_down_and_not_enabled(tmp_path):
    """A fanuc_pmc sink pointed at a port nothing listens on: the guard enables the axis,
    but status, render and metrics say the link is down and the axis is not enabled."""
    import socket

    from compd.service.metrics import SnapshotCollector

    with socket.socket() as s:  # a free port, closed again: connections are refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = sim_config(tmp_path, duration_s=600)
    cfg.write_text(
        cfg.read_text().replace(
            "sink: {kind: pci1756}", f"sink: {{kind: fanuc_pmc, host: 127.0.0.1, port: {port}, timeout_s: 0.1}}"
        )
    )
    app = App(load_config(cfg))
    app.open()
    try:
        deadline = time.monotonic() + 30
        while app.sink.link_state() != "down":
            assert time.monotonic() < deadline, app.sink.link_state()
            app.loop.run(max_cycles=50)
            time.sleep(0.05)
        app.loop.run(max_cycles=500)
        snap = snapshot(app.loop, state="running", observe=False)
        guard_enable = bool(app.guard.enable[0])
    finally:
        app.close()
    assert guard_enable  # the guard did enable the axis …
    assert snap["sink"]["link"] == "down"
    z = snap["axes"]["z"]
    # … but it is not confirmed at the machine: neither on nor off, and nothing read back counts
    assert z["enable"] is None and z["guard_enable"] is True and z["applied_um"] is None
    text = render(snap, True, "running")
    assert "link DOWN" in text and "NOT REACHING THE MACHINE" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("z "))
    assert " unknown " in line
    col = SnapshotCollector()
    col.update(snap, [], 0, 0.0)
    fams = {f.name: f for f in col.collect()}
    assert fams["compd_sink_link_up"].samples[0].value == 0.0
    assert math.isnan(fams["compd_axis_enabled"].samples[0].value)  # not confirmed at the machine
    down = [s for s in fams["compd_sink_link"].samples if s.labels["state"] == "down"]
    assert down[0].value == 1.0


def test_an_in_process_sink_is_up():
    from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink

    sink = Pci1756Sink(Pci1756Config(kind="pci1756"))
    assert sink.link_state() == "up" and sink.get_status()["link"] == "up"
