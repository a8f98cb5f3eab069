"""Before/after scoring of compensation: RMS and worst error without and with the correction.

One formula for every report that compares an axis's thermal error with what is
left once the machine applies compd's correction: `compd run`'s summary (streamed
cycle by cycle), `compd replay`'s report and the closed-loop residual logs.
The residual is the error plus the applied correction (a correction is minus the
predicted error); only samples where both are known count.
"""

from __future__ import annotations

import math

import numpy as np


def axis_score(
    rows: int, sum_sq_before: float, sum_sq_after: float, max_abs_before_um: float, max_abs_after_um: float
) -> dict[str, float]:
    """The report entry of one axis from its sums: `rows` samples, sums of squared µm."""
    before = math.sqrt(sum_sq_before / rows) if rows else 0.0
    after = math.sqrt(sum_sq_after / rows) if rows else 0.0
    return {
        "rows": int(rows),
        "rms_before_um": before,
        "rms_after_um": after,
        "max_abs_before_um": float(max_abs_before_um),
        "max_abs_after_um": float(max_abs_after_um),
        "reduction_pct": 100.0 * (1.0 - after / before) if before > 0 else 0.0,
    }


def score_residual(error_um: np.ndarray, residual_um: np.ndarray) -> dict[str, float]:
    """Score one axis from its error and residual series (samples where both are finite)."""
    error_um = np.asarray(error_um, dtype=float)
    residual_um = np.asarray(residual_um, dtype=float)
    ok = np.isfinite(error_um) & np.isfinite(residual_um)
    e, r = error_um[ok], residual_um[ok]
    return axis_score(
        int(e.size),
        float(np.dot(e, e)),
        float(np.dot(r, r)),
        float(np.max(np.abs(e))) if e.size else 0.0,
        float(np.max(np.abs(r))) if r.size else 0.0,
    )


def score_applied(error_um: np.ndarray, applied_um: np.ndarray) -> dict[str, float]:
    """Score one axis from its error and the correction the machine applied (residual = sum)."""
    error_um = np.asarray(error_um, dtype=float)
    return score_residual(error_um, error_um + np.asarray(applied_um, dtype=float))


class RunningScore:
    """The same score accumulated one sample at a time (the daemon's cycle), no allocation."""

    def __init__(self, n_axes: int) -> None:
        self.rows = np.zeros(n_axes, dtype=np.int64)
        self.sum_before = np.zeros(n_axes)
        self.sum_after = np.zeros(n_axes)
        self.max_before = np.zeros(n_axes)
        self.max_after = np.zeros(n_axes)

    def add(self, axis: int, error_um: float, applied_um: float) -> None:
        """One sample of an axis; skipped unless both values are finite."""
        if not (math.isfinite(error_um) and math.isfinite(applied_um)):
            return
        r = error_um + applied_um
        self.rows[axis] += 1
        self.sum_before[axis] += error_um * error_um
        self.sum_after[axis] += r * r
        if abs(error_um) > self.max_before[axis]:
            self.max_before[axis] = abs(error_um)
        if abs(r) > self.max_after[axis]:
            self.max_after[axis] = abs(r)

    def result(self, axis: int) -> dict[str, float]:
        """The report entry of `axis` so far."""
        return axis_score(
            int(self.rows[axis]),
            float(self.sum_before[axis]),
            float(self.sum_after[axis]),
            float(self.max_before[axis]),
            float(self.max_after[axis]),
        )
