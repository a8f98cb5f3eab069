"""Vertical machining centre: a motorized spindle on a steel column; Z error = spindle growth − column growth.

Two heat sources act on the one axis `z`, each read by its own sensors:

* the spindle, hil_sim's motorized spindle unchanged (`hil_sim.plants.spindle`: rotor and
  housing rods, bearing friction, stator losses, coolant jacket, the ξ sensor `T_xi`,
  `T_brg_front`, `T_brg_rear`, `T_coolant`): its axial growth and centrifugal lift push the
  tool nose toward the table, the spindle plant's `err_z_um`;
* the column, a vertical steel box rod (z = 0 on the base, z = H under the Z ball screw's
  fixed bearing at its top): it convects to the ambient over its outer surface, conducts
  to the base (taken at the ambient) through its foot joint, and takes the heat the
  spindle housing leaks through the headstock and the Z slide's guides at `headstock_at_mm`.
  Growing, it lifts the screw's bearing and with it the head: the tool moves away from the
  table by α_c ∫_0^H ΔT_c dz = α_c H ΔT̄_c. Sensors `T_col_top`, `T_col_bot` on its face.

    err_z_um = err_z_um_spindle + err_z_um_column
    err_z_um_spindle = α_r ∫ ΔT_rotor dx + lift      err_z_um_column = −α_c ∫_0^H ΔT_c dz

Positive is toward the table (the spindle plant's sign); the parts are logged apart as
`err_z_um_spindle` and `err_z_um_column`, simulator-only truth whose names compd takes
neither as a temperature (the `err_` prefix) nor as an axis's error (not `err_<axis>_um`).
The column's time constant is hours, the rotor's tens of minutes; the column moves with
the ambient when the spindle stands, and a little with the spindle's heat (most of it when
the coolant is off). A scenario's `params: {sensor_unplug_s: {T_col_top: 36000}}` unplugs
a sensor from that time (or over [from_s, to_s)): it reads NaN, a missing value.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil_sim.plants.spindle import SpindlePlant
from hil_sim.scenario import Scenario

STEEL_DENSITY_KG_M3 = 7850.0
STEEL_HEAT_CAPACITY_J_KGK = 460.0
COLUMN_SENSORS = ("T_col_top", "T_col_bot")
TRUTH = ("err_z_um_spindle", "err_z_um_column")


class VmcPlant(SpindlePlant):
    """Axis `z` of a VMC: the spindle plant's rotor and housing, plus the column they hang on.

    Sensors: the spindle's `T_xi`, `T_amb`, `T_brg_front`, `T_brg_rear`, `T_coolant`, then
    `T_col_top`, `T_col_bot` at `column_top_sensor_mm`, `column_bottom_sensor_mm` above
    the base. Extras: `speed_rpm`, `err_z_um_spindle`, `err_z_um_column` (the two parts of
    `err_z_um`).
    """

    name = "vmc"
    axes = ("z",)
    DEFAULTS: dict[str, Any] = {
        **SpindlePlant.DEFAULTS,
        # a steel box column, 500 × 500 mm outside with 40 mm walls (its ribs counted in), 600 mm
        # from the base joint to the Z screw's fixed bearing: 347 kg, ≈ 160 kJ/K, ≈ 8.4 W/K to
        # the air; with the foot's joint its time constant is ≈ 3 h (the rotor's ≈ 0.5 h)
        "column_height_mm": 600.0,
        "column_nodes": 12,
        "column_area_m2": 0.0736,  # wall cross-section, 0.5² − 0.42² m²
        "column_perimeter_m": 2.0,  # outer perimeter (the closed box's inside air is still)
        "column_conductivity_w_mk": 45.0,
        "column_alpha_per_k": 11.5e-6,  # α_c H = 6.9 µm per K of the column's mean rise
        # free convection on a tall face at a few K (≈ 2) plus radiation of a painted surface
        # (4 ε σ T³ ≈ 5)
        "column_h_w_m2k": 7.0,
        # the foot's bolted joint and the base beyond it, taken at the ambient (the base, a
        # mass several times the column's on the floor, is not simulated)
        "column_base_g_w_k": 8.0,
        # spindle housing → headstock → Z slide's guides → column face, W/K in all, spread
        # over the housing's length, into the column where the slide works
        "headstock_g_w_k": 1.5,
        "headstock_at_mm": 500.0,
        "column_top_sensor_mm": 550.0,
        "column_bottom_sensor_mm": 80.0,
        # {sensor: t_s} or {sensor: [from_s, to_s]}: the sensor reads NaN (unplugged) from
        # t_s on, or over [from_s, to_s); None = every sensor plugged
        "sensor_unplug_s": None,
    }

    def __init__(self, scenario: Scenario, params: dict[str, Any] | None = None) -> None:
        self.column: np.ndarray | None = None  # built after the spindle, in _build
        super().__init__(scenario, params)

    # --- build ----------------------------------------------------------------------
    def _build(self) -> None:
        super()._build()  # the spindle: rotor, housing, its sensors (network frozen)
        p, net = self.p, self.net
        height_m = p["column_height_mm"] / 1000.0
        for key in (
            "column_height_mm",
            "column_area_m2",
            "column_perimeter_m",
            "column_conductivity_w_mk",
            "column_alpha_per_k",
            "column_h_w_m2k",
        ):
            if not p[key] > 0:
                raise ValueError(f"vmc plant param {key}: must be > 0")
        for key in ("column_base_g_w_k", "headstock_g_w_k"):
            if not p[key] >= 0:
                raise ValueError(f"vmc plant param {key}: must be >= 0")
        nodes = p["column_nodes"]
        if isinstance(nodes, bool) or int(nodes) != nodes or nodes < 2:
            raise ValueError("vmc plant param column_nodes: an integer >= 2")
        places = {k: p[k] for k in ("headstock_at_mm", "column_top_sensor_mm", "column_bottom_sensor_mm")}
        for key, at_mm in places.items():
            if not 0.0 <= at_mm <= p["column_height_mm"]:
                raise ValueError(f"vmc plant param {key}: on the column, 0 … {p['column_height_mm']:g} mm")
        # the column joins the spindle's network; nothing has stepped yet, so freezing again
        # rebuilds the conduction matrix and starts every node, old and new, at the ambient
        self.column = net.add_rod(
            "column",
            height_m,
            int(nodes),
            area_m2=p["column_area_m2"],
            perimeter_m=p["column_perimeter_m"],
            conductivity_w_mk=p["column_conductivity_w_mk"],
            density_kg_m3=STEEL_DENSITY_KG_M3,
            heat_capacity_j_kgk=STEEL_HEAT_CAPACITY_J_KGK,
        )
        slide = int(self.column[np.argmin(np.abs(net.x_m["column"] - p["headstock_at_mm"] / 1000.0))])
        if p["headstock_g_w_k"] > 0:
            share = p["headstock_g_w_k"] / len(self.housing)
            for h in self.housing:
                net.link(int(h), slide, share)
        net.freeze()
        self._heat = np.zeros(net.n)
        if p["xi_mm"] is None:  # the ξ point of the rotor as it runs in this machine
            self.xi_mm = self.steady_state_xi_mm()
        self._column_z_m = np.array([p["column_top_sensor_mm"], p["column_bottom_sensor_mm"]]) / 1000.0
        self.sensor_names = self.sensor_names + list(COLUMN_SENSORS)
        self.extra_names = ["speed_rpm", *TRUTH]
        self._unplug = self._unplug_windows(p["sensor_unplug_s"])

    def _unplug_windows(self, spec: Any) -> tuple[np.ndarray, np.ndarray] | None:
        """(from_s, to_s) per sensor (−, + inf where plugged) from `sensor_unplug_s`."""
        if spec is None or spec == {}:
            return None
        where = "vmc plant param sensor_unplug_s"
        if not isinstance(spec, dict):
            raise ValueError(f"{where}: a mapping sensor: t_s or sensor: [from_s, to_s]")
        start = np.full(len(self.sensor_names), math.inf)
        end = np.full(len(self.sensor_names), math.inf)
        for sensor, when in spec.items():
            if sensor not in self.sensor_names:
                raise ValueError(f"{where}.{sensor}: not a sensor (sensors: {', '.join(self.sensor_names)})")
            pair = list(when) if isinstance(when, list | tuple) else [when, math.inf]
            ok = len(pair) == 2 and all(
                not isinstance(v, bool) and isinstance(v, int | float) and not math.isnan(v) for v in pair
            )
            if not ok or not 0.0 <= pair[0] < pair[1] or math.isinf(pair[0]):
                raise ValueError(f"{where}.{sensor}: a time >= 0 s, or [from_s, to_s] with from_s < to_s")
            k = self.sensor_names.index(sensor)
            start[k], end[k] = float(pair[0]), float(pair[1])
        return start, end

    # --- physics --------------------------------------------------------------------
    def _g_res(self, speed_rpm: float, coolant: bool) -> np.ndarray:
        """The spindle's conductances to [ambient, coolant], and the column's to the ambient."""
        g = super()._g_res(speed_rpm, coolant)
        if self.column is not None:
            p, net = self.p, self.net
            g[self.column, 0] = p["column_h_w_m2k"] * net.surface_m2[self.column]
            g[self.column[0], 0] += p["column_base_g_w_k"]
        return g

    # --- outputs --------------------------------------------------------------------
    def true_temperatures_c(self) -> np.ndarray:
        spindle = super().true_temperatures_c()
        column = np.interp(self._column_z_m, self.net.x_m["column"], self.net.T[self.column])
        return np.concatenate([spindle, column])

    def sensor_temperatures_c(self) -> np.ndarray:
        """The elements' temperatures (lag, cross-talk); an unplugged sensor's is NaN."""
        t = super().sensor_temperatures_c()
        if self._unplug is None:
            return t
        start, end = self._unplug
        off = (start <= self.t_s + 1e-9) & (self.t_s + 1e-9 < end)
        return np.where(off, math.nan, t)

    def spindle_um(self) -> float:
        """The spindle's part of the Z error (µm): axial growth + centrifugal lift (spindle plant)."""
        return self.axial_um() + self.lift_um()

    def column_um(self) -> float:
        """The column's part of the Z error (µm): −α_c ∫ ΔT dz, its growth lifts the head."""
        return 0.0 - self.net.growth_um("column", self.p["column_alpha_per_k"])  # 0.0, not -0.0, at rest

    def extras(self) -> np.ndarray:
        return np.array([self.segment().speed_rpm, self.spindle_um(), self.column_um()])

    def true_error_um(self) -> np.ndarray:
        return np.array([self.spindle_um() + self.column_um()])
