"""Identification of the ξ-point spindle model: the ξ-point search on a profile and the fit (paper 003)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from compd.config import Strict
from compd.errors import BadInput
from compd.identify.data import (
    FitResult,
    axis_names,
    columns,
    default_targets,
    require_rows,
    validate_options,
)
from compd.log import Log
from compd.models.base import MAX_LENGTH_MM
from compd.models.xi_spindle import RadialParams, XiSpindle, XiSpindleParams


def find_xi(x_mm: np.ndarray, t_c: np.ndarray) -> float:
    """The mean-value point ξ of a profile T(x): where T equals its length average.

    The mean uses the trapezoid rule; among crossings the one nearest the middle of
    the profile's warmest half is not guessed: the first crossing from the warm end
    (x = x[0] being the heated end in paper 003's convention, nose at 0) is returned,
    linearly interpolated. Raises BadInput if the profile is constant or unsorted.
    """
    x = np.asarray(x_mm, dtype=float)
    t = np.asarray(t_c, dtype=float)
    if x.ndim != 1 or x.shape != t.shape or x.size < 2:
        raise BadInput("a profile needs at least two (x, T) points of equal count")
    if np.any(np.diff(x) <= 0):
        raise BadInput("profile positions must be strictly increasing")
    if not np.all(np.isfinite(t)):
        raise BadInput("profile temperatures must be finite")
    mean = np.trapezoid(t, x) / (x[-1] - x[0])
    d = t - mean
    if np.allclose(d, 0.0):
        raise BadInput("the profile is constant: every point is a mean-value point")
    for i in range(x.size - 1):
        if d[i] == 0.0:
            return float(x[i])
        if d[i] * d[i + 1] < 0:
            return float(x[i] - d[i] * (x[i + 1] - x[i]) / (d[i + 1] - d[i]))
    return float(x[-1])


class Options(Strict):
    """`compd fit --kind xi_spindle --option KEY=VALUE`: the axial gain α L is fitted."""

    alpha_per_k: float = Field(13.6e-6, gt=0, lt=1e-3, description="α; the fit reports L = gain/α")
    xi_mm: float | None = Field(None, ge=0, description="where the sensor sits (kept in the file)")
    inner_sensors: int = Field(
        0, ge=0, le=2, description="radial fit: inner-ring sensors after the ξ sensor (0: ring at T_xi)"
    )
    outer_sensors: int = Field(1, ge=1, le=2, description="radial fit: outer-ring sensors")
    ring_alpha_per_k: float | None = Field(
        None, gt=0, lt=1e-3, description="radial fit: bearing steel α; none = the radial params' default"
    )
    clearance: bool = Field(True, description="radial fit: add the preload-loss clearance c(ΔL)")


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """Axial gain α L by least squares through the origin on the ξ sensor's rise.

    With two targets (axial, radial) the radial output is added: the rings' geometry
    is the paper's (7010 CETA), the ring temperatures come from the inputs after the
    ξ sensor ([inner ring sensors], outer ring sensors, [speed]), and only the
    centrifugal lift k (µm/rpm²) is fitted, by least squares on what u + c leaves,
    when the last input is the spindle speed.
    """
    opt = validate_options("xi_spindle", Options, options)
    targets = default_targets(log, targets)
    if len(targets) not in (1, 2):
        raise BadInput(
            f"xi_spindle fits the axial axis, or axial and radial; targets: {', '.join(targets)}",
            path="--target",
        )
    radial = len(targets) == 2
    inputs = _inputs(log, opt, inputs, radial)
    X = columns(log, inputs)
    E = columns(log, targets)
    gain, length = _axial_gain(log, opt, X[:, 0], E[:, 0], inputs[0])
    report: dict[str, Any] = {"gain_um_per_k": gain, "length_mm": length}
    rad = None
    if radial:
        given = {"alpha_per_k": opt.ring_alpha_per_k} if opt.ring_alpha_per_k is not None else {}
        rad = RadialParams(
            inner_sensors=opt.inner_sensors, outer_sensors=opt.outer_sensors, clearance=opt.clearance, **given
        )
        if len(inputs) == 2 + opt.inner_sensors + opt.outer_sensors:
            probe = XiSpindle(
                XiSpindleParams(
                    alpha_per_k=opt.alpha_per_k, length_mm=length,
                    radial=rad.model_copy(update={"k_um_per_rpm2": 0.0}),
                ),
                list(inputs), axis_names(targets),
            )
            left = E[:, 1] - probe.predict(X, np.zeros(X.shape[0]))[:, 1]
            rad = rad.model_copy(update={"k_um_per_rpm2": _fit_lift(left, X[:, -1], log, inputs[-1])})
            report["k_um_per_rpm2"] = rad.k_um_per_rpm2
    params = XiSpindleParams(
        alpha_per_k=opt.alpha_per_k, length_mm=length, t0_c=None, xi_mm=opt.xi_mm, radial=rad
    )
    model = XiSpindle(params, list(inputs), axis_names(targets))
    return FitResult(model, report)


def _inputs(log: Log, opt: Options, inputs: list[str] | None, radial: bool) -> list[str]:
    """The ξ sensor (the log's one temperature column when none is named), then for a radial
    fit the ring sensors and optionally the speed; BadInput for any other count."""
    rings = opt.inner_sensors + opt.outer_sensors
    if not inputs:
        temps = log.temperature_columns()
        if radial or len(temps) != 1:
            raise BadInput(
                "name the ξ sensor" + (" and the ring sensors" if radial else "")
                + f" with --inputs (the log has {len(temps)} temperature columns)",
                file=log.file, path="--inputs",
            )
        inputs = temps
    if not radial and len(inputs) != 1:
        raise BadInput(f"xi_spindle takes one input (the ξ sensor), got {len(inputs)}", path="--inputs")
    if radial and len(inputs) not in (1 + rings, 2 + rings):
        raise BadInput(
            f"a radial fit takes the ξ sensor, {opt.inner_sensors} inner-ring and {opt.outer_sensors} "
            f"outer-ring sensor(s), then optionally the speed: {1 + rings} or {2 + rings} inputs, "
            f"got {len(inputs)}", path="--inputs",
        )
    return inputs


def _axial_gain(log: Log, opt: Options, x: np.ndarray, e: np.ndarray, name: str) -> tuple[float, float]:
    """(gain α L µm/K, L mm): the gain by least squares through the origin of the error on the ξ sensor's rise."""
    require_rows(log, x.size, 3, "xi_spindle")
    rise = x - x[0]
    ss = float(rise @ rise)
    if ss == 0.0:
        raise BadInput("the ξ sensor never changes", file=log.file, path=name)
    gain = float(rise @ e) / ss
    if gain <= 0:
        raise BadInput(
            f"the error falls as {name} rises (gain {gain:.3g} µm/K): not a ξ sensor", file=log.file, path=name,
        )
    length = gain / (opt.alpha_per_k * 1000.0)
    if length > MAX_LENGTH_MM:
        raise BadInput(
            f"the gain {gain:.3g} µm/K means a spindle {length / 1000:.3g} m long at α = {opt.alpha_per_k:g}:"
            " not a ξ sensor", file=log.file, path=name,
        )
    return gain, length


def _fit_lift(left_um: np.ndarray, speed_rpm: np.ndarray, log: Log, name: str) -> float:
    """Centrifugal lift k (µm/rpm², ≥ 0): least squares of k n² on the radial error u + c leaves."""
    n2 = speed_rpm**2
    n4 = float(n2 @ n2)
    if n4 == 0.0:
        raise BadInput("the speed input is 0 throughout: the lift k cannot be fitted", file=log.file, path=name)
    return max(0.0, float(left_um @ n2) / n4)
