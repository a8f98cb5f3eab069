"""Linear-motor feed axis (paper 000): slide heated by the motor primary, fixed supports at both ends.

The error depends on position: `err_y_um` is the error where the axis stands
(`pos_y_mm`), `error_profile_um()` the whole E(y) on the laser's 20 mm grid.
Physics in hil_sim.plants.linear_axis.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.network import Network
from hil_sim.plants.base import Plant
from hil_sim.plants.linear_axis import AXIS_DEFAULTS, LinearAxis
from hil_sim.scenario import Segment

BASE_SENSORS_MM = (0.0, 150.0, 300.0, 450.0, 600.0)


class FeedAxisPlant(Plant):
    """One axis `y` over 0–600 mm. Sensors: primary coil `T_motor`, table `T_table`,
    read head `T_head`, a carriage block `T_block`, the base at 0/150/300/450/600 mm of
    the stroke (`T_base_000`…; `base_sensors_mm` on the stroke, those outside it dropped),
    and `T_amb`. A base sensor's name gives its nominal stroke position; it sits
    `base_sensor_shift_mm` (one shift per sensor, default none) from there, along the base.
    Extras: `pos_y_mm`, `current_y_a`.
    """

    name = "feed_axis"
    axes = ("y",)
    DEFAULTS: dict[str, Any] = {
        **AXIS_DEFAULTS,
        "profile_step_mm": 20.0,
        "base_sensors_mm": list(BASE_SENSORS_MM),
        "base_sensor_shift_mm": None,
        "drift_sensor": "T_base_450",
    }

    def _build(self) -> None:
        self.net = Network(self.dt_s, self.ambient_c(0.0))
        self.axis = LinearAxis(self.net, "y", self.p)
        self.net.freeze()
        self._heat = np.zeros(self.net.n)
        lo, hi = self.axis.stroke_mm
        step = float(self.p["profile_step_mm"])
        if not step > 0:
            raise ValueError("feed_axis plant param profile_step_mm: must be > 0")
        self.profile_mm = np.arange(lo, hi + 1e-9, step)
        nominal = [float(y) for y in self.p["base_sensors_mm"]]
        shift = self.p["base_sensor_shift_mm"]
        shift = [0.0] * len(nominal) if shift is None else [float(v) for v in shift]
        if len(shift) != len(nominal):
            raise ValueError("feed_axis plant param base_sensor_shift_mm: one shift per base sensor")
        on = [k for k, y in enumerate(nominal) if lo <= y <= hi]
        base_x = [self.p["stroke_offset_mm"] + nominal[k] + shift[k] for k in on]
        if any(not 0.0 <= x <= self.p["base_length_mm"] for x in base_x):
            raise ValueError("feed_axis plant param base_sensor_shift_mm: a base sensor off the base")
        ax, n = self.axis, self.net.n
        # readout: T at the fixed sensors = S @ T
        rows = [np.eye(n)[i] for i in (ax.motor, ax.table[0], ax.head, ax.blocks[0])]
        rows += [self.net.probe("y.base", x / 1000.0) for x in base_x]
        self._S = np.array(rows)
        self.sensor_names = (
            ["T_motor", "T_table", "T_head", "T_block"] + [f"T_base_{int(nominal[k]):03d}" for k in on] + ["T_amb"]
        )
        self.extra_names = ["pos_y_mm", "current_y_a"]

    def _g(self) -> np.ndarray:
        g = np.zeros((self.net.n, 1))
        self.axis.g_ambient(g)
        return g

    def _step(self, seg: Segment, t_amb_c: float) -> None:
        ax = self.axis
        ax.move(seg, self.dt_s)
        self.net.use(ax.speed_m_min, self._g)
        self._heat[:] = 0.0
        ax.add_heat(self._heat, seg, t_amb_c)
        self.net.step(np.array([t_amb_c]), self._heat)

    def true_temperatures_c(self) -> np.ndarray:
        return np.append(self._S @ self.net.T, self.ambient_c())

    def extras(self) -> np.ndarray:
        return np.array([self.axis.pos_mm, self.axis.current_a])

    def true_error_um(self) -> np.ndarray:
        return np.array([self.axis.error_here_um()])

    def residual_um(self) -> np.ndarray:
        return self.true_error_um() + self.correction_um

    def error_profile_um(self, y_mm: np.ndarray | None = None) -> np.ndarray:
        """E(y) at `y_mm` (default: the stroke on the `profile_step_mm` grid), µm."""
        return self.axis.error_um(self.profile_mm if y_mm is None else y_mm)
