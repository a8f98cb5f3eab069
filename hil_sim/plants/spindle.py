"""Motorized spindle (paper 003): rotor and housing rods, bearings, stator, coolant jacket.

Axial error: the rotor's free growth α ∫ (T − T_init) dx (paper 003 eq. 1; the
ξ-point model estimates it from one sensor, which this plant places at the mean-value
point of its own steady-state rotor field), plus the rotor's centrifugal lift (paper 003
§3.4): the balls' centrifugal force, wedged against the outer raceway at the contact
angle, pushes the inner ring along the axis against the bearing's axial stiffness, but
no further than the axial play the growth between the bearings has opened. Radial error
at the front bearing (paper 003 §2): ring thermoelastic displacement u = u_C − u_B from
the rings' radial temperature profiles, plus the clearance c opened by the preload loss
that the axial growth between the bearings causes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil_sim.network import Network
from hil_sim.plants.base import Plant
from hil_sim.scenario import Segment


def ring_displacement_um(
    r_mm: float, a_mm: float, b_mm: float, rise_c: np.ndarray, alpha_per_k: float, mu: float
) -> float:
    """Radial displacement u(r) of a free ring a ≤ r ≤ b with temperature rise T(r) (µm).

    u(r) = α/r [(1+μ) ∫_a^r T r' dr' + ((1−μ) r² + (1+μ) a²)/(b² − a²) ∫_a^b T r' dr']
    (paper 003 eq. 6, plane stress). `rise_c` samples T on an even grid from a to b.
    Uniform T gives α r ΔT.
    """
    rr = np.linspace(a_mm, b_mm, len(rise_c))
    tr = np.asarray(rise_c, float) * rr
    total = np.trapezoid(tr, rr)
    mask = rr <= r_mm + 1e-12
    part = np.trapezoid(tr[mask], rr[mask]) if mask.sum() > 1 else 0.0
    u_mm = (alpha_per_k / r_mm) * (
        (1 + mu) * part + ((1 - mu) * r_mm**2 + (1 + mu) * a_mm**2) / (b_mm**2 - a_mm**2) * total
    )
    return float(u_mm * 1000.0)


def preload_clearance_um(growth_um: float, ball_mm: float, f: float, contact_deg: float, share: float) -> float:
    """Radial clearance opened by axial growth between the bearings (paper 003 eqs. 9–11).

    α' = arcsin(sin α0 − share ΔL/(D_w (f − ½))), θ = (180° − (α0 − α'))/2 − 72°,
    c = share ΔL tan θ (ΔL, D_w in mm; result µm).
    """
    dl_mm = share * growth_um / 1000.0
    s = math.sin(math.radians(contact_deg)) - dl_mm / (ball_mm * (f - 0.5))
    a1 = math.degrees(math.asin(max(-1.0, min(1.0, s))))
    theta = (180.0 - (contact_deg - a1)) / 2.0 - 72.0
    return float(dl_mm * math.tan(math.radians(theta)) * 1000.0)


def centrifugal_thrust_n(
    speed_rpm: float, balls: int, ball_mm: float, pitch_mm: float, density_kg_m3: float, contact_deg: float
) -> float:
    """Axial thrust of the balls' centrifugal force on the inner ring (N), outer ring fixed.

    The cage turns at ω_c = ω/2 (1 − (D_w/d_m) cos α) (rolling without slip); each ball of
    mass ρ π D_w³/6 on the pitch circle d_m pushes outward with m ω_c² d_m/2, and the outer
    raceway, touching it at the contact angle α, turns that into an axial push tan α.
    """
    omega = speed_rpm * 2.0 * math.pi / 60.0
    a = math.radians(contact_deg)
    omega_cage = 0.5 * omega * (1.0 - ball_mm / pitch_mm * math.cos(a))
    mass_kg = density_kg_m3 * math.pi * (ball_mm / 1000.0) ** 3 / 6.0
    force_n = mass_kg * omega_cage**2 * pitch_mm / 2000.0
    return balls * force_n * math.tan(a)


def mean_value_point_mm(x_mm: np.ndarray, t_c: np.ndarray) -> float:
    """Where a rod of equal cells (centres `x_mm`, temperatures `t_c`) is at its mean temperature.

    The rod grows by α ∫ ΔT dx = α L (T̄ − T0), T̄ the average of its cells, so a sensor
    reading T̄ gives the growth exactly. A sensor on the rod reads it linearly between
    cell centres (`Network.at`); ξ is the first point from the nose (x = 0) where that
    reading crosses T̄.
    """
    x = np.asarray(x_mm, float)
    d = np.asarray(t_c, float) - float(np.mean(t_c))
    for i in range(x.size - 1):
        if d[i] == 0.0:
            return float(x[i])
        if d[i] * d[i + 1] < 0.0:
            return float(x[i] + d[i] / (d[i] - d[i + 1]) * (x[i + 1] - x[i]))
    raise ValueError("the rod's temperature is uniform: every point reads its mean")


class SpindlePlant(Plant):
    """Rotor (nose at x = 0) between a front and a rear bearing, inside a cooled housing.

    Bearing friction `front_w_per_krpm`·n/1000 W and `rear_w_per_krpm`·n/1000 W heat
    the rotor at its ends; the bearings also conduct `bearing_g_w_k` W/K to the
    housing. Stator losses `stator_w_per_krpm`·n/1000 W heat the housing's middle,
    where the coolant jacket (when a segment has `coolant: true`) takes
    `coolant_g_w_k` W/K to the coolant at ambient + `coolant_offset_c`. Convection to
    the ambient: rotor `h_w_m2k` + `h_speed_w_m2k_per_krpm`·n/1000, housing
    `housing_h_w_m2k`. Sensors: `T_xi` on the rotor at `xi_mm` (steady-state ξ if
    None), `T_amb`, outer-ring temperatures `T_brg_front`, `T_brg_rear`, and the
    coolant supply `T_coolant`. Errors: `err_z_um` axial (growth + centrifugal lift of
    `balls` balls against `axial_stiffness_n_per_um`), `err_radial_um` radial.
    """

    name = "spindle"
    axes = ("z", "radial")
    DEFAULTS: dict[str, Any] = {
        "length_mm": 165.0,
        "radius_mm": 40.0,
        "nodes": 33,
        "alpha_per_k": 13.6e-6,
        "conductivity_w_mk": 45.0,
        "front_w_per_krpm": 1.0,
        "rear_w_per_krpm": 0.35,
        "h_w_m2k": 30.0,
        "h_speed_w_m2k_per_krpm": 0.0,
        "xi_mm": None,
        "bearing_g_w_k": 0.3,
        "housing_outer_mm": 90.0,
        "housing_inner_mm": 60.0,
        "housing_h_w_m2k": 10.0,
        "stator_w_per_krpm": 2.0,
        "coolant_g_w_k": 25.0,
        "coolant_offset_c": -0.5,
        "ring_mm": [25.0, 27.34, 37.66, 40.0],
        "poisson": 0.26,
        "ball_mm": 10.319,
        "groove_f": 0.53,
        "contact_deg": 18.0,
        "growth_share": 0.8,
        # centrifugal lift: 18 steel balls (a 7010-size angular-contact bearing; the paper
        # gives D_w, not the count) against an axial stiffness typical of a light preload
        "balls": 18,
        "ball_density_kg_m3": 7850.0,
        "axial_stiffness_n_per_um": 60.0,
        "drift_sensor": "T_brg_rear",
    }

    def _build(self) -> None:
        p = self.p
        length_m = p["length_mm"] / 1000.0
        r = p["radius_mm"] / 1000.0
        n = int(p["nodes"])
        ro, ri = p["housing_outer_mm"] / 1000.0, p["housing_inner_mm"] / 1000.0
        self.net = net = Network(self.dt_s, self.ambient_c(0.0))
        self.rotor = net.add_rod(
            "rotor",
            length_m,
            n,
            area_m2=math.pi * r**2,
            perimeter_m=2 * math.pi * r,
            conductivity_w_mk=p["conductivity_w_mk"],
            density_kg_m3=7850.0,
            heat_capacity_j_kgk=460.0,
        )
        self.housing = net.add_rod(
            "housing",
            length_m,
            n,
            area_m2=math.pi * (ro**2 - ri**2),
            perimeter_m=2 * math.pi * ro,
            conductivity_w_mk=45.0,
            density_kg_m3=7850.0,
            heat_capacity_j_kgk=460.0,
        )
        for k in (0, n - 1):
            if p["bearing_g_w_k"] > 0:
                net.link(int(self.rotor[k]), int(self.housing[k]), p["bearing_g_w_k"])
        net.freeze()
        # stator: the middle half of the housing
        self._stator = self.housing[n // 4 : n - n // 4]
        self._heat = np.zeros(net.n)
        # u is linear in the rings' edge temperatures: precompute its coefficients
        r_a, r_b, r_c, r_d = p["ring_mm"]
        if not 0 < r_a < r_b < r_c < r_d:
            raise ValueError("spindle plant param ring_mm: need 0 < r_A < r_B < r_C < r_D")
        if not (int(p["balls"]) >= 0 and p["axial_stiffness_n_per_um"] > 0 and p["ball_density_kg_m3"] >= 0):
            raise ValueError("spindle plant params: need balls ≥ 0, axial_stiffness_n_per_um > 0, density ≥ 0")
        alpha, mu = p["alpha_per_k"], p["poisson"]
        lin = np.linspace(1.0, 0.0, 9)
        self._ub = [ring_displacement_um(r_b, r_a, r_b, w, alpha, mu) for w in (lin, lin[::-1])]
        self._uc = [ring_displacement_um(r_c, r_c, r_d, w, alpha, mu) for w in (lin, lin[::-1])]
        self.xi_mm = float(p["xi_mm"]) if p["xi_mm"] is not None else self.steady_state_xi_mm()
        self.sensor_names = ["T_xi", "T_amb", "T_brg_front", "T_brg_rear", "T_coolant"]
        self.extra_names = ["speed_rpm"]

    # --- physics --------------------------------------------------------------------
    def _g_res(self, speed_rpm: float, coolant: bool) -> np.ndarray:
        """Conductances (W/K) to [ambient, coolant] for each node."""
        p, net = self.p, self.net
        g = np.zeros((net.n, 2))
        h_rot = p["h_w_m2k"] + p["h_speed_w_m2k_per_krpm"] * speed_rpm / 1000.0
        g[self.rotor, 0] = h_rot * net.surface_m2[self.rotor]
        g[self.housing, 0] = p["housing_h_w_m2k"] * net.surface_m2[self.housing]
        if coolant:
            g[self._stator, 1] = p["coolant_g_w_k"] / len(self._stator)
        return g

    def _heat_for(self, speed_rpm: float, load: float = 1.0) -> np.ndarray:
        p = self.p
        krpm = speed_rpm / 1000.0
        q = np.zeros(self.net.n)
        q[self.rotor[0]] = p["front_w_per_krpm"] * krpm
        q[self.rotor[-1]] = p["rear_w_per_krpm"] * krpm
        q[self._stator] = p["stator_w_per_krpm"] * krpm * load / len(self._stator)
        return q

    def coolant_c(self, t_amb_c: float) -> float:
        return t_amb_c + self.p["coolant_offset_c"]

    def steady_state_xi_mm(self, speed_rpm: float = 10000.0) -> float:
        """ξ of the rotor's steady-state field at `speed_rpm`, coolant off (paper 003 eq. 2)."""
        t = self.net.steady_state(self._g_res(speed_rpm, False), np.zeros(2), self._heat_for(speed_rpm))
        return mean_value_point_mm(self.net.x_m["rotor"] * 1000.0, t[self.rotor])

    def _step(self, seg: Segment, t_amb_c: float) -> None:
        key = (seg.speed_rpm, seg.coolant)
        self.net.use(key, lambda: self._g_res(seg.speed_rpm, seg.coolant))
        self._heat[:] = self._heat_for(seg.speed_rpm, seg.load)
        self.net.step(np.array([t_amb_c, self.coolant_c(t_amb_c)]), self._heat)

    # --- outputs --------------------------------------------------------------------
    def true_temperatures_c(self) -> np.ndarray:
        net, t_amb = self.net, self.ambient_c()
        return np.array(
            [
                net.at("rotor", self.xi_mm / 1000.0),
                t_amb,
                net.T[self.housing[0]],
                net.T[self.housing[-1]],
                self.coolant_c(t_amb),
            ]
        )

    def extras(self) -> np.ndarray:
        return np.array([self.segment().speed_rpm])

    def axial_um(self) -> float:
        """The rotor's thermal growth (µm), without the lift."""
        return self.net.growth_um("rotor", self.p["alpha_per_k"])

    def lift_um(self) -> float:
        """Centrifugal lift (µm): thrust / axial stiffness, at most the axial play share·growth opened."""
        p = self.p
        r_b, r_c = p["ring_mm"][1], p["ring_mm"][2]
        thrust_n = centrifugal_thrust_n(
            self.segment().speed_rpm,
            int(p["balls"]),
            p["ball_mm"],
            r_b + r_c,
            p["ball_density_kg_m3"],
            p["contact_deg"],
        )
        play_um = p["growth_share"] * max(self.axial_um(), 0.0)
        return min(thrust_n / p["axial_stiffness_n_per_um"], play_um)

    def radial_um(self) -> float:
        """Front bearing: u_C − u_B + c(ΔL) (µm)."""
        p, net = self.p, self.net
        t_in = net.T[self.rotor[0]] - net.T_init[self.rotor[0]]
        t_out = net.T[self.housing[0]] - net.T_init[self.housing[0]]
        t_ball = 0.5 * (t_in + t_out)
        u_b = self._ub[0] * t_in + self._ub[1] * t_ball  # inner ring at r_B, T: shaft → balls
        u_c = self._uc[0] * t_ball + self._uc[1] * t_out  # outer ring at r_C, T: balls → housing
        c = preload_clearance_um(self.axial_um(), p["ball_mm"], p["groove_f"], p["contact_deg"], p["growth_share"])
        return u_c - u_b + c

    def true_error_um(self) -> np.ndarray:
        return np.array([self.axial_um() + self.lift_um(), self.radial_um()])
