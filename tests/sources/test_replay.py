"""Replay source: the last row at or before the loop time, NO_DATA for empty cells."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from compd.core.config import SourceConfig  # noqa: F401  (import check)
from compd.core.frame import Frame, Quality
from compd.sources.replay import ReplayConfig, ReplaySource


def test_replay_publishes_latest_row(tmp_path: Path) -> None:
    p = tmp_path / "log.csv"
    p.write_text("t_s,T1,T2\n10,20.0,21.0\n20,20.5,\n30,21.0,22.0\n")
    src = ReplaySource(ReplayConfig(kind="replay", name="log", path=str(p)))
    frame = Frame(src.signal_names())
    src.bind(frame)
    assert src.start_s == 10 and src.end_s == 30
    src.read(frame, 5.0)
    assert (frame.quality == Quality.NO_DATA).all()
    src.read(frame, 25.0)
    assert frame.values[0] == 20.5
    assert frame.quality.tolist() == [Quality.GOOD, Quality.NO_DATA]
    assert frame.stamp_s[0] == 20.0
    src.read(frame, 100.0)
    np.testing.assert_array_equal(frame.values, [21.0, 22.0])
