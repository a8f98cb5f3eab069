"""The daemon around the loop: status thread, observe mode, event log lines, real-time options."""

from __future__ import annotations

import json
import logging
import os
import threading
import time

import numpy as np

from compd.config import load_config
from compd.core.config import RealtimeConfig
from compd.cycle.publish import Tail
from compd.cycle.realtime import apply_realtime
from compd.daemon.app import App
from compd.service.logsetup import KeyValueFormatter
from compd.service.status import status_path
from tests.service_helpers import fault_config, sim_config


def _wait_for(pred, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def test_status_file_is_written_while_running_and_marked_stopped_at_the_end(tmp_path):
    # 1800 cycles paced over 1.5 s of wall time: some 30 snapshots at 0.05 s
    cfg = load_config(sim_config(tmp_path, "status: {path: st/status.json, period_s: 0.05}", speedup=1200))
    (tmp_path / "st").mkdir()
    app = App(cfg)
    seen: dict = {}

    def peek(loop, now):  # while it runs: has the service written a snapshot of a running loop?
        if seen:
            return
        try:
            data = json.loads((tmp_path / "st" / "status.json").read_text())
        except (OSError, ValueError):
            return
        if data["state"] == "running" and data["loop"]["cycles"] > 0:
            seen.update(data)

    app.loop.observers.append(peek)
    app.run()
    assert seen, "no running snapshot was written during the run"
    assert seen["pid"] == os.getpid() and seen["observe"] is False
    assert set(seen["axes"]["z"]) >= {"correction_um", "state", "policy", "enable", "prediction_um"}
    assert set(seen["signals"]["T_xi"]) == {"value", "quality", "stamp_s", "age_s"}
    assert set(seen["loop"]["lateness_us"]) == {"p50", "p99", "p999", "max"}
    final = json.loads((tmp_path / "st" / "status.json").read_text())
    assert final["state"] == "stopped"
    assert final["loop"]["cycles"] == app.loop.stats.cycles
    assert not list((tmp_path / "st").glob(".*.tmp")), "temp file left behind"


def test_status_path_defaults():
    class Top:
        class status:  # noqa: N801
            path = None

    class Cfg:
        top = Top

    assert status_path(Cfg, env={}) is None
    assert str(status_path(Cfg, env={"RUNTIME_DIRECTORY": "/run/compd/a:/run/other"})) == "/run/compd/a/status.json"


def test_observe_mode_holds_the_output_disabled(tmp_path):
    cfg = load_config(sim_config(tmp_path, "observe: true"))
    app = App(cfg)
    card = app.sink.inner.card
    words, card_words = [], []

    def watch(loop, now):
        words.append(loop.word)
        card_words.append(card.read_do_word(0))

    app.loop.observers.append(watch)
    result = app.run()
    assert result["observe"] is True
    assert max(words) > 0, "the loop computed no correction to hold back"
    assert set(card_words) == {0}
    comp = result["compensation"]["z"]
    assert comp["rms_before_um"] > 1.0
    assert comp["rms_after_um"] == comp["rms_before_um"]
    assert app.sink.get_status()["observe"] is True
    # the heartbeat bit keeps toggling: the PLC still sees compd alive (every scheduled
    # cycle, plus the loop's one priming cycle before the schedule starts)
    assert app.sink.inner.writes == app.loop.stats.cycles + 1


def test_observe_flag_overrides_the_config(tmp_path):
    cfg = load_config(sim_config(tmp_path, "observe: true"))
    assert App(cfg, observe=False).observe is False
    cfg = load_config(sim_config(tmp_path))
    assert App(cfg, observe=True).observe is True


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_guard_events_become_one_log_line_each_and_no_line_per_cycle(tmp_path):
    handler = _Collect()
    logger = logging.getLogger("compd")
    old = logger.level
    logger.setLevel(logging.INFO)
    logger.addHandler(handler)
    try:
        app = App(load_config(fault_config(tmp_path)))
        app.run()
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)
    events = [getattr(r, "event", None) for r in handler.records]
    assert events[0] == "start" and events[-1] == "stop"
    assert events.count("sensor_bad") == 1 and events.count("sensor_good") == 1
    assert events.count("axis_fault") == 1 and events.count("axis_normal") == 1
    bad = next(r for r in handler.records if getattr(r, "event", None) == "sensor_bad")
    assert bad.levelno == logging.WARNING and bad.sensor == "T_xi" and bad.reason == "out_of_range"
    assert 200 <= bad.t_s < 210
    fault = next(r for r in handler.records if getattr(r, "event", None) == "axis_fault")
    assert fault.axis == "z"
    assert app.loop.stats.cycles > 900
    assert len(handler.records) < 20
    line = KeyValueFormatter().format(bad)
    assert "\n" not in line and "level=warning event=sensor_bad" in line and "sensor=T_xi" in line


def test_the_publishers_tail_of_the_guards_events_survives_the_guards_trimming():
    events = [(float(i), "T", "bad", "stale") for i in range(3)]
    box = [events]
    tail = Tail(lambda: box[0])
    assert len(tail.new()) == 3
    assert tail.new() == []
    events.append((3.0, "T", "good", "recovered"))
    del events[:2]  # the guard trims old events
    assert tail.new() == [(3.0, "T", "good", "recovered")]
    box[0] = [(9.0, "z", "fault", "input bad")]  # everything seen was trimmed away
    assert tail.new() == [(9.0, "z", "fault", "input bad")]


def test_realtime_options_apply_to_the_calling_thread_only():
    cpus = sorted(os.sched_getaffinity(0))
    out: dict = {}

    def worker():
        cfg = RealtimeConfig(scheduler="fifo", priority=10, cpu_affinity=[cpus[0]])
        out["done"] = apply_realtime(cfg)
        out["policy"] = os.sched_getscheduler(0)
        out["affinity"] = os.sched_getaffinity(0)
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert os.sched_getaffinity(0) == set(cpus)
    assert out["affinity"] == {cpus[0]}
    fifo = [flag for flag, what in out["done"] if "SCHED_FIFO" in what]
    assert fifo == [out["policy"] == os.SCHED_FIFO]  # applied, or reported as refused
    assert apply_realtime(RealtimeConfig()) == []


def test_plain_app_has_no_status_file_or_metrics(tmp_path):
    app = App(load_config(sim_config(tmp_path, duration_s=60)))
    assert app.service.path is None and app.service.metrics is None
    app.run()
    assert np.isfinite(app.loop.pred_um).all()
