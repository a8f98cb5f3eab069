"""One before/after score: the streamed (daemon) and the batch (replay, residual logs) forms agree."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compd.core.scoring import RunningScore, score_applied, score_residual


def test_a_hand_computed_axis() -> None:
    err = np.array([3.0, -4.0, math.nan, 0.0])
    applied = np.array([-2.0, 3.0, -1.0, 1.0])  # residual 1, -1, (skipped), 1
    r = score_applied(err, applied)
    assert r["rows"] == 3
    assert r["rms_before_um"] == pytest.approx(math.sqrt(25.0 / 3))
    assert r["rms_after_um"] == pytest.approx(1.0)
    assert r["max_abs_before_um"] == 4.0 and r["max_abs_after_um"] == 1.0
    assert r["reduction_pct"] == pytest.approx(100.0 * (1.0 - 1.0 / math.sqrt(25.0 / 3)))


def test_no_samples_scores_zero_not_nan() -> None:
    r = score_residual(np.array([math.nan]), np.array([1.0]))
    assert r == {
        "rows": 0,
        "rms_before_um": 0.0,
        "rms_after_um": 0.0,
        "max_abs_before_um": 0.0,
        "max_abs_after_um": 0.0,
        "reduction_pct": 0.0,
    }


values = st.one_of(st.floats(-50, 50, allow_nan=False), st.just(math.nan))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(values, values), min_size=0, max_size=60))
def test_streamed_and_batch_scores_agree(samples: list[tuple[float, float]]) -> None:
    run = RunningScore(1)
    for e, a in samples:
        run.add(0, e, a)
    err = np.array([s[0] for s in samples], dtype=float)
    app = np.array([s[1] for s in samples], dtype=float)
    batch = score_applied(err, app)
    streamed = run.result(0)
    assert streamed["rows"] == batch["rows"]
    for key in ("rms_before_um", "rms_after_um", "max_abs_before_um", "max_abs_after_um", "reduction_pct"):
        assert streamed[key] == pytest.approx(batch[key], rel=1e-9, abs=1e-9)
