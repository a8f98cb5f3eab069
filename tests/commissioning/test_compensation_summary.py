"""compd's own compensation count skips cycles where the true error is not known yet (NaN)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from compd.daemon.app import CompensationSummary


def test_nan_true_error_is_skipped_not_propagated() -> None:
    frame = SimpleNamespace(index={"err_y_um": 0}, values=np.array([math.nan]))
    loop = SimpleNamespace(model=SimpleNamespace(outputs=["y"]), frame=frame, applied=lambda: np.array([-1.0]))
    s = CompensationSummary(loop)
    s(loop, 0.0)  # before the first sample of the error arrives
    for e in (2.0, 2.0):
        frame.values[0] = e
        s(loop, 1.0)
    r = s.result(["y"])["y"]
    assert r["rms_before_um"] == 2.0 and r["rms_after_um"] == 1.0
    assert r["reduction_pct"] == 50.0
