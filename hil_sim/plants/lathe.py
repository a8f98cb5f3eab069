"""CNC lathe (paper 001, Heidemann T65): spindle, headstock, bed and saddle; Z error = bed − spindle.

Bodies (thermal network): the spindle, a steel rod (nose s = 0 at the front bearing,
rear bearing at s = L_sp); the headstock, a cast-iron rod around it (same s); the bed,
a cast-iron rod with x = 0 under the headstock's rear, the spindle nose at
x = L_sp and the saddle (X slide) at `saddle_x_mm`; the saddle, a lumped mass.
Bearing friction P = P_ref (n/n_ref)^e · load heats each bearing, shared between the
spindle (inner ring) and the headstock (outer ring); bearings link spindle and
headstock; the headstock sits on the bed; the saddle sits on the bed and is warmed
by its drives while cutting. Everything convects to the ambient.

Z error (paper 001 eq. 15): ΔL_bed − ΔL_sp, with the true integrals
ΔL_bed = α_bed ∫_0^{saddle} ΔT_bed dx (paper: ≈ α L ΔT3, L ≈ 1.2 m) and
ΔL_sp = α_sp ∫_0^{L_sp} ΔT_sp ds (the 1-D rod of the paper).
Sensors as in the paper's Fig. 4: T1 headstock front, T2 headstock rear, T3 bed middle,
T4 bed left, T5 bed right, T6 saddle, T7 ambient.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil_sim.network import Network
from hil_sim.plants.base import Plant
from hil_sim.scenario import Segment


class LathePlant(Plant):
    """Axis `z`; extras `speed_rpm`."""

    name = "lathe"
    axes = ("z",)
    DEFAULTS: dict[str, Any] = {
        "spindle_length_mm": 600.0,
        "spindle_radius_mm": 50.0,
        "spindle_nodes": 30,
        "spindle_alpha_per_k": 12e-6,
        "spindle_h_w_m2k": 15.0,
        "spindle_h_w_m2k_per_krpm": 5.0,
        "front_bearing_w": 90.0,  # at n_ref
        "rear_bearing_w": 35.0,
        "ref_speed_rpm": 2000.0,
        "speed_exponent": 1.5,
        "inner_share": 0.5,  # part of the friction heat into the spindle
        "front_bearing_g_w_k": 20.0,
        "rear_bearing_g_w_k": 10.0,
        "headstock_area_m2": 0.10,
        "headstock_perimeter_m": 1.3,
        "headstock_h_w_m2k": 8.0,
        "drive_w": 15.0,  # main drive losses into the headstock's rear at n_ref
        "headstock_bed_g_w_k": 10.0,
        "bed_length_mm": 2000.0,
        "bed_nodes": 40,
        "bed_area_m2": 0.16,
        "bed_perimeter_m": 2.0,
        "bed_h_w_m2k": 6.0,
        "bed_alpha_per_k": 10e-6,
        "saddle_x_mm": 1200.0,
        "saddle_cap_j_k": 75000.0,
        "saddle_surface_m2": 1.0,
        "saddle_bed_g_w_k": 5.0,
        "saddle_w": 10.0,  # while the spindle turns
        "sensor_x_mm": [50.0, 550.0, 1000.0, 100.0, 1900.0],  # T1, T2 (headstock s), T3-T5 (bed x)
        "drift_sensor": "T4",
    }

    def _build(self) -> None:
        p = self.p
        self.net = net = Network(self.dt_s, self.ambient_c(0.0))
        lsp = p["spindle_length_mm"] / 1000.0
        r = p["spindle_radius_mm"] / 1000.0
        n = int(p["spindle_nodes"])
        iron = {"conductivity_w_mk": 50.0, "density_kg_m3": 7200.0, "heat_capacity_j_kgk": 500.0}
        self.spindle = net.add_rod(
            "spindle",
            lsp,
            n,
            area_m2=math.pi * r**2,
            perimeter_m=2 * math.pi * r,
            conductivity_w_mk=50.0,
            density_kg_m3=7850.0,
            heat_capacity_j_kgk=460.0,
        )
        self.headstock = net.add_rod(
            "headstock",
            lsp,
            n,
            area_m2=p["headstock_area_m2"],
            perimeter_m=p["headstock_perimeter_m"],
            **iron,
        )
        self.bed = net.add_rod(
            "bed",
            p["bed_length_mm"] / 1000.0,
            int(p["bed_nodes"]),
            area_m2=p["bed_area_m2"],
            perimeter_m=p["bed_perimeter_m"],
            **iron,
        )
        self.saddle = net.add_mass("saddle", p["saddle_cap_j_k"], p["saddle_surface_m2"])
        net.link(self.spindle[0], self.headstock[0], p["front_bearing_g_w_k"])
        net.link(self.spindle[-1], self.headstock[-1], p["rear_bearing_g_w_k"])
        # headstock node at s sits on the bed at x = L_sp − s
        bed_x = net.x_m["bed"]
        g_each = p["headstock_bed_g_w_k"] / n
        for k, s in enumerate(net.x_m["headstock"]):
            j = int(np.argmin(np.abs(bed_x - (lsp - s))))
            net.link(self.headstock[k], self.bed[j], g_each)
        self._saddle_x_m = p["saddle_x_mm"] / 1000.0
        j = int(np.argmin(np.abs(bed_x - self._saddle_x_m)))
        net.link(self.saddle, self.bed[j], p["saddle_bed_g_w_k"])
        net.freeze()
        self._heat = np.zeros(net.n)
        sx = [x / 1000.0 for x in p["sensor_x_mm"]]
        if len(sx) != 5:
            raise ValueError("lathe plant param sensor_x_mm: five positions (T1, T2, T3, T4, T5)")
        self._S = np.array(
            [
                net.probe("headstock", sx[0]),
                net.probe("headstock", sx[1]),
                net.probe("bed", sx[2]),
                net.probe("bed", sx[3]),
                net.probe("bed", sx[4]),
                np.eye(net.n)[self.saddle],
            ]
        )
        # Z error = w · (T − T_init)
        w = np.zeros(net.n)
        dx_bed = net.dx_m["bed"]
        edges = np.arange(len(self.bed) + 1) * dx_bed
        cover = np.clip(np.minimum(edges[1:], self._saddle_x_m) - edges[:-1], 0, None)
        w[self.bed] = p["bed_alpha_per_k"] * cover * 1e6
        w[self.spindle] = -p["spindle_alpha_per_k"] * net.dx_m["spindle"] * 1e6
        self._w_err = w
        self.sensor_names = ["T1", "T2", "T3", "T4", "T5", "T6", "T7"]
        self.extra_names = ["speed_rpm"]

    def _g(self, speed_rpm: float) -> np.ndarray:
        p, net = self.p, self.net
        g = np.zeros((net.n, 1))
        h_sp = p["spindle_h_w_m2k"] + p["spindle_h_w_m2k_per_krpm"] * speed_rpm / 1000.0
        g[self.spindle, 0] = h_sp * net.surface_m2[self.spindle]
        g[self.headstock, 0] = p["headstock_h_w_m2k"] * net.surface_m2[self.headstock]
        g[self.bed, 0] = p["bed_h_w_m2k"] * net.surface_m2[self.bed]
        g[self.saddle, 0] = p["headstock_h_w_m2k"] * net.surface_m2[self.saddle]
        return g

    def bearing_heat_w(self, speed_rpm: float, load: float = 1.0) -> tuple[float, float]:
        """Front and rear bearing friction (W): P_ref (n/n_ref)^e · load."""
        p = self.p
        f = (speed_rpm / p["ref_speed_rpm"]) ** p["speed_exponent"] * load if speed_rpm > 0 else 0.0
        return p["front_bearing_w"] * f, p["rear_bearing_w"] * f

    def _step(self, seg: Segment, t_amb_c: float) -> None:
        p, q = self.p, self._heat
        n_rpm = seg.speed_rpm
        self.net.use(n_rpm, lambda: self._g(n_rpm))
        front, rear = self.bearing_heat_w(n_rpm, seg.load)
        share = p["inner_share"]
        q[:] = 0.0
        q[self.spindle[0]] = share * front
        q[self.headstock[0]] = (1 - share) * front
        q[self.spindle[-1]] = share * rear
        q[self.headstock[-1]] = (1 - share) * rear
        if n_rpm > 0:
            q[self.headstock[-3:]] += p["drive_w"] * n_rpm / p["ref_speed_rpm"] / 3
            q[self.saddle] = p["saddle_w"] * seg.load
        self.net.step(np.array([t_amb_c]), q)

    def true_temperatures_c(self) -> np.ndarray:
        return np.append(self._S @ self.net.T, self.ambient_c())

    def extras(self) -> np.ndarray:
        return np.array([self.segment().speed_rpm])

    def spindle_growth_um(self) -> float:
        return self.net.growth_um("spindle", self.p["spindle_alpha_per_k"])

    def bed_growth_um(self) -> float:
        return self.net.growth_um("bed", self.p["bed_alpha_per_k"], self._saddle_x_m)

    def true_error_um(self) -> np.ndarray:
        return np.array([float(self._w_err @ (self.net.T - self.net.T_init))])
