"""Identification of the ξ-point spindle model: the ξ-point search on a profile and the fit (paper 003)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field
from scipy import optimize

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.identify import holdout
from compd.identify.data import (
    FitResult,
    axis_names,
    columns,
    default_targets,
    measured_rows,
    require_rows,
    target_columns,
    validate_options,
)
from compd.log import Log
from compd.models.base import MAX_LENGTH_MM
from compd.models.xi_spindle import LiftParams, RadialParams, XiSpindle, XiSpindleParams


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
    speed_input: str = Field(
        "speed_rpm",
        min_length=1,
        description="the input recognised as the spindle speed (rpm): when --inputs names it, the lift k is fitted",
    )
    inner_sensors: int = Field(
        0, ge=0, le=2, description="radial fit: inner-ring sensors after the ξ sensor (0: ring at T_xi)"
    )
    outer_sensors: int = Field(1, ge=1, le=2, description="radial fit: outer-ring sensors")
    ring_alpha_per_k: float | None = Field(
        None, gt=0, lt=1e-3, description="radial fit: bearing steel α; none = the radial params' default"
    )
    clearance: bool = Field(True, description="radial fit: add the preload-loss clearance c(ΔL)")
    xi_sensor: str | None = Field(
        None,
        min_length=1,
        description="the ξ sensor when --inputs names none (none: the temperature column that predicts the held-out"
        " folds best; the lag search holds the one chosen)",
    )
    ring_gains: bool = Field(
        True,
        description="radial fit: fit a gain on each ring's term (compd's form); false = paper 003's u_C − u_B + c"
        " with nothing fitted",
    )


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """Axial gain α L by least squares through the origin on the ξ sensor's rise.

    When --inputs names the speed (`speed_input`, default the log's `speed_rpm` column),
    the centrifugal lift k (µm/rpm²) is fitted with the gain on the axial error, where
    paper 003 §3.4 puts it, capped by the axial clearance 0.8 ΔL that the growth opens:
    the model's `lift`. With two targets (axial, radial) the radial output is added: the
    rings' geometry is the paper's (7010 CETA), the ring temperatures come from the inputs
    after the ξ sensor ([inner ring sensors], outer ring sensors); with `ring_gains` (the
    default) each ring's term gets a gain ≥ 0, fitted by least squares on the radial error
    that the clearance c(ΔL) leaves (RadialParams says why), else the paper's form stays
    unfitted. The radial output has no lift.
    """
    opt = validate_options("xi_spindle", Options, options)
    targets = default_targets(log, targets)
    if len(targets) not in (1, 2):
        raise BadInput(
            f"xi_spindle fits the axial axis, or axial and radial; targets: {', '.join(targets)}",
            path="--target",
        )
    radial = len(targets) == 2
    chosen = None
    if not inputs and not radial and opt.xi_sensor is not None:
        if opt.xi_sensor not in log.columns:
            raise BadInput(
                f"the ξ sensor {opt.xi_sensor} is not a column of the log", file=log.file, path="--option xi_sensor"
            )
        inputs = [opt.xi_sensor, *([opt.speed_input] if opt.speed_input in log.columns else [])]
    elif not inputs and not radial and len(log.temperature_columns()) > 1:
        inputs, chosen = _xi_sensor(log, targets, opt)
    inputs = _inputs(log, opt, inputs, radial)
    speed = opt.speed_input if opt.speed_input in inputs else None
    temps = [c for c in inputs if c != speed]
    X = columns(log, temps)
    E = target_columns(log, targets)
    ok = measured_rows(E)  # the loss counts the rows with every target measured
    rise = X[:, 0] - X[0, 0]  # from the reading at start, as the model's T0
    # the direction the spindle grows in on the axis (machine coordinates): the sign of the error's
    # slope on the sensor's rise; the fit then works on the growth, s·error
    sign = _axial_sign(rise[ok], E[ok, 0])
    E[:, 0] *= sign
    gain, length = _axial_gain(log, opt, rise[ok], E[ok, 0], temps[0])
    report: dict[str, Any] = {}
    lift = None
    if speed is not None:
        n2 = columns(log, [speed])[:, 0] ** 2
        if not np.any(n2[ok] > 0):
            raise BadInput("the speed input is 0 throughout: the lift k cannot be fitted", file=log.file, path=speed)
        gain, k = _fit_gain_and_lift(rise[ok], n2[ok], E[ok, 0], gain, LIFT_SHARE)
        length = _length_mm(log, opt, gain, temps[0])
        lift = LiftParams(k_um_per_rpm2=k, speed_input=speed, preload_share=LIFT_SHARE)
        report["k_um_per_rpm2"] = k
    rad = None
    if radial:
        given = {"alpha_per_k": opt.ring_alpha_per_k} if opt.ring_alpha_per_k is not None else {}
        rad = RadialParams(
            inner_sensors=opt.inner_sensors,
            outer_sensors=opt.outer_sensors,
            clearance=opt.clearance,
            preload_share=LIFT_SHARE,
            **given,
        )
        if opt.ring_gains:
            g_out, g_in = _ring_gains(log, temps, targets, opt, length, rad, E[:, 1], ok)
            rad = rad.model_copy(update={"outer_gain": g_out, "inner_gain": g_in})
            report["outer_gain"], report["inner_gain"] = g_out, g_in
        report["radial_form"] = "ring_gains" if opt.ring_gains else "paper"
    report = {"gain_um_per_k": gain, "length_mm": length, "axial_sign": sign, **report}
    if chosen is not None:
        report["inputs_chosen"] = chosen
    params = XiSpindleParams(
        alpha_per_k=opt.alpha_per_k,
        length_mm=length,
        t0_c=None,
        xi_mm=opt.xi_mm,
        lift=lift,
        radial=rad,
        axial_sign=sign,
    )
    model = XiSpindle(params, temps + ([speed] if speed else []), axis_names(targets))
    return FitResult(model, report)


# paper 003 §3.3: 80 % of the growth lies between the bearings (the lift's cap, the clearance's ΔL)
LIFT_SHARE = 0.8


def _ring_gains(
    log: Log,
    temps: list[str],
    targets: list[str],
    opt: Options,
    length_mm: float,
    rad: RadialParams,
    e_um: np.ndarray,
    ok: np.ndarray,
) -> tuple[float, float]:
    """(g_C, g_B) ≥ 0 minimising Σ (e − g_C u_C + g_B u_B − c)², u and c as the model computes them.

    The terms come from the model itself, each alone (the others' gains 0, c off), so the
    fit and the run-time evaluation cannot disagree.
    """
    X = columns(log, temps)
    t = log.t_s

    def term(**update: Any) -> np.ndarray:
        p = XiSpindleParams(alpha_per_k=opt.alpha_per_k, length_mm=length_mm, radial=rad.model_copy(update=update))
        return XiSpindle(p, list(temps), axis_names(targets)).predict(X, t)[:, 1]

    u_c = term(inner_gain=0.0, outer_gain=1.0, clearance=False)
    u_b = -term(inner_gain=1.0, outer_gain=0.0, clearance=False)
    c = term(inner_gain=0.0, outer_gain=0.0) if rad.clearance else np.zeros_like(u_c)
    A = np.column_stack([u_c, -u_b])[ok]
    if not np.any(A):
        raise BadInput(
            "the ring sensors never change: the ring gains cannot be fitted (--option ring_gains=false)",
            file=log.file,
            path="--inputs",
        )
    g, _ = optimize.nnls(A, (e_um - c)[ok])
    if np.any(g > 10.0):
        raise BadInput(
            f"the ring gains come out at {g[0]:.3g} (outer), {g[1]:.3g} (inner), beyond 10: the radial error"
            " does not follow these ring sensors (--option ring_gains=false keeps the paper's form)",
            file=log.file,
            path="--inputs",
        )
    return float(g[0]), float(g[1])


def _xi_sensor(log: Log, targets: list[str], opt: Options) -> tuple[list[str], dict[str, Any]]:
    """The ξ sensor when --inputs names none and the log has several temperatures: the one whose
    axial model (with the lift where the log has the speed) predicts the held-out folds best
    (compd.identify.holdout). Returns (inputs, what the report says)."""
    speed = [opt.speed_input] if opt.speed_input in log.columns else []
    tried: dict[str, float | str] = {}
    for c in log.temperature_columns():
        try:
            rmse = holdout.held_out_rmse(
                log, targets, lambda lg, c=c: fit(lg, [c, *speed], targets, **opt.model_dump())
            )
            tried[c] = float(rmse[0])
        except (BadInput, ValueError) as e:
            tried[c] = str(e)
    scored = {c: v for c, v in tried.items() if isinstance(v, float)}
    if not scored:
        raise BadInput(
            "no temperature column of the log works as the ξ sensor: name it with --inputs",
            file=log.file,
            path="--inputs",
        )
    best = min(scored, key=scored.__getitem__)
    return [best, *speed], {
        "inputs": [best, *speed],
        "method": holdout.METHOD + "; the ξ sensor with the smallest held-out RMSE",
        "held_out_rmse_um": tried,
    }


def _inputs(log: Log, opt: Options, inputs: list[str] | None, radial: bool) -> list[str]:
    """The ξ sensor (the log's one temperature column when none is named), then for a radial
    fit the ring sensors; the speed (`speed_input`) anywhere among them adds the lift.
    BadInput for any other count."""
    rings = opt.inner_sensors + opt.outer_sensors
    if not inputs:
        temps = log.temperature_columns()
        if radial or len(temps) != 1:
            raise BadInput(
                "name the ξ sensor"
                + (" and the ring sensors" if radial else "")
                + f" with --inputs (the log has {len(temps)} temperature columns)",
                file=log.file,
                path="--inputs",
            )
        return temps
    rest = [c for c in inputs if c != opt.speed_input]
    if not rest:
        raise BadInput(f"--inputs names only the speed {opt.speed_input}: name the ξ sensor first", path="--inputs")
    if not radial and len(rest) != 1:
        raise BadInput(
            f"xi_spindle takes one input (the ξ sensor), and the speed {opt.speed_input} for the lift;"
            f" got {', '.join(inputs)} (another speed column: --option speed_input=COL)",
            path="--inputs",
        )
    if radial and len(rest) != 1 + rings:
        raise BadInput(
            f"a radial fit takes the ξ sensor, {opt.inner_sensors} inner-ring and {opt.outer_sensors} "
            f"outer-ring sensor(s): {1 + rings} inputs besides the speed {opt.speed_input}, got {len(rest)}"
            " (another speed column: --option speed_input=COL)",
            path="--inputs",
        )
    return list(inputs)


def _axial_sign(rise: np.ndarray, e: np.ndarray) -> int:
    """+1 when the error grows with the ξ sensor's rise (the spindle grows toward the axis's +
    direction), −1 when it falls (toward −: a vertical spindle growing down, logged in machine
    coordinates); +1 when the rise says nothing."""
    return -1 if float(rise @ e) < 0.0 else 1


def _axial_gain(log: Log, opt: Options, rise: np.ndarray, e: np.ndarray, name: str) -> tuple[float, float]:
    """(gain α L µm/K, L mm): the gain by least squares through the origin of the error on the ξ sensor's rise."""
    require_rows(log, rise.size, 3, "xi_spindle")
    ss = float(rise @ rise)
    if ss == 0.0:
        raise BadInput("the ξ sensor never changes", file=log.file, path=name)
    gain = float(rise @ e) / ss
    if gain <= 0:
        raise BadInput(
            f"the error falls as {name} rises (gain {gain:.3g} µm/K): not a ξ sensor",
            file=log.file,
            path=name,
        )
    return gain, _length_mm(log, opt, gain, name)


def _length_mm(log: Log, opt: Options, gain_um_per_k: float, name: str) -> float:
    """L = gain/α in mm; BadInput if that is no spindle (longer than the model allows)."""
    length = gain_um_per_k / (opt.alpha_per_k * 1000.0)
    if length > MAX_LENGTH_MM:
        raise BadInput(
            f"the gain {gain_um_per_k:.3g} µm/K means a spindle {length / 1000:.3g} m long at"
            f" α = {opt.alpha_per_k:g}: not a ξ sensor",
            file=log.file,
            path=name,
        )
    return length


def _fit_gain_and_lift(
    rise_k: np.ndarray,
    n2_rpm2: np.ndarray,
    e_um: np.ndarray,
    gain_um_per_k: float,
    share: float,
) -> tuple[float, float]:
    """(gain µm/K, k µm/rpm² ≥ 0) minimising Σ (e − g·rise − min(k n², share·max(g·rise, 0)))².

    The lift is capped by the axial clearance the growth opens (paper 003 §3.4), so the
    model is piecewise linear in each of g and k. Coordinate descent: each step minimises
    exactly over one of them (`_argmin_piecewise`), so the sum of squares never rises.
    """
    g, k = gain_um_per_k, 0.0
    pos = rise_k > 0
    for _ in range(200):
        # k, g fixed: row i predicts k n² below its knot cap/n², the cap above it
        cap = share * np.maximum(g * rise_k, 0.0)
        y = e_um - g * rise_k
        with np.errstate(divide="ignore", invalid="ignore"):
            knot = np.where(n2_rpm2 > 0, cap / n2_rpm2, np.inf)
        zero = np.zeros_like(y)
        k_new = _argmin_piecewise(y, knot, n2_rpm2, zero, zero, cap)
        # g, k fixed: a warm row predicts (1 + share) g rise below g = k n²/(share rise), g rise + k n² above
        lift = k_new * n2_rpm2
        if share > 0:
            with np.errstate(divide="ignore", invalid="ignore"):
                knot_g = np.where(pos, lift / (share * rise_k), np.inf)
        else:
            knot_g = np.zeros_like(y)
        slope_lo = np.where(pos, (1.0 + share) * rise_k, rise_k)
        icpt_hi = np.where(pos, lift, 0.0)
        g_new = _argmin_piecewise(e_um, knot_g, slope_lo, zero, rise_k, icpt_hi, lo_bound=1e-12)
        done = abs(g_new - g) <= 1e-13 * abs(g) and abs(k_new - k) <= 1e-13 * max(abs(k), 1e-30)
        g, k = g_new, k_new
        if done:
            break
    return g, k


def _argmin_piecewise(
    y: np.ndarray,
    knot: np.ndarray,
    s_lo: np.ndarray,
    c_lo: np.ndarray,
    s_hi: np.ndarray,
    c_hi: np.ndarray,
    lo_bound: float = 0.0,
) -> float:
    """argmin over p ≥ lo_bound of Σ (y − f_i(p))², f_i(p) = s_lo p + c_lo for p < knot_i, s_hi p + c_hi beyond.

    Each f_i is continuous at its knot, so the sum is a quadratic on each interval between
    sorted knots; cumulative sums give every interval's minimiser at once.
    """
    order = np.argsort(knot, kind="stable")
    kn = knot[order]
    # rows already past their knot: 0..j-1 (hi), the rest lo; j runs over the n + 1 intervals. Each
    # sum is Σ_lo over all rows plus the forward cumulative sum of (hi − lo) terms: one cumsum for the three
    rh, rl = y[order] - c_hi[order], y[order] - c_lo[order]
    sh, sl = s_hi[order], s_lo[order]
    terms = np.empty((3, kn.size + 1))
    terms[:, 0] = 0.0
    terms[0, 1:] = sh * sh - sl * sl
    terms[1, 1:] = sh * rh - sl * rl
    terms[2, 1:] = rh * rh - rl * rl
    np.cumsum(terms, axis=1, out=terms)
    q = terms[0] + float(sl @ sl)
    b = terms[1] + float(sl @ rl)
    c = terms[2] + float(rl @ rl)
    left = np.empty(kn.size + 1)
    left[0] = -np.inf
    np.maximum(kn, lo_bound, out=left[1:])
    left[0] = max(left[0], lo_bound)
    right = np.empty(kn.size + 1)
    right[:-1] = kn
    right[-1] = np.inf
    ok = (right >= left) & np.isfinite(left)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(q > 0, b / q, left)
    p = np.clip(p, left, right)
    p = np.where(ok, p, 0.0)
    sse = np.where(ok, q * p * p - 2.0 * b * p + c, np.inf)
    return float(p[int(np.argmin(sse))])


def choices(result: FitResult) -> dict[str, Any]:
    """Nothing beyond its coefficients and inputs: the ξ sensor it chose (`inputs_chosen`) is held
    while the lag is searched as every kind's chosen inputs are (compd.identify.lag.HELD_INPUTS)."""
    return {}
