"""ξ-point spindle model, axial ΔL = α L [T(ξ) − T0] and radial bearing-ring model (paper 003)."""
# Centrifugal lift (paper 003 §3.4): the balls' centrifugal force pushes the rotor along its
# axis by k·n², but never further than the axial clearance that the preload loss has opened.
# The paper gives no formula for that clearance; its eq. 29 does: the inner ring carries the
# balls share·ΔL (0.8 ΔL) along the axis away from the outer raceway, and eq. 32's radial
# clearance c = share·ΔL·tan θ is the radial leg of that move. Its axial leg, share·ΔL, is the
# play the rotor has along its axis before the balls bear on the raceway at the original
# preload again: `axial_clearance_um`. Only the growth between the bearings (share) counts,
# because growth ahead of the front bearing moves the nose, not the rings. A shrinking
# rotor (ΔL ≤ 0) raises the preload and opens nothing.

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.core.errors import BadInput
from compd.models.base import MAX_LENGTH_MM, TEMP_MAX_C, TEMP_MIN_C, LeadParams, Model, ModelParams


def axial_growth_um(t_xi_c: float | np.ndarray, t0_c: float, alpha_per_k: float, length_mm: float):
    """Axial growth ΔL = α L (T(ξ) − T0) in µm (paper 003, eq. 2; L in mm → ×1000)."""
    return alpha_per_k * length_mm * 1000.0 * (np.asarray(t_xi_c) - t0_c)


def ring_integral(t_in: float, t_out: float, a_mm: float, b_mm: float) -> float:
    """∫_a^b T(r) r dr (K·mm²) for T linear in r from t_in at r = a to t_out at r = b."""
    s = (t_out - t_in) / (b_mm - a_mm)
    return (t_in - s * a_mm) * (b_mm**2 - a_mm**2) / 2.0 + s * (b_mm**3 - a_mm**3) / 3.0


def ring_displacement_um(
    r_mm: float,
    a_mm: float,
    b_mm: float,
    r_nodes_mm: np.ndarray,
    dt_nodes_k: np.ndarray,
    alpha_per_k: float,
    mu: float,
) -> float:
    """Radial displacement u(r) of a ring a ≤ r ≤ b with temperature rise T(r) (paper 003, eq. 8), µm.

    u(r) = α/r [(1+μ) ∫_a^r T r' dr' + ((1−μ) r² + (1+μ) a²)/(b² − a²) ∫_a^b T r' dr'];
    T(r) is given at nodes and integrated by the trapezoid rule. A uniform rise ΔT gives α r ΔT.
    """
    r_nodes = np.asarray(r_nodes_mm, dtype=float)
    f = np.asarray(dt_nodes_k, dtype=float) * r_nodes
    total = float(np.trapezoid(f, r_nodes))
    inside = r_nodes <= r_mm
    rr = np.r_[r_nodes[inside], r_mm]
    ff = np.r_[f[inside], np.interp(r_mm, r_nodes, f)]
    part = float(np.trapezoid(ff, rr))
    u_mm = (
        alpha_per_k / r_mm * ((1 + mu) * part + ((1 - mu) * r_mm**2 + (1 + mu) * a_mm**2) / (b_mm**2 - a_mm**2) * total)
    )
    return u_mm * 1000.0


def inner_ring_um(
    dt_in_k: float, dt_out_k: float, r_a_mm: float, r_b_mm: float, alpha_per_k: float, mu: float
) -> float:
    """u_B: inner ring (a = r_A, b = r_B) at its outer surface r_B, linear T(r), µm (paper 003)."""
    i = ring_integral(dt_in_k, dt_out_k, r_a_mm, r_b_mm)
    k = (1 + mu) + ((1 - mu) * r_b_mm**2 + (1 + mu) * r_a_mm**2) / (r_b_mm**2 - r_a_mm**2)
    return alpha_per_k / r_b_mm * k * i * 1000.0


def outer_ring_um(dt_in_k: float, dt_out_k: float, r_c_mm: float, r_d_mm: float, alpha_per_k: float) -> float:
    """u_C = 2 α r_C/(r_D² − r_C²) ∫_{r_C}^{r_D} T r dr: outer ring at its inner surface, µm (paper 003)."""
    i = ring_integral(dt_in_k, dt_out_k, r_c_mm, r_d_mm)
    return 2.0 * alpha_per_k * r_c_mm / (r_d_mm**2 - r_c_mm**2) * i * 1000.0


