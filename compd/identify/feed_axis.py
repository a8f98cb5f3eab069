"""Identifying the feed-axis model: the analytic form (paper 000) or compd's field form, whichever predicts better.

Forms (compd.models.feed_axis states the equations):
* analytic, the paper's: the erf temperature field driven by the motor loss, by bounded
  nonlinear least squares of (η, U1, U2, χ[, a, τ]) below;
* field, compd's: the measured field of the slide's sensors, by linear least squares of
  the gains (g_I, g_R, g_A) and the offsets b_o.
`form: auto` (the default) fits every form the log can carry (field: slide sensors along
the stroke; analytic: a motor current or `power_w`) and keeps the one with the smaller
held-out RMSE: the log in three time blocks, each block after the first predicted by a fit
on the blocks before it. The report gives both figures and the form kept.

Slide sensors are named by `--option slide_sensors=COL@MM,COL@MM,...` or found by name: a
group of temperature columns PREFIX<number>[mm] (T_base_000, T_base_150, ...) whose
numbers, read as axis positions in mm, spread over at least a quarter of the stroke
(so T1 … T19 are not mistaken for positions). The ambient is `--ambient COL` or the one
temperature column whose name says amb/room; every other temperature input (`--inputs`,
default every temperature column) enters as an offset b_o ΔT_o.

Identifiability of the analytic form: E is proportional to ξ times a function linear in (U1, U2, η), so ξ
cannot be told apart from a common scale of (U1, U2, η). The fit therefore holds ξ at
a given value (default 1) and identifies η, U1, U2 together with the field's shape χ
(and, optionally, the diffusivity a and the duty-cycle form's τ) by bounded nonlinear
least squares started from the exact linear solution on a grid of χ (and τ).
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import Field
from scipy import optimize, special

from compd.core.config import Strict
from compd.core.errors import BadInput
from compd.identify import holdout
from compd.identify.data import (
    AMBIENT_NAME,
    FitResult,
    axis_names,
    columns,
    default_targets,
    measured_rows,
    progress,
    require_rows,
    target_columns,
    validate_options,
)
from compd.log import Log
from compd.models.feed_axis import (
    FeedAxis,
    FeedAxisParams,
    PositionPoly,
    SlideField,
    _erf_weights,
    _heat_capacity,
    _midpoints_m,
    field_terms,
    leaky_heat_j,
    linear_reduction,
    position_weights,
)


class Options(Strict):
    """`compd fit --kind feed_axis --option KEY=VALUE` (`--ambient COL` sets `ambient`)."""

    position: str | None = Field(None, description="position column; none = pos_<axis>_mm")
    current: str | None = Field(None, description="current column; none = current_<axis>_a if logged")
    motor_temp: str | None = Field(None, description="motor surface temperature column (ζ correction)")
    ambient: str | None = Field(None, description="ambient column T_fo (ζ correction)")
    power_w: float | None = Field(None, ge=0, description="constant motor loss instead of a current")
    r_cu_ohm: float = Field(1.0, gt=0, description="copper resistance per phase (with a current)")
    zeta_per_k: float = 0.00393
    length_mm: float | None = Field(None, gt=0, description="stroke; none = largest logged position")
    segments: int = Field(30, ge=2, le=1000)
    stroke_start_mm: float = 0.0
    alpha_per_k: float = Field(11.5e-6, gt=0, lt=1e-3)
    rho_c_j_m3k: float = Field(3.61e6, gt=0)
    diffusivity_m2_s: float = Field(1.25e-5, gt=0)
    xi: float = Field(1.0, gt=0, description="ξ, held fixed (not identifiable apart from U1, U2, η)")
    chi_per_m: float | None = Field(None, gt=0, description="fix χ; none = fit it")
    fit_diffusivity: bool = Field(False, description="also fit a")
    duty_cycle: bool = Field(
        False, description="fit the duty-cycle form (the slide cools with τ; see the model's cooling_time_s)"
    )
    cooling_time_s: float | None = Field(None, gt=0, description="with duty_cycle: fix τ; none = fit it")
    linear_p0_mm: float | None = Field(None, description="kept in the model: see the params' linear_p0_mm")
    form: Literal["auto", "analytic", "field", "position_poly"] = Field(
        "auto",
        description="analytic = paper 000's; field = compd's from the slide sensors at known positions;"
        " position_poly = compd's with each temperature's effect a polynomial in the position; auto = the best"
        " held out of those the log carries",
    )
    poly_degree: int | None = Field(None, ge=1, le=3, description="position_poly degree; none = 1 or 2, held out")
    slide_sensors: str | None = Field(
        None, description="the slide's sensors as COL@MM,COL@MM,... (axis positions); none = found by name"
    )
    slide_volume_m3: float | None = Field(
        None, gt=0, le=100, description="the slide's volume V: η is then the paper's dimensionless share"
    )


def fit(log: Log, inputs: list[str] | None = None, targets: list[str] | None = None, **options: Any) -> FitResult:
    """The feed-axis model of `form` (auto: the form with the smaller held-out RMSE)."""
    opt = validate_options("feed_axis", Options, options)
    targets = default_targets(log, targets)
    if len(targets) != 1:
        raise BadInput(f"feed_axis fits one axis at a time; targets: {', '.join(targets)}", path="--target")
    axis = axis_names(targets)[0]
    pos_col = opt.position or f"pos_{axis}_mm"
    if pos_col not in log.columns:
        raise BadInput(
            f"the log has no position column {pos_col} (E depends on where the axis stands)",
            file=log.file,
            path="--option position",
        )
    temps = _temperatures(log, inputs, pos_col)
    layout = _field_layout(log, temps, opt, pos_col)
    has_loss = opt.power_w is not None or (opt.current or f"current_{axis}_a") in log.columns
    if opt.form == "analytic":
        return _named(_fit_analytic(log, targets, axis, opt), "analytic", {"method": "asked"})
    forms: dict[str, Callable[[Log], FitResult]] = {}
    if opt.form in ("auto", "field") and layout is not None:
        forms["field"] = lambda lg: _fit_field(lg, targets, axis, opt, layout)
    if opt.form == "auto" and has_loss:
        forms["analytic"] = lambda lg: _fit_analytic(lg, targets, axis, opt)
    if opt.form in ("auto", "position_poly") and temps:
        for d in [opt.poly_degree] if opt.poly_degree else [1, 2]:
            forms[f"position_poly{d}"] = lambda lg, d=d: _fit_poly(lg, targets, axis, opt, temps, d)
    if not forms:
        need = {
            "field": "two or more slide sensors along the stroke (--option slide_sensors=COL@MM,COL@MM;"
            " none found by name)",
            "position_poly": "temperature columns",
            "auto": "slide sensors, temperature columns, or the motor loss (a current column or --option power_w)",
        }[opt.form]
        raise BadInput(
            f"the {opt.form} form needs {need}",
            file=log.file,
            path="--option slide_sensors" if opt.form == "field" else "--inputs",
        )
    if len(forms) == 1:
        ((name, fit_on),) = forms.items()
        how = "asked" if opt.form != "auto" else "the only form the log carries"
        return _named(fit_on(log), name, {"method": how})
    held, blocks = holdout.compare(log, targets[0], forms)
    scored = {k: v for k, v in held.items() if isinstance(v, float)}
    if not scored:  # e.g. the axis stands still until the log's last block: physics first
        best = next(iter(forms))
        return _named(
            forms[best](log),
            best,
            {
                "method": "no form could be fitted on the log's first blocks, so no held-out comparison: the first the"
                " log carries of field, analytic, position_poly",
                "held_out_rmse_um": held,
            },
        )
    # the fewest coefficients whose held-out RMSE is within 5 % of the best: the analytic form's few,
    # the field's gains, then the position regression's sensors × powers
    lowest = min(scored.values())
    best = next(k for k in SIMPLEST_FIRST if k in scored and scored[k] * FORM_MARGIN <= lowest)
    return _named(
        forms[best](log),
        best,
        {
            "method": holdout.METHOD + f"; the form with the fewest coefficients within {1 / FORM_MARGIN - 1:.0%} of"
            " the smallest RMSE is kept (analytic, field, position_poly1, position_poly2)",
            "held_out_blocks": blocks,
            "held_out_rmse_um": held,
        },
    )


SIMPLEST_FIRST = ("analytic", "field", "position_poly1", "position_poly2", "position_poly3")
FORM_MARGIN = 0.95  # a form with more coefficients must cut the held-out RMSE by 5 % to be kept


def _named(result: FitResult, form: str, selection: dict[str, Any]) -> FitResult:
    """The fit's report says which form it is and how it was chosen."""
    result.report["form"] = form.rstrip("0123456789")
    result.report["form_selection"] = selection
    return result


