"""Gantry driven by two linear-motor axes X1, X2 (paper 002), joined by the cross beam.

Each side is a linear-motor axis (hil_sim.plants.linear_axis); the beam (a lumped
mass) links the two tables. The sides carry unequal loads (`load_x1`, `load_x2`
scale the motor force, so P_cu ∝ load²; a segment's `axis_load` adds to that), so
their temperatures and errors differ. 19 sensors as in the paper: ambient `T0`;
per side i: primary coil `Ti0`, read head `Ti1`, table `Ti2`, `Ti3`, guide surface
where the table stands `Ti4` (infrared), carriage blocks `TiA`…`TiD`.
Errors `err_x1_um`, `err_x2_um` where the gantry stands; `error_profile_um()` at
`profile_mm` (paper: X = 20, 40, 60, 80 mm).

Optionally (`column_cap_j_k` > 0; 0, the default, builds none) each side carries an
unmeasured column, the upright between its table and the beam: a lumped mass linked to
the table and the beam that convects like the beam; its growth α_c · lever · ΔT_column
along X adds to that side's error, and no sensor sees it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.network import Network
from hil_sim.plants.base import Plant
from hil_sim.plants.linear_axis import AXIS_DEFAULTS, LinearAxis
from hil_sim.scenario import Segment


class GantryPlant(Plant):
    """Two synchronised sides over a common stroke; both move to the same commanded X."""

    name = "gantry"
    axes = ("x1", "x2")
    DEFAULTS: dict[str, Any] = {
        **AXIS_DEFAULTS,
        "base_length_mm": 1200.0,
        "base_nodes": 48,
        "base_area_m2": 0.02,
        "base_perimeter_m": 0.7,
        "stroke_mm": [0.0, 1000.0],
        "stroke_offset_mm": 100.0,
        "table_cap_j_k": 20000.0,
        "table_surface_m2": 0.6,
        "tool_offset_mm": 250.0,  # read head to the measuring point on the beam
        "current_a": 1.0,
        "current_a_per_m_min": 0.5,
        "hold_current_a": 0.6,  # the gantry's weight on the motors' force ripple and the servo
        "r_cu_ohm": 3.0,
        "load_x1": 1.0,
        "load_x2": 1.3,
        "beam_cap_j_k": 60000.0,
        "beam_surface_m2": 1.5,
        "beam_table_g_w_k": 3.0,
        "profile_mm": [20.0, 40.0, 60.0, 80.0],
        "column_cap_j_k": 0.0,  # 0: no column
        "column_surface_m2": 1.0,
        "column_table_g_w_k": 2.0,
        "column_beam_g_w_k": 1.0,
        "column_alpha_per_k": 11.5e-6,
        "column_lever_mm": 200.0,  # the column's extent along X between table and tool
        "drift_sensor": "T1C",
    }

    def _build(self) -> None:
        p = self.p
        self.net = net = Network(self.dt_s, self.ambient_c(0.0))
        self.sides = [LinearAxis(net, a, p) for a in self.axes]
        self.beam = net.add_mass("beam", p["beam_cap_j_k"], p["beam_surface_m2"])
        for side in self.sides:
            net.link(self.beam, side.table[0], p["beam_table_g_w_k"])
        self.columns: list[int] = []
        if p["column_cap_j_k"] > 0:
            for side in self.sides:
                c = net.add_mass(f"{side.name}.column", p["column_cap_j_k"], p["column_surface_m2"])
                net.link(c, side.table[0], p["column_table_g_w_k"])
                net.link(c, self.beam, p["column_beam_g_w_k"])
                self.columns.append(c)
        net.freeze()
        self._column_um_per_k = p["column_alpha_per_k"] * p["column_lever_mm"] * 1e3
        for side in self.sides:
            side.load_factor = float(p[f"load_{side.name}"])
        self.profile_mm = np.asarray(p["profile_mm"], float)
        self._heat = np.zeros(net.n)
        eye = np.eye(net.n)
        self.sensor_names = ["T0"]
        rows = []
        self._guide_rows = []
        for i, side in enumerate(self.sides, start=1):
            names = [f"T{i}{c}" for c in "01234ABCD"]
            self.sensor_names += names
            self._guide_rows.append(len(rows) + 4)  # Ti4 follows the table (filled per sample)
            rows += [eye[side.motor], eye[side.head], eye[side.table[0]], eye[side.table[1]], np.zeros(net.n)] + [
                eye[b] for b in side.blocks
            ]
        self._S = np.array(rows)
        self.extra_names = ["pos_x1_mm", "pos_x2_mm", "current_x1_a", "current_x2_a"]

    def _g(self) -> np.ndarray:
        g = np.zeros((self.net.n, 1))
        for side in self.sides:
            side.g_ambient(g)
        h = self.p["h_w_m2k"] + self.p["h_speed_w_m2k_per_m_s"] * self.sides[0].speed_m_min / 60.0
        g[self.beam, 0] = h * self.net.surface_m2[self.beam]
        for c in self.columns:
            g[c, 0] = h * self.net.surface_m2[c]
        return g

    def _step(self, seg: Segment, t_amb_c: float) -> None:
        self._heat[:] = 0.0
        for side in self.sides:
            side.move(seg, self.dt_s)
        self.net.use(self.sides[0].speed_m_min, self._g)
        for side in self.sides:
            side.add_heat(self._heat, seg, t_amb_c)
        self.net.step(np.array([t_amb_c]), self._heat)

    def true_temperatures_c(self) -> np.ndarray:
        t = self._S @ self.net.T
        for row, side in zip(self._guide_rows, self.sides, strict=True):
            t[row] = side.guide_c()
        return np.concatenate([[self.ambient_c()], t])

    def extras(self) -> np.ndarray:
        a, b = self.sides
        return np.array([a.pos_mm, b.pos_mm, a.current_a, b.current_a])

    def true_error_um(self) -> np.ndarray:
        err = np.array([side.error_here_um() for side in self.sides])
        if self.columns:
            err += self._column_um_per_k * (self.net.T[self.columns] - self.net.T_init[self.columns])
        return err

    def error_profile_um(self, y_mm: np.ndarray | None = None) -> np.ndarray:
        """E at positions `y_mm` (default `profile_mm`) for each side: shape (2, positions), µm."""
        y = self.profile_mm if y_mm is None else np.asarray(y_mm, float)
        prof = np.array([side.error_um(y) for side in self.sides])
        if self.columns:
            rise = self.net.T[self.columns] - self.net.T_init[self.columns]
            prof += (self._column_um_per_k * rise)[:, None]
        return prof