def clearance_um(dl_um: float, d_w_mm: float, f: float, contact_deg: float = 18.0, share: float = 0.8) -> float:
    """Radial clearance opened by preload loss from an axial growth ΔL (paper 003, eqs. 11–13), µm.

    α' = arcsin(sin α0 − share·ΔL / (D_w (f − 0.5))), θ = (180° − (α0 − α'))/2 − (90° − α0),
    c = share·ΔL·tan θ. α0 = 18° gives the paper's 72°. ΔL in µm (converted to mm inside).
    """
    dl_mm = dl_um / 1000.0
    arg = math.sin(math.radians(contact_deg)) - share * dl_mm / (d_w_mm * (f - 0.5))
    arg = min(1.0, max(-1.0, arg))
    a1 = math.degrees(math.asin(arg))
    theta = (180.0 - (contact_deg - a1)) / 2.0 - (90.0 - contact_deg)
    return share * dl_um * math.tan(math.radians(theta))


def axial_clearance_um(dl_um: float, share: float = 0.8) -> float:
    """Axial clearance opened by preload loss from an axial growth ΔL: share·max(ΔL, 0), µm (paper 003 eq. 29)."""
    return share * max(dl_um, 0.0)


def lift_um(k_um_per_rpm2: float, speed_rpm: float, dl_um: float, share: float = 0.8) -> float:
    """Centrifugal lift min(k n², share·ΔL), never < 0, µm (paper 003 §3.4: bounded by the axial clearance)."""
    return max(0.0, min(k_um_per_rpm2 * speed_rpm * speed_rpm, axial_clearance_um(dl_um, share)))


class RadialParams(ModelParams):
    """Radial model of one angular-contact bearing (paper 003; defaults: 7010 CETA).

    E = g_C u_C − g_B u_B + c(ΔL) (µm). Paper 003 eq. 18 has g_C = g_B = 1: the outer ring
    uniform at its seat temperature, the inner ring at the rotor journal's. `compd fit`
    writes compd's form by default: the two per-ring gains fitted by least squares (≥ 0)
    on the radial error that c leaves in the training log, because the sensors compd has
    (one on the outer ring's seat, the ξ sensor on the rotor) do not read the rings' own
    temperature fields (the raceways sit at the balls' temperature, the nose bearing's
    journal runs warmer than ξ). Each gain then also takes up what the other ring's unread
    temperature shares with its sensor, so the gains are least-squares weights, not ring
    temperatures. c is the paper's, unscaled: it follows from ΔL, which the axial fit calibrates.
    Files without the gains (written before them) are the paper's form.

    Ranges: radii and ball in (0, 1000] mm (a bearing, not a machine); α in (0, 1e-3) /K;
    Poisson's μ in (0, 0.5); gains in [0, 10]. `k_um_per_rpm2` is the centrifugal lift as
    files written before the top-level `lift` section meant it: k·n² uncapped on the radial
    output, the speed the last input. Such files keep that meaning; `compd fit` puts the
    lift where paper 003 §3.4 does, in `lift` (axial, capped by the axial clearance).
    """

    r_a_mm: float = Field(25.0, gt=0, le=1000, description="inner ring bore radius")
    r_b_mm: float = Field(27.34, gt=0, le=1000, description="inner ring outer (raceway) radius")
    r_c_mm: float = Field(37.66, gt=0, le=1000, description="outer ring inner (raceway) radius")
    r_d_mm: float = Field(40.0, gt=0, le=1000, description="outer ring outer radius")
    alpha_per_k: float = Field(11.5e-6, gt=0, lt=1e-3, description="bearing steel α")
    mu: float = Field(0.26, gt=0, lt=0.5, description="Poisson's ratio")
    d_w_mm: float = Field(10.319, gt=0, le=1000, description="ball diameter D_w")
    f: float = Field(0.53, gt=0.5, lt=1, description="raceway groove radius ratio")
    contact_deg: float = Field(18.0, gt=0, lt=90, description="initial contact angle")
    preload_share: float = Field(0.8, ge=0, le=1, description="share of ΔL between the bearings")
    clearance: bool = Field(True, description="add the preload-loss clearance term c")
    inner_sensors: int = Field(
        1,
        ge=0,
        le=2,
        description="0: uniform ring at the ξ sensor's (rotor) temperature; 1: uniform ring; 2: T at bore and raceway",
    )
    outer_sensors: int = Field(1, ge=1, le=2, description="1: uniform ring; 2: T at raceway and OD")
    inner_gain: float = Field(
        1.0,
        ge=0,
        le=10,
        description="g_B on the inner ring's u_B: 1 = paper 003; compd fit writes the least-squares gain",
    )
    outer_gain: float = Field(
        1.0,
        ge=0,
        le=10,
        description="g_C on the outer ring's u_C: 1 = paper 003; compd fit writes the least-squares gain",
    )
    k_um_per_rpm2: float | None = Field(
        None,
        ge=0,
        le=1e-3,
        description="older files' lift k·n² (µm/rpm²), uncapped on the radial output, speed the last input;"
        " new models carry the lift in the top-level `lift` (axial, paper 003 §3.4)",
    )

    @model_validator(mode="after")
    def _radii(self) -> RadialParams:
        if not self.r_a_mm < self.r_b_mm < self.r_c_mm < self.r_d_mm:
            raise ValueError("radii must satisfy r_a < r_b < r_c < r_d")
        return self

    @property
    def n_inputs(self) -> int:
        return self.inner_sensors + self.outer_sensors + (self.k_um_per_rpm2 is not None)