def _temperatures(log: Log, inputs: list[str] | None, pos_col: str) -> list[str]:
    """The temperature inputs: `--inputs`, or every temperature column of the log."""
    temps = [c for c in (list(inputs) if inputs else log.temperature_columns()) if c != pos_col]
    for c in temps:
        if c not in log.columns:
            raise BadInput(f"the log has no column {c}", file=log.file, path="--inputs")
    return temps


def _fit_poly(log: Log, targets: list[str], axis: str, opt: Options, temps: list[str], degree: int) -> FitResult:
    """Linear least squares of b_kp in E = Σ_k ΔT_k Σ_p b_kp (y/L)^p (rises from the first row)."""
    pos_col = opt.position or f"pos_{axis}_mm"
    names = [pos_col, *temps]
    X = columns(log, names)
    E = target_columns(log, targets)[:, 0]
    ok = measured_rows(E)
    n_coef = len(temps) * (degree + 1)
    require_rows(log, int(ok.sum()), n_coef + 3, f"feed_axis position_poly form ({n_coef} coefficients)")
    if np.ptp(X[:, 0]) <= 0:
        raise BadInput("the axis never moves: E(t, y) needs several positions", file=log.file, path=pos_col)
    length = opt.length_mm or float(np.max(X[:, 0]) - opt.stroke_start_mm)
    if length <= 0:
        raise BadInput("the stroke length must be positive", path="--option length_mm")
    u = np.clip(X[:, 0] - opt.stroke_start_mm, 0.0, length) / length
    R = X[:, 1:] - X[0, 1:]
    A = (R[:, :, None] * (u[:, None, None] ** np.arange(degree + 1))).reshape(len(E), -1)
    coef, *_ = np.linalg.lstsq(A[ok], E[ok], rcond=None)
    B = coef.reshape(len(temps), degree + 1)
    params = FeedAxisParams(
        length_mm=length,
        segments=opt.segments,
        stroke_start_mm=opt.stroke_start_mm,
        alpha_per_k=opt.alpha_per_k,
        input_roles=["position"] + ["rise"] * len(temps),
        linear_p0_mm=opt.linear_p0_mm,
        position_poly=PositionPoly(degree=degree, coef_um_per_k=[[float(v) for v in row] for row in B]),
    )
    report = {
        "degree": degree,
        "note": "position_poly: E = Σ_k ΔT_k Σ_p b_kp (y/L)^p, rises from the readings at start",
    }
    return FitResult(FeedAxis(params, names, [axis]), report)


