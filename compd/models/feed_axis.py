"""Analytic feed-axis model of a linear-motor axis: erf temperature field, segment-sum error (paper 000).

With heating time t [s], heat put in by the motor Q(t) = ∫ P_J dt [J] (= P_J t for a
constant loss), and the slide cut into m segments of ΔL with midpoints y_j [m]:

    T_hps(t) − T_fo = η Q(t) / (ρ c)                          eq. 15 (P_J t → Q)
    T_hds(y) − T_fo = U2 e^(χ y) + U1 e^(−χ y)                eq. 17
    T(t, y) − T_fo  = T_hds + erf(y / (2 √(a t))) (T_hps − T_hds)   eq. 19
    E(t, y_i)       = ξ α ΔL Σ_{j ≤ i} [T(t, y_j) − T_fo]     eq. 21

The motor loss is the copper loss P_cu = 3 i² R_cu [1 + ζ (T_m − T_fo)] (eq. 9) from the
motor current, or a configured constant power. Between segment midpoints E is linear
in y, and E(t, 0) = 0.

Duty-cycle form (compd's, like the ambient term of the AR(1) model): the paper's
model describes a heating run from rest — Q only grows and the steady profile T_hds
is the one of the loss it was fitted at. A machine that stops and starts all day
needs the slide to cool. With `cooling_time_s` τ set, the heat in the slide leaks
to the air, Q(t) = ∫ P(s) e^(−(t−s)/τ) ds, and the steady profile scales with the
mean loss Q/τ relative to `ref_power_w`: T_hds(t, y) = Q/(τ P_ref) (U2 e^(χ y) + U1 e^(−χ y)).
Without the loss (τ → ∞) Q is the paper's ∫ P dt; with a constant loss the steady
profile reaches the paper's U1, U2 after a few τ. The fit finds τ with χ.

η is the paper's dimensionless share of the motor loss that heats the slide when
`slide_volume_m3` V is given: T_hps − T_fo = η Q/(ρ c V). Files without V keep the older
meaning, η per m³ (T_hps − T_fo = η Q/(ρ c)); the two differ by the factor V.

Field form (compd's, `field:` set): where the slide carries temperature sensors, the
measured field replaces the analytic one. With the rises ΔT_k = T_k − T_k0 of the slide
sensors at stroke positions s_k, interpolated linearly in y (held flat beyond the first
and last sensor) to ΔT̂(y), the ambient rise ΔT_a and further sensors ΔT_o (table, head:
parts whose growth does not depend on the position), y the position from the stroke start
and L the stroke:

    I(y)    = α ∫_0^y ΔT̂ dy'                      the segment sum of eq. 21 on the measured field
    R(y)    = α (y/L) ∫_0^L ΔT̂ dy'                the end supports' restraint (the reversal)
    A(y)    = α y ΔT_a                             a scale or a guide that follows the room
    C       = α ∫_0^L ΔT̂ dy'                      the same everywhere on the stroke
    E(t, y) = g_I I + g_R R + g_A A + g_C C + Σ_o b_o ΔT_o   µm

g_I plays ξ's part (the expansion's correction factor), g_R < 0 pulls the error back
towards the far end as the fixed supports do, g_C takes what moves the whole stroke (the
base before the stroke's start grows with it, the supports' pull has a part that does not
depend on y), and every term is linear in its
coefficient, so the fit is a least-squares solve. Heat that enters where the coil
travels shows in the sensors there, so partial strokes are seen, and the slide's
response to the room is measured rather than modelled. T_k0 are the readings at start
(the heating run's equilibrium, as t = 0 is for the analytic form).

Position-regression form (compd's, `position_poly:` set): where the slide's sensors are
logged but not where they sit, each temperature rise ΔT_k acts through a polynomial in the
relative position u = y/L:

    E(t, y) = Σ_k ΔT_k Σ_{p=0..d} b_kp u^p        µm, d = `degree` (1–3)

It is the field form with the integral's weights learnt instead of known: a sensor's
share of ∫_0^y ΔT̂ grows with y, which a low-degree polynomial in u follows.

The fit (η, U1, U2, χ and optionally a and τ from a log, or the measured forms' gains) is
compd.identify.feed_axis.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from compd.core.errors import BadInput
from compd.models.base import MAX_GAIN_UM_PER_K, MAX_LENGTH_MM, LeadParams, Model, ModelParams
from compd.models.erf import erf, erf_inplace

ErfFn = Callable[[np.ndarray], np.ndarray]

Role = Literal["position", "current", "motor_temp", "ambient", "slide", "offset", "rise"]


def _position_only() -> list[Role]:
    """The default input_roles: one input, the position."""
    return ["position"]


FIELD_ROLES = ("slide", "offset", "rise")  # roles several inputs may have (the measured forms)


class SlideField(ModelParams):
    """compd's field form of the feed-axis model: the measured slide field (see the module doc).

    Ranges: gains |g| ≤ 100 (g_I ≈ ξ ≈ 1 for a slide of the given α); offsets within the
    gain bound of the linear models (µm per K).
    """

    slide_mm: list[Annotated[float, Field(ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM)]] = Field(
        min_length=2,
        description="axis position of each `slide` input, in input order, strictly increasing (mm)",
    )
    gain_integral: float = Field(ge=-100, le=100, description="g_I on α ∫_0^y ΔT̂ (≈ ξ)")
    gain_restraint: float = Field(0.0, ge=-100, le=100, description="g_R on α (y/L) ∫_0^L ΔT̂ (the end supports)")
    gain_constant: float = Field(
        0.0,
        ge=-100,
        le=100,
        description="g_C on α ∫_0^L ΔT̂, the same everywhere on the stroke: the base before the stroke's start and"
        " the supports' pull on it (0: files before the key)",
    )
    gain_ambient: float = Field(0.0, ge=-100, le=100, description="g_A on α y ΔT_ambient (needs an `ambient` input)")
    offset_um_per_k: list[Annotated[float, Field(ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K)]] = Field(
        default_factory=list, description="b_o per `offset` input, in input order (µm/K)"
    )

    @field_validator("slide_mm")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        if any(b <= a for a, b in zip(v[:-1], v[1:], strict=True)):
            raise ValueError("slide_mm must be strictly increasing (the sensors' order along the slide)")
        return v


class PositionPoly(ModelParams):
    """compd's position-regression form: E = Σ_k ΔT_k Σ_p b_kp (y/L)^p (see the module doc).

    For a log whose slide sensors' positions are not known: each temperature's effect is a
    polynomial in the position. Ranges: degree 1–3; gains within the linear models' bound.
    """

    degree: int = Field(ge=1, le=3, description="p = 0 … degree")
    coef_um_per_k: list[list[Annotated[float, Field(ge=-MAX_GAIN_UM_PER_K, le=MAX_GAIN_UM_PER_K)]]] = Field(
        description="b_kp: one row per `rise` input (input order), degree + 1 columns (µm/K)"
    )

    @model_validator(mode="after")
    def _shape(self) -> PositionPoly:
        for i, row in enumerate(self.coef_um_per_k):
            if len(row) != self.degree + 1:
                raise ValueError(
                    f"coef_um_per_k[{i}] has {len(row)} gains for degree {self.degree} ({self.degree + 1})"
                )
        return self


class FeedAxisParams(LeadParams):
    """Fixed physics and fitted coefficients of the feed-axis model (paper 000).

    Ranges: lengths in (0, 100 m]; α in (0, 1e-3) /K; ρc of a solid in [1e5, 1e8] J/(m³ K)
    (steel 3.6e6); a in (0, 1e-3] m²/s (metals ≤ 1.2e-4); χ L ≤ 700 so e^(χ y) stays finite;
    η and ξ ≥ 0 (heat flows into the slide); |U1|, |U2| ≤ 1000 K (the fit's bounds).
    """

    length_mm: float = Field(gt=0, le=MAX_LENGTH_MM, description="slide length L (the stroke)")
    segments: int = Field(30, ge=1, le=1000, description="m, segments of ΔL = L/m")
    stroke_start_mm: float = Field(0.0, ge=-MAX_LENGTH_MM, le=MAX_LENGTH_MM, description="axis position at y = 0")
    alpha_per_k: float = Field(11.5e-6, gt=0, lt=1e-3, description="α_l, 1/K")
    rho_c_j_m3k: float = Field(3.61e6, ge=1e5, le=1e8, description="ρ c, J/(m³ K)")
    diffusivity_m2_s: float = Field(1.25e-5, gt=0, le=1e-3, description="a = λ/(ρ c), m²/s")
    chi_per_m: float | None = Field(None, gt=0, le=1e5, description="χ = √(h A/(ρ c a)), 1/m (analytic form)")
    eta: float | None = Field(
        None,
        ge=0,
        le=1e3,
        description="η, share of the motor loss that heats the slide (×ξ scale; dimensionless with"
        " slide_volume_m3, else per m³) (analytic form)",
    )
    u1_k: float | None = Field(None, ge=-1e3, le=1e3, description="U1, K (analytic form)")
    u2_k: float | None = Field(None, ge=-1e3, le=1e3, description="U2, K (analytic form)")
    slide_volume_m3: float | None = Field(
        None,
        gt=0,
        le=100,
        description="V, the slide's volume: η is then the paper's dimensionless share;"
        " none = η per m³ (files written before the key)",
    )
    field: SlideField | None = Field(
        None, description="compd's field form from the slide's sensors (then χ, η, U1, U2 are unused)"
    )
    position_poly: PositionPoly | None = Field(
        None, description="compd's position-regression form (then χ, η, U1, U2 are unused)"
    )
    xi: float = Field(1.0, gt=0, le=1e3, description="ξ, correction factor of the expansion")
    power_w: float | None = Field(None, ge=0, le=1e6, description="constant motor loss; none = from current")
    r_cu_ohm: float | None = Field(None, gt=0, le=1e3, description="copper resistance per phase")
    zeta_per_k: float = Field(
        0.00393, ge=0, le=0.1, description="ζ, copper resistance temperature coefficient (copper 0.00393)"
    )
    input_roles: list[Role] = Field(default_factory=_position_only, description="what each input is, in input order")
    cooling_time_s: float | None = Field(
        None,
        gt=0,
        le=1e8,
        description="duty-cycle form: τ of the slide's heat balance (Q leaks as e^(−t/τ), the steady profile"
        " scales with Q/(τ ref_power_w)); none = the paper's heating run from rest",
    )
    ref_power_w: float | None = Field(
        None, gt=0, le=1e6, description="duty-cycle form: the motor loss at which U1, U2 give the steady profile"
    )
    linear_p0_mm: float | None = Field(
        None,
        ge=-MAX_LENGTH_MM,
        le=MAX_LENGTH_MM,
        description="run time: output the least-squares line K0 + tanβ (y − P0) of E over the stroke"
        " at P0 = this (for a CNC whose compensation is linear in position: Siemens, paper 001);"
        " none = E at the current position",
    )

    @model_validator(mode="after")
    def _power(self) -> FeedAxisParams:
        roles = self.input_roles
        once = [r for r in roles if r not in FIELD_ROLES]
        if roles.count("position") != 1 or len(set(once)) != len(once):
            raise ValueError("input_roles needs one 'position' and each role but slide and offset at most once")
        if self.field is not None and self.position_poly is not None:
            raise ValueError("give a field or a position_poly section, not both")
        if self.field is not None:
            return self._field_roles()
        if self.position_poly is not None:
            if not set(roles) <= {"position", "rise"} or roles.count("rise") != len(self.position_poly.coef_um_per_k):
                raise ValueError("position_poly takes the position and one `rise` input per row of coef_um_per_k")
            return self
        if any(r in FIELD_ROLES for r in roles):
            raise ValueError("slide, offset and rise inputs belong to the measured forms: give a field section")
        coefs = {"chi_per_m": self.chi_per_m, "eta": self.eta, "u1_k": self.u1_k, "u2_k": self.u2_k}
        missing = [k for k, v in coefs.items() if v is None]
        if missing:
            raise ValueError(f"the analytic form needs {', '.join(missing)} (or a field section)")
        if "current" in roles:
            if self.r_cu_ohm is None:
                raise ValueError("a 'current' input needs r_cu_ohm")
        elif self.power_w is None:
            raise ValueError("give power_w or a 'current' input (with r_cu_ohm)")
        if self.cooling_time_s is not None and self.ref_power_w is None:
            raise ValueError("cooling_time_s needs ref_power_w")
        return self

    def _field_roles(self) -> FeedAxisParams:
        f, roles = self.field, self.input_roles
        assert f is not None
        if not set(roles) <= {"position", "ambient", "slide", "offset"}:
            raise ValueError("the field form takes position, slide, offset and ambient inputs only")
        if roles.count("slide") != len(f.slide_mm):
            raise ValueError(f"field.slide_mm has {len(f.slide_mm)} positions for {roles.count('slide')} slide inputs")
        if roles.count("offset") != len(f.offset_um_per_k):
            raise ValueError(
                f"field.offset_um_per_k has {len(f.offset_um_per_k)} gains for {roles.count('offset')} offset inputs"
            )
        if f.gain_ambient and "ambient" not in roles:
            raise ValueError("field.gain_ambient needs an ambient input")
        return self

    @field_validator("chi_per_m")
    @classmethod
    def _chi_finite_exp(cls, chi: float | None, info: ValidationInfo) -> float | None:
        if chi is None:
            return chi
        length_m = info.data.get("length_mm", 0.0) / 1000.0
        if chi * length_m > 700.0:
            raise ValueError(
                f"χ L = {chi * length_m:.3g}: e^(χ L) overflows above 700 (χ ≤ {700.0 / length_m:.4g} 1/m)"
            )
        return chi


def copper_loss_w(current_a, r_cu_ohm: float, zeta_per_k: float, motor_c=None, ambient_c=None):
    """P_cu = 3 i² R_cu [1 + ζ (T − T_fo)] in W (paper 000, eq. 9); no temperatures → no correction."""
    i = np.asarray(current_a, dtype=float)
    corr = 1.0
    if motor_c is not None and ambient_c is not None:
        corr = 1.0 + zeta_per_k * (np.asarray(motor_c, dtype=float) - np.asarray(ambient_c, dtype=float))
    return 3.0 * i * i * r_cu_ohm * corr


def heat_j(t_s: np.ndarray, power_w: np.ndarray) -> np.ndarray:
    """Q(t) = ∫ P dt by the trapezoid rule from the first sample (J); what evaluate accumulates."""
    t = np.asarray(t_s, dtype=float)
    p = np.broadcast_to(np.asarray(power_w, dtype=float), t.shape)
    q = np.zeros_like(t)
    if t.size > 1:
        q[1:] = np.cumsum(0.5 * (p[1:] + p[:-1]) * np.diff(t))
    return q


def leaky_heat_j(t_s: np.ndarray, power_w: np.ndarray, tau_s: float | None) -> np.ndarray:
    """Q(t) = ∫ P(s) e^(−(t−s)/τ) ds from the first sample (J); τ None = no loss (`heat_j`).

    Each step holds the mean of its two end losses: Q ← e^(−Δt/τ) Q + τ (1 − e^(−Δt/τ)) P̄.
    """
    if tau_s is None:
        return heat_j(t_s, power_w)
    t = np.asarray(t_s, dtype=float)
    p = np.broadcast_to(np.asarray(power_w, dtype=float), t.shape)
    q = np.zeros_like(t)
    if t.size > 1:
        dt = np.diff(t)
        decay = np.exp(-dt / tau_s)
        gain = tau_s * (1.0 - decay) * 0.5 * (p[1:] + p[:-1])
        acc = 0.0
        for k in range(dt.size):
            acc = decay[k] * acc + gain[k]
            q[k + 1] = acc
    return q


def _heat_capacity(p: FeedAxisParams) -> float:
    """ρ c V in J/K with the slide's volume, ρ c in J/(m³ K) without (η per m³)."""
    return p.rho_c_j_m3k * (p.slide_volume_m3 or 1.0)


def _midpoints_m(p: FeedAxisParams) -> np.ndarray:
    seg_m = p.length_mm / 1000.0 / p.segments
    return (np.arange(p.segments) + 0.5) * seg_m


def _erf_weights(t_s: np.ndarray, y_m: np.ndarray, a: float, erf_fn: ErfFn = erf) -> np.ndarray:
    """erf(y / (2 √(a t))) for each time (rows) and midpoint (columns); 1 at t ≤ 0."""
    t = np.asarray(t_s, dtype=float)[:, None]
    with np.errstate(divide="ignore"):
        s = np.where(t > 0, 0.5 / np.sqrt(a * np.maximum(t, 1e-300)), np.inf)
    return erf_fn(y_m[None, :] * s)


def error_basis(
    t_s, q_j, pos_mm, p: FeedAxisParams, chi: float, a: float, tau_s: float | None = None, erf_fn: ErfFn = erf
) -> np.ndarray:
    """E = ξ α ΔL [U1 f1 + U2 f2 + η f3] at each row's position: returns (f1, f2, f3) as n × 3 (µm/K·…).

    `tau_s` (duty-cycle form) scales the steady profile by Q/(τ P_ref); default: the params' τ.
    `erf_fn`: the error function; compd.models.erf's (the C library's) by default, a fit passes
    scipy's (faster on the large arrays a fit evaluates many times; equal to a few ulp)."""
    if tau_s is None:
        tau_s = p.cooling_time_s
    y = _midpoints_m(p)
    g = _erf_weights(t_s, y, a, erf_fn)
    h = 1.0 - g
    if tau_s is not None and p.ref_power_w is not None:  # the steady profile's share Q/(τ P_ref)
        h *= (np.asarray(q_j, float) / (tau_s * p.ref_power_w))[:, None]
    parts = np.stack(
        [h * np.exp(-chi * y), h * np.exp(chi * y), g * (np.asarray(q_j, float)[:, None] / _heat_capacity(p))],
        axis=2,
    )
    cum = np.cumsum(parts, axis=1)  # n × m × 3, sum over j ≤ i
    scale = p.alpha_per_k * (p.length_mm / p.segments) * 1000.0  # µm per K per segment
    return scale * _at_position(cum, np.asarray(pos_mm, float) - p.stroke_start_mm, p)


def _at_position(cum: np.ndarray, y_mm: np.ndarray, p: FeedAxisParams) -> np.ndarray:
    """Linear interpolation of per-midpoint sums at positions y (node 0 at y = 0 with value 0)."""
    seg = p.length_mm / p.segments
    u = np.clip(y_mm / seg - 0.5, -1.0, p.segments - 1.0)  # −1 is the y = 0 node
    j = np.floor(u).astype(int)
    j = np.minimum(j, p.segments - 2) if p.segments > 1 else np.full_like(j, -1)
    frac = u - j
    rows = np.arange(cum.shape[0])
    lo = np.where((j >= 0)[:, None], cum[rows, np.maximum(j, 0)], 0.0)
    hi = cum[rows, np.minimum(j + 1, p.segments - 1)]
    return lo + frac[:, None] * (hi - lo)


def position_weights(pos_mm: np.ndarray, p: FeedAxisParams) -> np.ndarray:
    """`_at_position` as weights (n × m): row r's value at its position is Σ_j W[r, j] x_j of the
    per-segment terms x (1 up to the segment below it, the interpolation's share of the next, 0
    beyond): a fit evaluating many shapes sums with one product instead of a cumulative sum each."""
    seg = p.length_mm / p.segments
    u = np.clip((np.asarray(pos_mm, float) - p.stroke_start_mm) / seg - 0.5, -1.0, p.segments - 1.0)
    j = np.floor(u).astype(int)
    j = np.minimum(j, p.segments - 2) if p.segments > 1 else np.full_like(j, -1)
    frac = u - j
    cols = np.arange(p.segments)[None, :]
    return np.where(cols <= j[:, None], 1.0, np.where(cols == (j + 1)[:, None], frac[:, None], 0.0))


def error_um(t_s, q_j, pos_mm, p: FeedAxisParams) -> np.ndarray:
    """E(t, y) in µm for arrays of heating time, heat and position (paper 000, eq. 21)."""
    assert p.chi_per_m is not None, "the analytic form's params (FeedAxisParams checks they are all given)"
    f = error_basis(np.atleast_1d(t_s), np.atleast_1d(q_j), np.atleast_1d(pos_mm), p, p.chi_per_m, p.diffusivity_m2_s)
    return p.xi * (f @ np.array([p.u1_k, p.u2_k, p.eta]))


def error_profile_um(t_s: float, q_j: float, p: FeedAxisParams, pos_mm: np.ndarray | None = None):
    """(positions mm, E µm) along the stroke at one heating time: the E(y) curve."""
    if pos_mm is None:
        pos_mm = p.stroke_start_mm + np.linspace(0.0, p.length_mm, 4 * p.segments + 1)
    pos_mm = np.asarray(pos_mm, dtype=float)
    n = pos_mm.size
    return pos_mm, error_um(np.full(n, t_s), np.full(n, q_j), pos_mm, p)


def linear_reduction(
    t_s: float, q_j: float, p: FeedAxisParams, p0_mm: float | None = None
) -> tuple[float, float, float]:
    """(K0 µm, tanβ µm/mm, P0 mm): E(t, y) ≈ K0 + tanβ (y − P0) over the stroke by least squares.

    For CNCs whose compensation is linear in position (Siemens SD43900/43910/43920, paper 001).
    P0 defaults to the stroke start.
    """
    y, e = error_profile_um(t_s, q_j, p)
    p0 = p.stroke_start_mm if p0_mm is None else p0_mm
    A = np.c_[np.ones_like(y), y - p0]
    (k0, tan_b), *_ = np.linalg.lstsq(A, e, rcond=None)
    return float(k0), float(tan_b), float(p0)


def field_nodes(p: FeedAxisParams) -> tuple[np.ndarray, np.ndarray]:
    """(node y from the stroke start in mm, the slide input each node reads) of the field form.

    The nodes are the sensors, plus the stroke's ends where no sensor stands there (they
    read the nearest sensor: the field is held flat beyond the first and the last)."""
    assert p.field is not None
    ys = np.asarray(p.field.slide_mm, float) - p.stroke_start_mm
    nodes, src = list(ys), list(range(ys.size))
    if ys[0] > 0.0:
        nodes.insert(0, 0.0)
        src.insert(0, 0)
    if ys[-1] < p.length_mm:
        nodes.append(p.length_mm)
        src.append(ys.size - 1)
    return np.asarray(nodes), np.asarray(src, dtype=np.intp)


def _cumulative_at(nodes: np.ndarray, cum: np.ndarray, rn: np.ndarray, y: np.ndarray) -> np.ndarray:
    """∫ from the first node to y of the piecewise-linear field (rows of `rn`, `cum` at nodes)."""
    y = np.clip(y, nodes[0], nodes[-1])
    j = np.clip(np.searchsorted(nodes, y, side="right") - 1, 0, nodes.size - 2)
    h = nodes[j + 1] - nodes[j]
    f = y - nodes[j]
    rows = np.arange(y.size)
    r0, r1 = rn[rows, j], rn[rows, j + 1]
    return cum[rows, j] + f * (r0 + 0.5 * (r1 - r0) * f / h)


def field_terms(rises_k: np.ndarray, y_mm: np.ndarray, ambient_k: np.ndarray | None, p: FeedAxisParams) -> np.ndarray:
    """(I, R, A, C) of the field form in µm, n × 4, at positions y from the stroke start (mm).

    `rises_k`: n × K rises of the slide sensors; `ambient_k`: n rises of the ambient (None: A = 0)."""
    nodes, src = field_nodes(p)
    rn = np.asarray(rises_k, float)[:, src]
    cum = np.zeros_like(rn)
    cum[:, 1:] = np.cumsum(0.5 * (rn[:, 1:] + rn[:, :-1]) * np.diff(nodes), axis=1)
    y = np.clip(np.asarray(y_mm, float), 0.0, p.length_mm)
    start = _cumulative_at(nodes, cum, rn, np.zeros_like(y))
    integral = _cumulative_at(nodes, cum, rn, y) - start
    total = _cumulative_at(nodes, cum, rn, np.full_like(y, p.length_mm)) - start
    um_per_k_mm = p.alpha_per_k * 1000.0
    amb = np.zeros_like(y) if ambient_k is None else np.asarray(ambient_k, float) * y
    return um_per_k_mm * np.column_stack([integral, total * y / p.length_mm, amb, total])


class _Measured:
    """What both measured forms share: the position input, the readings at start T_k0 and the
    rises of the inputs of one role, taken into preallocated buffers (no allocation per cycle)."""

    def __init__(self, p: FeedAxisParams, role: str) -> None:
        roles = p.input_roles
        self.p = p
        self.i_pos = roles.index("position")
        self.i_rise = _role_indices(roles, role)
        self.t0 = np.zeros(len(roles))
        self.t0_rise = np.zeros(self.i_rise.size)
        self.rise = np.zeros(self.i_rise.size)
        self.lin: np.ndarray | None = None  # (K0, tanβ) = lin @ (…) with linear_p0_mm
        self.k0_slope = np.zeros(2)

    def start(self, x: np.ndarray) -> None:
        """Latch the readings at start (the references of every rise)."""
        self.t0[:] = x
        np.take(self.t0, self.i_rise, out=self.t0_rise)

    def _rises(self, x: np.ndarray) -> np.ndarray:
        np.take(x, self.i_rise, out=self.rise)
        self.rise -= self.t0_rise
        return self.rise


def _role_indices(roles: Sequence[str], role: str) -> np.ndarray:
    return np.array([i for i, r in enumerate(roles) if r == role], dtype=np.intp)


class _FieldForm(_Measured):
    """Run-time evaluation of the field form."""

    def __init__(self, p: FeedAxisParams) -> None:
        f = p.field
        assert f is not None
        super().__init__(p, "slide")
        roles = p.input_roles
        self.i_slide = self.i_rise
        self.i_off = _role_indices(roles, "offset")
        self.t0_off = np.zeros(self.i_off.size)
        self.i_amb = roles.index("ambient") if "ambient" in roles else -1
        self.nodes, self.src = field_nodes(p)
        self.node_list = [float(v) for v in self.nodes]
        self.half_dy = 0.5 * np.diff(self.nodes)
        self.gain = np.array([f.gain_integral, f.gain_restraint, f.gain_ambient, f.gain_constant])
        self.b_off = np.asarray(f.offset_um_per_k, float)
        self.um_per_k_mm = p.alpha_per_k * 1000.0
        self.rn = np.zeros(self.nodes.size)
        self.trap = np.zeros(self.nodes.size - 1)
        self.cum = np.zeros(self.nodes.size)
        self.off = np.zeros(self.i_off.size)
        self.v = np.zeros(self.i_slide.size + 1 + self.i_off.size)
        if p.linear_p0_mm is not None:
            self.lin = self._linear_matrix(p, p.linear_p0_mm)

    def _linear_matrix(self, p: FeedAxisParams, p0_mm: float) -> np.ndarray:
        """M with (K0, tanβ) = M v, v = (slide rises, ambient rise, offset rises): E is linear in v."""
        y = np.linspace(0.0, p.length_mm, p.segments + 1)
        k = self.i_slide.size
        cols = []
        for j in range(k):  # a unit rise of slide sensor j
            r = np.zeros((y.size, k))
            r[:, j] = 1.0
            cols.append(field_terms(r, y, None, p) @ self.gain)
        cols.append(field_terms(np.zeros((y.size, k)), y, np.ones_like(y), p) @ self.gain)
        cols += [np.full_like(y, b) for b in self.b_off]
        W = np.column_stack(cols)
        P = np.c_[np.ones_like(y), p.stroke_start_mm + y - p0_mm]
        return np.linalg.pinv(P) @ W

    def start(self, x: np.ndarray) -> None:
        super().start(x)
        np.take(self.t0, self.i_off, out=self.t0_off)

    def evaluate(self, x: np.ndarray) -> float:
        """E at the position in x, µm; with linear_p0_mm K0 (tanβ in k0_slope[1])."""
        self._rises(x)
        amb = x[self.i_amb] - self.t0[self.i_amb] if self.i_amb >= 0 else 0.0
        off = 0.0
        if self.i_off.size:
            np.take(x, self.i_off, out=self.off)
            self.off -= self.t0_off
            off = float(self.b_off @ self.off)
        if self.lin is not None:
            v, k = self.v, self.rise.size
            v[:k] = self.rise
            v[k] = amb
            v[k + 1 :] = self.off
            np.dot(self.lin, v, out=self.k0_slope)
            return float(self.k0_slope[0])
        p = self.p
        np.take(self.rise, self.src, out=self.rn)
        rn, cum = self.rn, self.cum
        np.add(rn[1:], rn[:-1], out=self.trap)
        self.trap *= self.half_dy
        np.cumsum(self.trap, out=cum[1:])
        y = min(max(x[self.i_pos] - p.stroke_start_mm, 0.0), p.length_mm)
        at_y, at_0, at_l = self._c(y), self._c(0.0), self._c(p.length_mm)
        g = self.gain
        s = self.um_per_k_mm
        total = at_l - at_0
        return s * (g[0] * (at_y - at_0) + g[1] * total * y / p.length_mm + g[2] * amb * y + g[3] * total) + off

    def _c(self, y: float) -> float:
        """∫ from the first node to y of the field held in rn, cum."""
        nodes = self.node_list
        y = min(max(y, nodes[0]), nodes[-1])
        j = min(max(bisect.bisect_right(nodes, y) - 1, 0), len(nodes) - 2)
        h = nodes[j + 1] - nodes[j]
        f = y - nodes[j]
        r0, r1 = self.rn[j], self.rn[j + 1]
        return float(self.cum[j] + f * (r0 + 0.5 * (r1 - r0) * f / h))

    def predict(self, X: np.ndarray) -> np.ndarray:
        """E at each row's position (also with linear_p0_mm, as the analytic form), from the readings t0."""
        p = self.p
        R = X[:, self.i_slide] - self.t0[self.i_slide]
        amb = X[:, self.i_amb] - self.t0[self.i_amb] if self.i_amb >= 0 else None
        off = (X[:, self.i_off] - self.t0[self.i_off]) @ self.b_off if self.i_off.size else 0.0
        y = X[:, self.i_pos] - p.stroke_start_mm
        return field_terms(R, y, amb, p) @ self.gain + off


class _PolyForm(_Measured):
    """Run-time evaluation of the position-regression form."""

    def __init__(self, p: FeedAxisParams) -> None:
        poly = p.position_poly
        assert poly is not None
        super().__init__(p, "rise")
        self.B = np.asarray(poly.coef_um_per_k, float)  # K × (d + 1)
        self.c = np.zeros(poly.degree + 1)  # Σ_k ΔT_k b_kp per power p
        self.u = np.zeros(poly.degree + 1)
        if p.linear_p0_mm is not None:  # (K0, tanβ) = M c: E(y) is a polynomial with coefficients c
            y = np.linspace(0.0, p.length_mm, p.segments + 1)
            U = (y[:, None] / p.length_mm) ** np.arange(poly.degree + 1)
            P = np.c_[np.ones_like(y), p.stroke_start_mm + y - p.linear_p0_mm]
            self.lin = np.linalg.pinv(P) @ U

    def evaluate(self, x: np.ndarray) -> float:
        np.dot(self._rises(x), self.B, out=self.c)
        if self.lin is not None:
            np.dot(self.lin, self.c, out=self.k0_slope)
            return float(self.k0_slope[0])
        p = self.p
        u = min(max(x[self.i_pos] - p.stroke_start_mm, 0.0), p.length_mm) / p.length_mm
        v = 1.0
        for k in range(self.u.size):  # 1, u, u², … without an array per cycle
            self.u[k] = v
            v *= u
        return float(self.c @ self.u)

    def predict(self, X: np.ndarray) -> np.ndarray:
        p = self.p
        R = X[:, self.i_rise] - self.t0[self.i_rise]
        u = np.clip(X[:, self.i_pos] - p.stroke_start_mm, 0.0, p.length_mm) / p.length_mm
        return np.sum((R @ self.B) * u[:, None] ** np.arange(self.B.shape[1]), axis=1)


class FeedAxis(Model):
    """Position-dependent feed-axis error E(t, y) of a linear-motor axis (paper 000)."""

    kind = "feed_axis"
    summary_keys = (
        "eta",
        "u1_k",
        "u2_k",
        "chi_per_m",
        "xi",
        "alpha_per_k",
        "length_mm",
        "cooling_time_s",
        "linear_p0_mm",
        "field",
        "position_poly",
    )
    Params = FeedAxisParams
    params: FeedAxisParams

    def __init__(self, params: FeedAxisParams, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        p = params
        roles = p.input_roles
        self._i_pos = roles.index("position")
        self._i_cur = roles.index("current") if "current" in roles else -1
        self._i_mot = roles.index("motor_temp") if "motor_temp" in roles else -1
        self._i_amb = roles.index("ambient") if "ambient" in roles else -1
        self._field: _FieldForm | _PolyForm | None = None  # a measured form (compd's), else the analytic
        if p.field is not None:
            self._field = _FieldForm(p)
        elif p.position_poly is not None:
            self._field = _PolyForm(p)
        self._field_started = False
        y = _midpoints_m(p)
        self._y_m = y
        if self._field is None:
            assert p.chi_per_m is not None and p.u1_k is not None and p.u2_k is not None
            self._hds = p.u2_k * np.exp(p.chi_per_m * y) + p.u1_k * np.exp(-p.chi_per_m * y)
        else:
            self._hds = np.zeros_like(y)
        self._buf = np.zeros(p.segments)
        self._cum = np.zeros(p.segments)
        self._seg_mm = p.length_mm / p.segments
        self._scale = p.xi * p.alpha_per_k * self._seg_mm * 1000.0
        self._inv_rho_c = (p.eta or 0.0) / _heat_capacity(p)
        self._tau = p.cooling_time_s
        # (the params give ref_power_w with cooling_time_s)
        self._steady_per_j = 1.0 / (p.cooling_time_s * p.ref_power_w) if p.cooling_time_s and p.ref_power_w else 0.0
        # the motor's loss without a current input: constant (the params give power_w then)
        self._power_w = 0.0 if p.power_w is None else float(p.power_w)
        self._hds_now = self._hds.copy()
        self.t_start_s: float | None = None
        self.heat_j = 0.0
        self._t_prev = 0.0
        self._p_prev = 0.0
        self._restore: tuple[float, float] | None = None
        # linear reduction E ≈ K0 + tanβ (y − P0), least squares over the segment midpoints
        self._lin: np.ndarray | None = None
        self.slope_um_per_mm = 0.0
        if p.linear_p0_mm is not None:
            y_mm = p.stroke_start_mm + y * 1000.0
            self._lin = np.linalg.pinv(np.c_[np.ones_like(y_mm), y_mm - p.linear_p0_mm])

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        if len(inputs) != len(params.input_roles):
            raise BadInput(
                f"has {len(params.input_roles)} roles ({', '.join(params.input_roles)})"
                f" but the model has {len(inputs)} inputs (one role per input)",
                path=("params", "input_roles"),
            )
        if len(outputs) != 1:
            raise BadInput(f"feed_axis has one output axis, got {len(outputs)}", path=("outputs",))

    def _power(self, x: np.ndarray) -> float:
        p = self.params
        if self._field is not None:
            return 0.0
        if self._i_cur < 0:
            return self._power_w
        i = x[self._i_cur]
        corr = 1.0
        if self._i_mot >= 0 and self._i_amb >= 0:
            corr += p.zeta_per_k * (x[self._i_mot] - x[self._i_amb])
        return 3.0 * i * i * p.r_cu_ohm * corr

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self._field is not None and not self._field_started:  # T_k0: the readings at start
            self._field.start(x)
            self._field_started = True
        if self._restore is not None:
            heating_s, self.heat_j = self._restore
            self.t_start_s = t_s - heating_s
            self._restore = None
        elif self.t_start_s is None:
            self.t_start_s = t_s
        self._t_prev = t_s
        self._p_prev = self._power(x)

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """E(t, y) at the current position (eq. 21); heat integrated by the trapezoid rule.

        Field form: E from the measured field (module doc); with linear_p0_mm K0 and tanβ."""
        if self._field is not None:
            out[0] = self._field.evaluate(x)
            if self._field.lin is not None:
                self.slope_um_per_mm = float(self._field.k0_slope[1])
            self._t_prev = t_s
            return
        pw = self._power(x)
        dt = t_s - self._t_prev
        if self._tau is None:
            self.heat_j += 0.5 * (pw + self._p_prev) * dt
        else:
            decay = math.exp(-dt / self._tau)
            self.heat_j = decay * self.heat_j + self._tau * (1.0 - decay) * 0.5 * (pw + self._p_prev)
        self._p_prev = pw
        self._t_prev = t_s
        assert self.t_start_s is not None  # `start` set it
        t = t_s - self.t_start_s
        if t <= 0.0:
            out[0] = 0.0
            return
        buf, cum = self._buf, self._cum
        np.multiply(self._y_m, 0.5 / math.sqrt(self.params.diffusivity_m2_s * t), out=buf)
        erf_inplace(buf)
        hps = self._inv_rho_c * self.heat_j
        hds = self._hds
        if self._tau is not None:  # duty-cycle form: the steady profile follows the mean loss
            hds = self._hds_now
            np.multiply(self._hds, self._steady_per_j * self.heat_j, out=hds)
        # T − T_fo = hds + erf (hps − hds) = hds (1 − erf) + erf hps
        np.subtract(hps, hds, out=cum)
        cum *= buf
        cum += hds
        np.cumsum(cum, out=cum)
        if self._lin is not None:  # the line at P0; the CNC adds tanβ (P − P0)
            k0, slope = self._lin @ cum
            self.slope_um_per_mm = float(self._scale * slope)
            out[0] = self._scale * float(k0)
            return
        u = (x[self._i_pos] - self.params.stroke_start_mm) / self._seg_mm - 0.5
        m = self.params.segments
        if u <= -1.0:
            out[0] = 0.0
        elif u >= m - 1:
            out[0] = self._scale * cum[m - 1]
        elif u < 0.0:
            out[0] = self._scale * (u + 1.0) * cum[0]
        else:
            j = int(u)
            f = u - j
            out[0] = self._scale * (cum[j] + f * (cum[j + 1] - cum[j]))

    def linear_terms(self) -> list[tuple[float, float]] | None:
        """[(tanβ µm/mm, P0 mm)] of the last evaluation when `linear_p0_mm` is set (Siemens sink)."""
        if self._lin is None:
            return None
        return [(self.slope_um_per_mm, float(self.params.linear_p0_mm or 0.0))]

    def predict_rows(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Vectorised over rows: heat by the trapezoid rule, then eq. 21 at each row.

        E is taken at each row's position, also with linear_p0_mm.
        """
        n = X.shape[0]
        if n == 0:
            return np.zeros((0, 1))
        t = np.asarray(t_s, dtype=float)
        self.start(X[0], float(t[0]))
        if self._field is not None:
            self._t_prev = float(t[-1])
            return self._field.predict(X)[:, None]
        pw = np.array([self._power(row) for row in X])
        q = leaky_heat_j(t, pw, self._tau)
        if self.heat_j:  # heat from before this block, leaking on
            q = q + self.heat_j * (np.exp(-(t - t[0]) / self._tau) if self._tau else 1.0)
        out = error_um(t - self.t_start_s, q, X[:, self._i_pos], self.params)[:, None]
        self.heat_j = float(q[-1])
        self._t_prev, self._p_prev = float(t[-1]), float(pw[-1])
        return out

    @property
    def field_form(self) -> bool:
        """True for compd's measured forms (field, position_poly), False for the paper's analytic form."""
        return self._field is not None

    def field_profile_um(self, X: np.ndarray, x: np.ndarray, pos_mm: np.ndarray) -> np.ndarray:
        """Field form: E along `pos_mm` with the readings `x`, the references being the first row of X (for reports)."""
        assert self._field is not None
        self._field.start(X[0])
        rows = np.repeat(np.asarray(x, float)[None, :], len(pos_mm), axis=0)
        rows[:, self._i_pos] = pos_mm
        return self._field.predict(rows)

    def heating(self, X: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(heating time s, heat J) at each row of a log, from its first row (for reports)."""
        t = np.asarray(t_s, dtype=float)
        pw = np.array([self._power(row) for row in X])
        return t - t[0], leaky_heat_j(t, pw, self._tau)

    def get_state(self) -> dict[str, Any]:
        if self._field is not None:  # the field form's memory is its reference readings
            return {"t0_c": [float(v) for v in self._field.t0] if self._field_started else None}
        heating = None if self.t_start_s is None else self._t_prev - self.t_start_s
        return {"heating_s": heating, "heat_j": self.heat_j}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        """Resume the heating run: the outage counts as heating time without heat input
        (in the duty-cycle form the slide also cools by e^(−outage/τ)). The field form keeps
        its reference readings: the machine is still in the run it started from."""
        if self._field is not None:
            t0 = state.get("t0_c")
            if isinstance(t0, list) and len(t0) == self._field.t0.size:
                self._field.start(np.asarray(t0, dtype=float))
                self._field_started = True
            return
        if state.get("heating_s") is not None:
            gap = max(elapsed_s, 0.0)
            q = float(state.get("heat_j", 0.0))
            if self._tau is not None:
                q *= math.exp(-gap / self._tau)
            self._restore = (float(state["heating_s"]) + gap, q)