class LiftParams(ModelParams):
    """Centrifugal lift of the rotor on the axial output (paper 003 §3.4), µm.

    lift = min(k n², share·max(ΔL, 0)): the balls' centrifugal force lifts the rotor along
    its axis in proportion to n², never further than the axial clearance the preload loss
    has opened. n is the input named `speed_input` (rpm), ΔL the ξ-point growth.
    Ranges: k in [0, 1e-3] µm/rpm² (≥ 0: centrifugal force lifts), share in [0, 1].
    """

    k_um_per_rpm2: float = Field(ge=0, le=1e-3, description="lift per rpm² below the cap, µm/rpm²")
    speed_input: str = Field(
        "speed_rpm", min_length=1, description="the model input that carries the spindle speed (rpm)"
    )
    preload_share: float = Field(
        0.8, ge=0, le=1, description="share of ΔL between the bearings: the axial clearance (the cap) is share·ΔL"
    )


class XiSpindleParams(LeadParams):
    """Parameters of the axial ξ-point model (α in (0, 1e-3) /K, lengths in (0, 100 m])."""

    alpha_per_k: float = Field(gt=0, lt=1e-3, description="linear expansion coefficient, 1/K")
    length_mm: float = Field(gt=0, le=MAX_LENGTH_MM, description="spindle length L over which ξ averages")
    t0_c: float | None = Field(
        None, ge=TEMP_MIN_C, le=TEMP_MAX_C, description="reference temperature; none = first reading at start"
    )
    xi_mm: float | None = Field(None, ge=0, le=MAX_LENGTH_MM, description="where the sensor sits (documentation)")
    axial_sign: Literal[1, -1] = Field(
        1,
        description="the direction the spindle grows in on the axis, in machine coordinates: +1 toward the"
        " axis's + direction (the papers' case), -1 toward its - direction (e.g. a vertical spindle growing"
        " down toward the table, Z+ pointing away from the workpiece as ISO 841 has it)",
    )
    lift: LiftParams | None = Field(
        None, description="add the centrifugal lift to the axial output; takes the speed input it names"
    )
    radial: RadialParams | None = Field(None, description="add a radial output: inputs [T_xi, inner ring, outer ring]")

    @model_validator(mode="after")
    def _one_lift(self) -> XiSpindleParams:
        rad = self.radial
        if self.lift is not None and rad is not None:
            if rad.k_um_per_rpm2 is not None:
                raise ValueError("lift and radial.k_um_per_rpm2 (the older files' radial lift) cannot both be set")
            if self.lift.preload_share != rad.preload_share:
                raise ValueError(
                    f"lift.preload_share {self.lift.preload_share:g} differs from radial.preload_share"
                    f" {rad.preload_share:g}: both are the share of ΔL between the same bearings"
                )
        return self