_NUMBERED = re.compile(r"^(?P<prefix>.*?)(?P<mm>\d+(?:\.\d+)?)(?:_?mm)?$", re.IGNORECASE)


def _field_layout(log: Log, temps: list[str], opt: Options, pos_col: str) -> dict[str, Any] | None:
    """The field form's inputs among the temperatures: slide sensors with positions, ambient, offsets;
    None without slide sensors."""
    pos = log.col(pos_col)
    length = opt.length_mm or float(np.max(pos) - opt.stroke_start_mm)
    if opt.slide_sensors:
        slide = _parse_slide(opt.slide_sensors, log)
        how = "--option slide_sensors"
    else:
        slide = _slide_by_name(temps, opt.stroke_start_mm, length)
        how = "found by name"
    if slide is None or len(slide) < 2:
        return None
    slide.sort(key=lambda cm: cm[1])
    names = [c for c, _ in slide]
    ambient = opt.ambient
    if ambient is None:
        amb = [c for c in temps if AMBIENT_NAME.search(c) and c not in names]
        ambient = amb[0] if len(amb) == 1 else None
    elif ambient not in log.columns:
        raise BadInput(f"the log has no ambient column {ambient}", file=log.file, path="--ambient")
    offsets = [c for c in temps if c not in names and c != ambient]
    return {"slide": slide, "ambient": ambient, "offsets": offsets, "found": how, "length_mm": length}


