"""Benchmark (make bench only): each machine simulates a 24 h day at 1 s steps in a few seconds."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from hil_sim.logcmd import load_plant

SCENARIOS = Path(__file__).resolve().parents[2] / "hil_sim" / "scenarios"


@pytest.mark.bench
@pytest.mark.parametrize("machine", ["lathe", "spindle", "gantry", "feed_axis"])
def test_a_day_in_a_few_seconds(machine):
    plant = load_plant(str(SCENARIOS / f"{machine}_train.yaml"))
    t0 = time.perf_counter()
    rows = plant.record(np.arange(0.0, 86400.0 + 1e-9, 1.0))
    elapsed_s = time.perf_counter() - t0
    print(f"{machine}: 24 h in {elapsed_s:.2f} s")
    assert rows.shape[0] == 86401
    assert elapsed_s < 10.0