class XiSpindle(Model):
    """ξ-point model: axial output from the ξ sensor (plus the lift); optional radial output from the rings.

    Inputs: T_xi, then with `radial` the inner ring sensor(s) and outer ring sensor(s) (and
    the speed last for an older file's radial `k_um_per_rpm2`), in that order; with `lift`,
    also the speed input it names, anywhere in the list. Outputs: [axial] or [axial, radial].
    """

    kind = "xi_spindle"
    summary_keys = ("alpha_per_k", "length_mm", "xi_mm", "t0_c", "lift")
    Params = XiSpindleParams
    params: XiSpindleParams

    def __init__(self, params: XiSpindleParams, inputs: list[str], outputs: list[str], fit=None):
        super().__init__(params, inputs, outputs, fit)
        self._gain_um_per_k = params.alpha_per_k * params.length_mm * 1000.0
        self._sign = float(params.axial_sign)  # the growth's direction on the axis (and the lift's with it)
        self.t0_c: float | None = params.t0_c
        self.ref_c: np.ndarray | None = None  # references of the ring sensors
        self._ref: list[float] = []  # the same, as Python floats for evaluate
        # positions in x of T_xi, the ring sensors (and a legacy radial speed); the lift's speed
        self._speed = inputs.index(params.lift.speed_input) if params.lift else -1
        self._pos = [i for i in range(len(inputs)) if i != self._speed]

    @classmethod
    def check_wiring(cls, params, inputs, outputs) -> None:
        super().check_wiring(params, inputs, outputs)
        rad, lift = params.radial, params.lift
        if lift is not None and lift.speed_input not in inputs:
            raise BadInput(
                f"names {lift.speed_input!r}, which is not among the model's inputs ({', '.join(inputs)})",
                path=("params", "lift", "speed_input"),
            )
        need_in = 1 + (rad.n_inputs if rad else 0) + (lift is not None)
        need_out = 2 if rad else 1
        if len(inputs) != need_in:
            what = "the ξ sensor" + (", ring sensors" if rad else "") + (", the speed" if lift else "")
            raise BadInput(f"xi_spindle takes {need_in} inputs ({what}), got {len(inputs)}", path=("inputs",))
        if len(outputs) != need_out:
            raise BadInput(
                f"xi_spindle has {need_out} output axes (axial{', radial' if rad else ''}), got {len(outputs)}",
                path=("outputs",),
            )

    def start(self, x: np.ndarray, t_s: float) -> None:
        if self.t0_c is None:
            self.t0_c = float(x[self._pos[0]])
        if self.params.radial is not None and self.ref_c is None:
            self.ref_c = np.array(x, dtype=float)
            self._ref = self.ref_c.tolist()

    def evaluate(self, x: np.ndarray, t_s: float, out: np.ndarray) -> None:
        """Axial s·(ΔL [+ min(k n², share·ΔL)]), ΔL = α L (T(ξ) − T0), s = `axial_sign`; radial
        E = g_C u_C − g_B u_B + c(ΔL) (paper 003), µm.

        An older file's radial `k_um_per_rpm2` adds k n² uncapped to E instead.
        """
        xs = x.tolist()  # Python floats: cheaper arithmetic than numpy scalars, cycle after cycle
        p = self._pos
        dl = self._gain_um_per_k * (xs[p[0]] - self.t0_c)
        lift = self.params.lift
        if lift is None:
            out[0] = self._sign * dl
        else:  # lift_um inlined: min(k n², share·max(ΔL, 0)), k ≥ 0
            n = xs[self._speed]
            kn2 = lift.k_um_per_rpm2 * n * n
            cap = lift.preload_share * dl if dl > 0.0 else 0.0
            out[0] = self._sign * (dl + (kn2 if kn2 < cap else cap))
        rad = self.params.radial
        if rad is None:
            return
        ref = self._ref
        k = 1
        if rad.inner_sensors == 0:  # paper 003: the inner ring is at the rotor journal's temperature
            ti = to = xs[p[0]] - ref[p[0]]
        else:
            ti = xs[p[k]] - ref[p[k]]
            to = xs[p[k + 1]] - ref[p[k + 1]] if rad.inner_sensors == 2 else ti
        k += rad.inner_sensors
        oi = xs[p[k]] - ref[p[k]]
        oo = xs[p[k + 1]] - ref[p[k + 1]] if rad.outer_sensors == 2 else oi
        k += rad.outer_sensors
        e = rad.outer_gain * outer_ring_um(oi, oo, rad.r_c_mm, rad.r_d_mm, rad.alpha_per_k) - (
            rad.inner_gain * inner_ring_um(ti, to, rad.r_a_mm, rad.r_b_mm, rad.alpha_per_k, rad.mu)
        )
        if rad.clearance:
            e += clearance_um(dl if dl > 0.0 else 0.0, rad.d_w_mm, rad.f, rad.contact_deg, rad.preload_share)
        if rad.k_um_per_rpm2 is not None:  # an older file's lift: uncapped, radial
            n = xs[p[k]]
            e += rad.k_um_per_rpm2 * n * n
        out[1] = e

    def get_state(self) -> dict[str, Any]:
        ref = None if self.ref_c is None else [float(v) for v in self.ref_c]
        return {"t0_c": self.t0_c, "ref_c": ref}

    def set_state(self, state: dict[str, Any], elapsed_s: float = 0.0) -> None:
        if self.params.t0_c is None and state.get("t0_c") is not None:
            self.t0_c = float(state["t0_c"])
        ref = state.get("ref_c")
        if ref is not None and len(ref) == len(self.inputs):
            self.ref_c = np.asarray(ref, dtype=float)
            self._ref = self.ref_c.tolist()