def _parse_slide(text: str, log: Log) -> list[tuple[str, float]]:
    out = []
    for item in text.split(","):
        col, sep, mm = item.strip().partition("@")
        try:
            at = float(mm)
        except ValueError:
            at = math.nan
        if not sep or not col or not math.isfinite(at):
            raise BadInput(f"expected COL@MM, got {item.strip()!r}", path="--option slide_sensors")
        if col not in log.columns:
            raise BadInput(f"the log has no column {col}", file=log.file, path="--option slide_sensors")
        out.append((col, at))
    if len({c for c, _ in out}) != len(out) or len({m for _, m in out}) != len(out):
        raise BadInput("each slide sensor and each position once", path="--option slide_sensors")
    return out


def _slide_by_name(temps: list[str], start_mm: float, length_mm: float) -> list[tuple[str, float]] | None:
    """The largest group PREFIX<number>[mm] whose numbers lie on the stroke and span ≥ ¼ of it."""
    groups: dict[str, list[tuple[str, float]]] = {}
    for c in temps:
        m = _NUMBERED.match(c)
        if m and m["prefix"]:
            groups.setdefault(m["prefix"], []).append((c, float(m["mm"])))
    best = None
    for members in groups.values():
        mm = [v for _, v in members]
        on_stroke = all(start_mm - 1e-9 <= v <= start_mm + length_mm + 1e-9 for v in mm)
        spread = len(members) >= 2 and len(set(mm)) == len(mm) and max(mm) - min(mm) >= 0.25 * length_mm
        if on_stroke and spread and (best is None or len(members) > len(best)):
            best = members
    return None if best is None else list(best)


def _fit_field(log: Log, targets: list[str], axis: str, opt: Options, layout: dict[str, Any]) -> FitResult:
    """Linear least squares of (g_I, g_R, g_A, b_o) on the measured field (rises from the first row)."""
    pos_col = opt.position or f"pos_{axis}_mm"
    slide = layout["slide"]
    amb, offs = layout["ambient"], layout["offsets"]
    names = [pos_col] + [c for c, _ in slide] + ([amb] if amb else []) + offs
    roles = ["position"] + ["slide"] * len(slide) + (["ambient"] if amb else []) + ["offset"] * len(offs)
    X = columns(log, names)
    E = target_columns(log, targets)[:, 0]
    ok = measured_rows(E)
    n_coef = 3 + bool(amb) + len(offs)
    require_rows(log, int(ok.sum()), n_coef + 3, f"feed_axis field form ({n_coef} coefficients)")
    if np.ptp(X[:, 0]) <= 0:
        raise BadInput("the axis never moves: E(t, y) needs several positions", file=log.file, path=pos_col)
    length = layout["length_mm"]
    if length <= 0:
        raise BadInput("the stroke length must be positive", path="--option length_mm")
    geometry = dict(
        length_mm=length,
        segments=opt.segments,
        stroke_start_mm=opt.stroke_start_mm,
        alpha_per_k=opt.alpha_per_k,
        input_roles=roles,
        linear_p0_mm=opt.linear_p0_mm,
    )
    k = len(slide)
    probe = FeedAxisParams(
        **geometry,
        field=SlideField(slide_mm=[m for _, m in slide], gain_integral=1.0, offset_um_per_k=[0.0] * len(offs)),
    )
    rise = X - X[0]
    F = field_terms(rise[:, 1 : 1 + k], X[:, 0] - opt.stroke_start_mm, rise[:, 1 + k] if amb else None, probe)
    A = np.column_stack(
        [F[:, 0], F[:, 1], F[:, 3]]
        + ([F[:, 2]] if amb else [])
        + [rise[:, 1 + k + bool(amb) + j] for j in range(len(offs))]
    )
    coef, *_ = np.linalg.lstsq(A[ok], E[ok], rcond=None)
    g_amb = float(coef[3]) if amb else 0.0
    params = FeedAxisParams(
        **geometry,
        field=SlideField(
            slide_mm=[m for _, m in slide],
            gain_integral=float(coef[0]),
            gain_restraint=float(coef[1]),
            gain_constant=float(coef[2]),
            gain_ambient=g_amb,
            offset_um_per_k=[float(v) for v in coef[3 + bool(amb) :]],
        ),
    )
    model = FeedAxis(params, names, [axis])
    report = {
        "slide_sensors": {c: m for c, m in slide},
        "slide_sensors_from": layout["found"],
        "ambient": amb,
        "offsets": offs,
        "note": "the field form: E = g_I α∫ΔT̂ + g_R α(y/L)∫_0^L ΔT̂ + g_C α∫_0^L ΔT̂ + g_A α y ΔT_amb + Σ b_o ΔT_o,"
        " rises from the readings at start",
    }
    return FitResult(model, report)


