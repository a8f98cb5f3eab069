"""One linear-motor feed axis inside a thermal network (papers 000 and 002).

Bodies: the base (guides, magnet track and scale) as a rod along the stroke, held by
fixed supports at both ends; the moving motor primary, a two-part table, the scale
read head and four carriage blocks as lumped masses. The primary's copper loss
P_cu = 3 i² R_cu [1 + ζ (T − T_fo)] (paper 000 eq. 9) heats it; it gives heat to the
table and, across the air gap, to the base under its footprint; the blocks add
guide friction and give heat to the rail where they stand. Gap and rail exchanges
follow the moving position and are taken explicitly (their G·dt/C ≪ 1).

Thermal error at axis position y (µm), the scale being carried by the base:
  E(y) = α_b [∫_0^x ΔT dx' − κ (x/L) ∫_0^L ΔT dx'] + α_t d ΔT_table,  x = offset + y,
where κ ∈ [0, 1] is how much the end supports restrain the base's growth (1 = rigid:
the compressive force makes the error turn back towards the far end, the end-of-stroke
reversal of paper 000) and d the distance from the read head to the tool point.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.network import Network
from hil_sim.scenario import Segment

# Parameters of one axis (a plant takes them as its own params).
AXIS_DEFAULTS: dict[str, Any] = {
    "base_length_mm": 800.0,
    "base_nodes": 40,
    "base_area_m2": 0.012,
    "base_perimeter_m": 0.52,
    "base_h_w_m2k": 8.0,
    "base_alpha_per_k": 11.5e-6,
    "support_g_w_k": 0.5,  # each end support to the ambient
    "support_restraint": 0.95,  # κ
    "stroke_mm": [0.0, 600.0],
    "stroke_offset_mm": 100.0,  # base x of y = 0
    "footprint_mm": 250.0,  # primary length over the base
    "motor_cap_j_k": 2500.0,
    "motor_surface_m2": 0.06,
    "gap_g_w_k": 1.5,
    "motor_table_g_w_k": 6.0,
    "table_cap_j_k": 14000.0,  # both halves together
    "table_surface_m2": 0.5,
    "table_alpha_per_k": 11.5e-6,
    "tool_offset_mm": 80.0,  # d
    "h_w_m2k": 10.0,  # moving parts at rest
    "h_speed_w_m2k_per_m_s": 8.0,  # forced convection while moving
    "block_cap_j_k": 700.0,
    "block_table_g_w_k": 2.0,
    "block_rail_g_w_k": 1.0,
    "friction_w_per_m_min": 0.25,  # per block, at load 1
    "head_cap_j_k": 300.0,
    "head_table_g_w_k": 1.0,
    "current_a": 0.5,  # moving, load 1: i = load (current_a + current_a_per_m_min v)
    "current_a_per_m_min": 0.22,
    "hold_current_a": 0.2,
    "r_cu_ohm": 4.0,
    "zeta_per_k": 0.00393,
}


class LinearAxis:
    """An axis named `name` built into `net` (call before `net.freeze()`)."""

    def __init__(self, net: Network, name: str, p: dict[str, Any]) -> None:
        self.net, self.name, self.p = net, name, p
        lo, hi = (float(v) for v in p["stroke_mm"])
        self.stroke_mm = (lo, hi)
        self.length_m = p["base_length_mm"] / 1000.0
        if not hi > lo or p["stroke_offset_mm"] + hi > p["base_length_mm"] or p["stroke_offset_mm"] + lo < 0:
            raise ValueError(f"axis {name}: stroke_mm must lie on the base (offset + stroke within its length)")
        self.base = net.add_rod(
            f"{name}.base",
            self.length_m,
            int(p["base_nodes"]),
            area_m2=p["base_area_m2"],
            perimeter_m=p["base_perimeter_m"],
            conductivity_w_mk=45.0,
            density_kg_m3=7850.0,
            heat_capacity_j_kgk=460.0,
        )
        self.dx_m = net.dx_m[f"{name}.base"]
        self.motor = net.add_mass(f"{name}.motor", p["motor_cap_j_k"], p["motor_surface_m2"])
        half = p["table_cap_j_k"] / 2.0
        s_half = p["table_surface_m2"] / 2.0
        self.table = np.array(
            [net.add_mass(f"{name}.table_front", half, s_half), net.add_mass(f"{name}.table_rear", half, s_half)]
        )
        net.link(self.table[0], self.table[1], 10.0)
        net.link(self.motor, self.table[0], 0.6 * p["motor_table_g_w_k"])
        net.link(self.motor, self.table[1], 0.4 * p["motor_table_g_w_k"])
        self.head = net.add_mass(f"{name}.head", p["head_cap_j_k"], 0.02)
        net.link(self.head, self.table[0], p["head_table_g_w_k"])
        self.blocks = np.array([net.add_mass(f"{name}.block_{c}", p["block_cap_j_k"], 0.03) for c in "ABCD"])
        for k, b in enumerate(self.blocks):
            net.link(b, self.table[0 if k < 2 else 1], p["block_table_g_w_k"])
        self.moving = np.concatenate([[self.motor], self.table, [self.head], self.blocks])
        # contiguous node ranges as slices (views: cheaper than fancy indexing every step)
        self._base_sl = slice(int(self.base[0]), int(self.base[-1]) + 1)
        self._blk_sl = slice(int(self.blocks[0]), int(self.blocks[-1]) + 1)
        self._base_x0_m = p["stroke_offset_mm"] / 1000.0
        self.pos_mm = lo
        self._dir = 1.0
        self.speed_m_min = 0.0
        self.current_a = 0.0
        self.load_factor = 1.0  # the side's own load (gantry), times the segment's load
        self._fp_cache: dict[int, np.ndarray] = {}
        self._ew_cache: dict[int, np.ndarray] = {}

    # --- kinematics ------------------------------------------------------------------
    def move(self, seg: Segment, dt_s: float) -> None:
        """Advance the position over one step: reciprocate at the feed, or stand at pos_mm."""
        lo, hi = seg.stroke_mm or self.stroke_mm
        lo, hi = max(lo, self.stroke_mm[0]), min(hi, self.stroke_mm[1])
        if seg.feed_mm_min > 0 and hi > lo:
            width = hi - lo
            pos = min(max(self.pos_mm, lo), hi)
            s0 = (pos - lo) if self._dir > 0 else 2 * width - (pos - lo)
            s = (s0 + seg.feed_mm_min / 60.0 * dt_s) % (2 * width)
            self.pos_mm = lo + (s if s <= width else 2 * width - s)
            self._dir = 1.0 if s < width else -1.0
            self.speed_m_min = seg.feed_mm_min / 1000.0
        else:
            if seg.pos_mm is not None:
                self.pos_mm = min(max(seg.pos_mm, self.stroke_mm[0]), self.stroke_mm[1])
            self.speed_m_min = 0.0

    def footprint(self, pos_mm: float) -> np.ndarray:
        """Weights (sum 1) of the base cells under the primary centred at `pos_mm`."""
        key = int(round(pos_mm))
        w = self._fp_cache.get(key)
        if w is None:
            c = (self.p["stroke_offset_mm"] + key) / 1000.0
            half = self.p["footprint_mm"] / 2000.0
            edges = np.arange(len(self.base) + 1) * self.dx_m
            w = np.clip(np.minimum(edges[1:], c + half) - np.maximum(edges[:-1], c - half), 0, None)
            w = w / w.sum()
            self._fp_cache[key] = w
        return w

    # --- heat ------------------------------------------------------------------------
    def g_ambient(self, g: np.ndarray) -> None:
        """Fill this axis's conductances to the ambient (column 0 of `g`) for the current speed."""
        p, net = self.p, self.net
        g[self.base, 0] = p["base_h_w_m2k"] * net.surface_m2[self.base]
        g[self.base[0], 0] += p["support_g_w_k"]
        g[self.base[-1], 0] += p["support_g_w_k"]
        h = p["h_w_m2k"] + p["h_speed_w_m2k_per_m_s"] * self.speed_m_min / 60.0
        g[self.moving, 0] = h * net.surface_m2[self.moving]

    def add_heat(self, q: np.ndarray, seg: Segment, t_amb_c: float) -> None:
        """Add this step's heat (W) into `q`: copper loss, friction, gap and rail exchange."""
        p, t = self.p, self.net.T
        load = seg.load_of(self.name) * self.load_factor
        if self.speed_m_min > 0:
            self.current_a = load * (p["current_a"] + p["current_a_per_m_min"] * self.speed_m_min)
        else:
            self.current_a = load * p["hold_current_a"]
        t_m = float(t[self.motor])
        p_cu = 3.0 * self.current_a**2 * p["r_cu_ohm"] * (1.0 + p["zeta_per_k"] * (t_m - t_amb_c))
        w = self.footprint(self.pos_mm)
        t_under = float(w @ t[self._base_sl])
        gap = p["gap_g_w_k"] * (t_m - t_under)
        rail = p["block_rail_g_w_k"] * (t[self._blk_sl] - t_under)
        q[self.motor] += p_cu - gap
        q[self._blk_sl] += p["friction_w_per_m_min"] * self.speed_m_min * load - rail
        q[self._base_sl] += (gap + float(rail.sum())) * w

    # --- outputs ---------------------------------------------------------------------
    def guide_c(self) -> float:
        """Guide surface temperature where the table stands (what an infrared sensor sees)."""
        x = self._base_x0_m + self.pos_mm / 1000.0
        n = self._base_sl.stop - self._base_sl.start
        f = min(max(x / self.dx_m - 0.5, 0.0), n - 1.0)  # cell centres at (i + ½) dx
        k = min(int(f), n - 2)
        t = self.net.T
        return float(t[self._base_sl.start + k] * (1 - (f - k)) + t[self._base_sl.start + k + 1] * (f - k))

    def error_weights(self, y_mm: np.ndarray | float) -> np.ndarray:
        """Rows w(y) over all network nodes with E(y) = w(y)·(T − T_init), µm/K (see module doc)."""
        p, net = self.p, self.net
        y = np.atleast_1d(np.asarray(y_mm, float))
        x = (p["stroke_offset_mm"] + y) / 1000.0
        edges = np.arange(len(self.base) + 1) * self.dx_m
        cover = np.clip(np.minimum(edges[1:][None, :], x[:, None]) - edges[:-1][None, :], 0, None)
        cover -= p["support_restraint"] * (x / self.length_m)[:, None] * self.dx_m
        w = np.zeros((y.size, net.n))
        w[:, self.base] = p["base_alpha_per_k"] * cover * 1e6
        w[:, self.table] = p["table_alpha_per_k"] * p["tool_offset_mm"] * 1e3 / len(self.table)
        return w

    def error_um(self, y_mm: np.ndarray | float) -> np.ndarray:
        """True thermal error E(y) at axis positions `y_mm` (µm), see the module docstring."""
        return self.error_weights(y_mm) @ (self.net.T - self.net.T_init)

    def error_here_um(self) -> float:
        """E at the current position (weights cached per 0.01 mm)."""
        key = int(round(self.pos_mm * 100.0))
        w = self._ew_cache.get(key)
        if w is None:
            if len(self._ew_cache) > 200_000:
                self._ew_cache.clear()
            w = self._ew_cache[key] = self.error_weights(key / 100.0)[0]
        return float(w @ (self.net.T - self.net.T_init))
