"""Before a signal's first sample is not a fault: no `sensor_bad no_data` at every start, but a
signal that never arrives within its staleness limit is one (the event log of a short run)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from compd.cli import main
from compd.core.config import GuardConfig
from compd.core.frame import Frame, Quality
from compd.cycle.guard import Guard
from compd.log import write_log

CONFIG = """\
loop: {clock: sim, period_s: 0.5}
sources:
  - {kind: replay, name: log, path: day.csv}
model:
  kind: xi_spindle
  inputs: [T_xi]
  outputs: [z]
  params: {alpha_per_k: 13.6e-6, length_mm: 165.0}
guard: {max_slew_um_per_s: 2.0, stale_after_s: 5.0}
sink: {kind: pci1756}
"""


def _run(tmp_path: Path, first_sample_s: float, caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    t = np.arange(0.0, 30.0, 0.5)
    T = np.where(t < first_sample_s, np.nan, 20.0 + 0.01 * t)  # blank cells read no_data
    write_log(tmp_path / "day.csv", ["t_s", "T_xi"], np.column_stack([t, T]))
    (tmp_path / "c.yaml").write_text(CONFIG)
    with caplog.at_level(logging.DEBUG, logger="compd"):
        assert main(["run", str(tmp_path / "c.yaml"), "--duration", "25"]) == 0
    return [r for r in caplog.records if r.name.startswith("compd")]


def test_first_sample_after_start_is_no_fault(tmp_path, caplog, capsys):
    records = _run(tmp_path, 2.0, caplog)  # 2 s without a sample, the limit is 5 s
    events = [getattr(r, "event", None) for r in records]
    assert "start" in events and "stop" in events  # the run was logged
    assert not [r for r in records if r.levelno >= logging.WARNING], [r.getMessage() for r in records]
    assert "sensor_bad" not in events and "sensor_good" not in events


def test_signal_that_never_arrives_in_time_is_a_fault(tmp_path, caplog, capsys):
    records = _run(tmp_path, 12.0, caplog)  # no sample for 12 s: bad after its 5 s
    bad = [r for r in records if getattr(r, "event", None) == "sensor_bad"]
    assert len(bad) == 1 and bad[0].levelno == logging.WARNING
    assert bad[0].reason == "no_data" and bad[0].sensor == "T_xi"
    assert 5.0 < bad[0].t_s <= 6.0  # once its staleness limit has passed since start
    good = [r for r in records if getattr(r, "event", None) == "sensor_good"]
    assert len(good) == 1 and 12.0 <= good[0].t_s <= 12.5


def test_guard_waits_per_input_then_reports():
    frame = Frame(["A", "B"])
    g = Guard(GuardConfig(stale_after_s=1.0), ["z"], frame, ["A", "B"])
    for k in range(30):  # A samples from 0.3 s, B never
        t = 0.1 * k
        if t >= 0.3:
            frame.set(0, 20.0, Quality.GOOD, t)
        assert not g.check_inputs(frame, t)
    assert [e[1:] for e in g.events] == [("B", "bad", "no_data")]
    assert g.events[0][0] == pytest.approx(1.1)
    assert g.faults == {"bad:no_data": 1}