def _fit_analytic(log: Log, targets: list[str], axis: str, opt: Options) -> FitResult:
    """Bounded nonlinear least squares of (η, U1, U2, χ[, a, τ]) against the logged error."""
    names, roles, cur_col = _inputs_and_roles(log, opt, axis)
    X = columns(log, names)
    E = target_columns(log, targets)[:, 0]
    require_rows(log, int(measured_rows(E).sum()), 8, "feed_axis (4 to 5 coefficients)")
    t = log.t_s - log.t_s[0]
    pos = X[:, 0]
    if np.ptp(pos) <= 0:
        raise BadInput("the axis never moves: E(t, y) needs several positions", file=log.file, path=names[0])
    length = opt.length_mm or float(np.max(pos) - opt.stroke_start_mm)
    if length <= 0:
        raise BadInput("the stroke length must be positive", path="--option length_mm")
    base = dict(
        length_mm=length,
        segments=opt.segments,
        stroke_start_mm=opt.stroke_start_mm,
        alpha_per_k=opt.alpha_per_k,
        rho_c_j_m3k=opt.rho_c_j_m3k,
        diffusivity_m2_s=opt.diffusivity_m2_s,
        xi=opt.xi,
        zeta_per_k=opt.zeta_per_k,
        power_w=opt.power_w if cur_col is None else None,
        r_cu_ohm=opt.r_cu_ohm if cur_col is not None else None,
        input_roles=roles,
        linear_p0_mm=opt.linear_p0_mm,
        slide_volume_m3=opt.slide_volume_m3,
    )
    probe = FeedAxisParams(chi_per_m=1.0, eta=0.0, u1_k=0.0, u2_k=0.0, **base)
    tmp = FeedAxis(probe, names, [axis])
    pw = np.array([tmp._power(row) for row in X])
    if opt.duty_cycle:
        if not np.any(pw > 0):
            raise BadInput("duty_cycle: the motor loss is zero throughout the log", file=log.file)
        # the loss while the axis works: U1, U2 give the steady profile at this loss
        base["ref_power_w"] = float(np.mean(pw[pw > 0.1 * np.max(pw)]))
        probe = FeedAxisParams(chi_per_m=1.0, eta=0.0, u1_k=0.0, u2_k=0.0, **base)
    shape = _Shape(opt, t, pw, pos, E, probe, length)
    res, (eta, u1, u2, chi, a, tau) = shape.refine(*shape.start())
    params = FeedAxisParams(
        **{**base, "diffusivity_m2_s": a},
        chi_per_m=chi,
        eta=float(eta),
        u1_k=float(u1),
        u2_k=float(u2),
        cooling_time_s=tau,
    )
    model = FeedAxis(params, names, [axis])
    report = {
        "converged": bool(res.success),
        "at_bounds": shape.at_bounds,
        "optimizer": res.message,
        "nfev": int(res.nfev),
        "xi_fixed": opt.xi,
        "eta_share": float(eta) if opt.slide_volume_m3 else None,
        "eta_per_m3": float(eta) / (opt.slide_volume_m3 or 1.0),
        "note": "ξ is held fixed: E scales with ξ·(U1, U2, η), so ξ alone is not identifiable"
        + (
            ""
            if opt.slide_volume_m3
            else "; η is per m³: give --option slide_volume_m3 for the paper's dimensionless share"
        ),
        "linear_reduction": _reductions(t, shape.heat(tau), params),
    }
    return FitResult(model, report)


