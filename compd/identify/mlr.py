"""Identification of the MLR baseline: ordinary least squares of the error on temperature rises."""

from __future__ import annotations

from typing import Any

import numpy as np

from compd.core.config import Strict
from compd.identify.data import (
    FitResult,
    axis_names,
    check_not_constant,
    columns,
    default_inputs,
    default_targets,
    measured_rows,
    require_rows,
    target_columns,
    validate_options,
)
from compd.log import Log
from compd.models.mlr import MLR, RiseLinearParams


def rise_stats(R: np.ndarray) -> dict[str, Any]:
    """Mean and covariance of the rises (what degraded mode needs), as params."""
    cov = np.atleast_2d(np.cov(R, rowvar=False)) if R.shape[0] > 1 else np.zeros((R.shape[1],) * 2)
    return {"rise_mean_k": R.mean(axis=0).tolist(), "rise_cov_k2": cov.tolist()}


def rises(X: np.ndarray) -> np.ndarray:
    """Temperature rises: each row minus the first row (the reading at start)."""
    return X - X[0]


def linear_data(
    log: Log, inputs: list[str] | None, targets: list[str] | None
) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """Inputs, targets, X (raw readings) and Y for a rise model; NaN and constant inputs refused,
    Y NaN where the error was not measured (compd.identify.data.target_columns)."""
    inputs = default_inputs(log, inputs)
    targets = default_targets(log, targets)
    X = columns(log, inputs)
    Y = target_columns(log, targets)
    check_not_constant(log, X, inputs)
    return inputs, targets, X, Y


class Options(Strict):
    """`compd fit --kind mlr` takes no options beyond inputs and targets."""


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """Ordinary least squares of E on [1, T − T(first row)], over the rows with the error measured."""
    validate_options("mlr", Options, options)
    inputs, targets, X, Y = linear_data(log, inputs, targets)
    ok = measured_rows(Y)
    require_rows(log, int(ok.sum()), len(inputs) + 2, f"mlr with {len(inputs)} inputs")
    model = fit_mlr_model(inputs, axis_names(targets), X, Y)
    return FitResult(model, {"rank": int(np.linalg.matrix_rank(rises(X)[ok]))})


def fit_mlr_model(inputs: list[str], axes: list[str], X: np.ndarray, Y: np.ndarray) -> MLR:
    """The MLR model of Y on the rises of X from its first row (used as the baseline by every
    report); rows where a target is NaN do not enter the least squares."""
    ok = measured_rows(Y)
    R = rises(X)[ok]
    A = np.hstack([np.ones((R.shape[0], 1)), R])
    sol, *_ = np.linalg.lstsq(A, Y[ok], rcond=None)
    params = RiseLinearParams(coef_um_per_k=sol[1:].tolist(), intercept_um=sol[0].tolist(), t0_c=None, **rise_stats(R))
    return MLR(params, inputs, axes)


def choices(result: FitResult) -> dict[str, Any]:
    """Nothing beyond its coefficients."""
    return {}
