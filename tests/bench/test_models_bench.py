"""Benchmarks (make bench only): model evaluation cost and the LVR fit with exact LOO Q² or blocked cross-validation."""

from __future__ import annotations

import time

import numpy as np
import pytest

from compd.identify.lvr import equal_blocks, select_blocked, select_components
from rig.bench_models import model_eval_us

pytestmark = pytest.mark.bench

LIMIT_US = {"lvr": 10.0, "xi_spindle": 10.0, "ar1": 10.0, "mlr": 10.0, "feed_axis": 50.0}


def test_model_eval_us():
    got = model_eval_us()
    print("model_eval_us", got)
    assert set(got) == set(LIMIT_US)
    for kind, limit in LIMIT_US.items():
        assert got[kind] <= limit, (kind, got[kind])


def test_lvr_fit_with_exact_loo_3100x19():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(3100, 19)).cumsum(axis=0)
    Y = X @ rng.normal(size=(19, 2)) + rng.normal(size=(3100, 2))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        select_components(X, Y, 10)
        best = min(best, time.perf_counter() - t0)
    print(f"lvr fit + LOO Q2, 3100 x 19, 10 components: {best:.3f} s")
    assert best <= 0.5


def test_lvr_blocked_selection_10000x19():
    # a 1 Hz log of 2.8 h, 19 sensors, 2 axes: 5 held-out stretches × a 10-component fit each
    rng = np.random.default_rng(0)
    X = rng.normal(size=(10_000, 19)).cumsum(axis=0)
    Y = X @ rng.normal(size=(19, 2)) + rng.normal(size=(10_000, 2))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        select_blocked(X, Y, 10, equal_blocks(10_000, 5), 300)
        best = min(best, time.perf_counter() - t0)
    print(f"lvr blocked selection, 10000 x 19, 5 blocks, 10 components: {best:.3f} s")
    assert best <= 0.5