def _inputs_and_roles(log: Log, opt: Options, axis: str) -> tuple[list[str], list[str], str | None]:
    """(input columns, their roles, the current column or None) of the fit from its options and the log."""
    names, roles = [opt.position or f"pos_{axis}_mm"], ["position"]
    cur_col = opt.current
    if cur_col is None and opt.power_w is None and f"current_{axis}_a" in log.columns:
        cur_col = f"current_{axis}_a"
    if cur_col is not None:
        names.append(cur_col)
        roles.append("current")
        for col, role in ((opt.motor_temp, "motor_temp"), (opt.ambient, "ambient")):
            if col is not None:
                names.append(col)
                roles.append(role)
    elif opt.power_w is None:
        raise BadInput(
            f"feed_axis needs the motor loss: a current_{axis}_a column or --option power_w=W",
            file=log.file,
        )
    return names, roles, cur_col


class _Shape:
    """The field's shape χ (and a, τ) with the coefficients (η, U1, U2) that are linear given it."""

    def __init__(
        self,
        opt: Options,
        t: np.ndarray,
        pw: np.ndarray,
        pos: np.ndarray,
        E: np.ndarray,
        probe: FeedAxisParams,
        length_mm: float,
    ) -> None:
        self.opt, self.t, self.pw, self.pos, self.probe, self.length_mm = opt, t, pw, pos, probe, length_mm
        # the field runs through every row (its heat is a memory); the residuals count the measured ones
        self.ok = measured_rows(E)
        self.E = E[self.ok]
        self.heat = functools.lru_cache(maxsize=64)(self._heat)
        self.weighted = functools.lru_cache(maxsize=8)(self._weighted)
        self.a0 = opt.diffusivity_m2_s
        self.free_chi = opt.chi_per_m is None
        self.free_tau = opt.duty_cycle and opt.cooling_time_s is None

    def _heat(self, tau: float | None) -> np.ndarray:
        return leaky_heat_j(self.t, self.pw, tau)

    def _weighted(self, a: float) -> tuple[np.ndarray, np.ndarray]:
        """At the measured rows, for diffusivity a: W ⊙ (1 − erf) (n × m) and Σ_j W ⊙ erf (n), W the
        rows' position weights (compd.models.feed_axis.position_weights): what error_basis sums,
        less the shape χ and the heat, which enter as a vector and a per-row factor."""
        p = self.probe
        g = _erf_weights(self.t[self.ok], _midpoints_m(p), a, special.erf)
        W = position_weights(self.pos[self.ok], p)
        return W * (1.0 - g), (W * g).sum(axis=1)

    def basis(self, chi: float, a: float, tau: float | None) -> np.ndarray:
        """The error's basis (U1, U2, η columns) at the measured rows: error_basis's, summed by the
        position weights (one product per column instead of error_basis's n × m × 3 cumulative sum)."""
        p = self.probe
        wh, wg = self.weighted(a)
        q = self.heat(tau)[self.ok]
        y = _midpoints_m(p)
        out = np.empty((wg.size, 3))
        out[:, 0] = wh @ np.exp(-chi * y)
        out[:, 1] = wh @ np.exp(chi * y)
        if tau is not None and p.ref_power_w is not None:  # the steady profile's share Q/(τ P_ref)
            out[:, :2] *= (q / (tau * p.ref_power_w))[:, None]
        out[:, 2] = wg * (q / _heat_capacity(p))
        return (self.opt.xi * p.alpha_per_k * (p.length_mm / p.segments) * 1000.0) * out

    def linear(self, chi: float, a: float, tau: float | None) -> tuple[float, np.ndarray]:
        """(sum of squared errors, (U1, U2, η)) by linear least squares at this shape."""
        F = self.basis(chi, a, tau)
        coef, *_ = np.linalg.lstsq(F, self.E, rcond=None)
        return float(np.sum((F @ coef - self.E) ** 2)), coef

    def start(self) -> tuple[float, float | None, np.ndarray]:
        """(χ0, τ0, (U1, U2, η)): the best of a grid of χ (and τ), each solved linearly."""
        opt = self.opt
        if opt.chi_per_m is not None:
            chi_grid = np.array([opt.chi_per_m])
        else:
            chi_grid = np.geomspace(0.05, 30.0, 40) / (self.length_mm / 1000.0)
        if not opt.duty_cycle:
            tau_grid: list[float | None] = [None]
        elif self.free_tau:
            tau_grid = [float(v) for v in np.geomspace(600.0, 86400.0, 12)]
        else:
            tau_grid = [opt.cooling_time_s]
        starts = [(c, tau) for tau in tau_grid for c in chi_grid]
        costs = [self.linear(c, self.a0, tau)[0] for c, tau in progress(starts, desc="feed_axis start")]
        chi0, tau0 = starts[int(np.argmin(costs))]
        chi0 = float(chi0)
        return chi0, tau0, self.linear(chi0, self.a0, tau0)[1]

    def refine(self, chi0: float, tau0: float | None, coef: np.ndarray) -> tuple[Any, tuple]:
        """Bounded nonlinear least squares from the start: (result, (η, U1, U2, χ, a, τ))."""
        opt, a0, free_chi, free_tau = self.opt, self.a0, self.free_chi, self.free_tau
        u1, u2, eta = coef
        x0 = (
            [eta, u1, u2]
            + ([math.log(chi0)] if free_chi else [])
            + ([math.log(a0)] if opt.fit_diffusivity else [])
            + ([math.log(tau0)] if free_tau else [])
        )

        def unpack(v):
            k = 3
            chi = math.exp(v[k]) if free_chi else chi0
            k += free_chi
            a = math.exp(v[k]) if opt.fit_diffusivity else a0
            k += opt.fit_diffusivity
            tau = math.exp(v[k]) if free_tau else tau0
            return v[0], v[1], v[2], chi, a, tau

        def resid(v):
            eta_, u1_, u2_, chi, a, tau = unpack(v)
            return self.basis(chi, a, tau) @ np.array([u1_, u2_, eta_]) - self.E

        chi_max = min(1e3, 700.0 / (self.length_mm / 1000.0))  # the params' bound: e^(χ L) stays finite
        lo = (
            [0.0, -1e3, -1e3]
            + ([math.log(1e-3)] if free_chi else [])
            + ([math.log(1e-8)] if opt.fit_diffusivity else [])
        )
        hi = (
            [1e3, 1e3, 1e3]
            + ([math.log(chi_max)] if free_chi else [])
            + ([math.log(1e-3)] if opt.fit_diffusivity else [])
        )
        if free_tau:
            lo.append(math.log(60.0))
            hi.append(math.log(30 * 86400.0))
        x0 = np.clip(x0, np.array(lo) + 1e-12, np.array(hi) - 1e-12)
        res = optimize.least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", max_nfev=2000)
        names = (
            ["η", "U1", "U2"]
            + (["χ"] if free_chi else [])
            + (["a"] if opt.fit_diffusivity else [])
            + (["τ"] if free_tau else [])
        )
        span = np.array(hi) - np.array(lo)
        self.at_bounds = [
            f"{name} is at the {'lower' if abs(v - a) <= abs(v - b) else 'upper'} bound of its search range"
            for name, v, a, b, w in zip(names, res.x, lo, hi, span, strict=True)
            if min(abs(v - a), abs(v - b)) <= 1e-6 * max(w, 1.0)
        ]
        return res, unpack(res.x)


def _reductions(t: np.ndarray, q: np.ndarray, params: FeedAxisParams) -> dict[str, dict[str, float]]:
    """The linear reduction (K0, tanβ, P0) at the quarters of the log's heating time (for a Siemens CNC)."""
    reductions = {}
    for tt in sorted({float(v) for v in np.quantile(t, [0.25, 0.5, 0.75, 1.0])}):
        k0, tb, p0 = linear_reduction(tt, float(np.interp(tt, t, q)), params)
        reductions[f"{tt:g}"] = {"k0_um": k0, "tan_beta_um_per_mm": tb, "p0_mm": p0}
    return reductions


def choices(result: FitResult) -> dict[str, Any]:
    """What this fit chose beyond its coefficients, as options (compd.identify.lag holds them): the form."""
    form = result.report["form"]
    return {"form": form, **({"poly_degree": result.report["degree"]} if form == "position_poly" else {})}
