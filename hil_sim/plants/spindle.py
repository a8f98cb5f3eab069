"""Motorized spindle, axial: a rotor rod heated by its bearings, one PT100 at ξ (paper 003)."""

from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.pt100 import Pt100Bank
from hil_sim.rod import Rod
from hil_sim.scenario import Scenario


class SpindlePlant:
    """Rotor of length 165 mm between a front (nose, x = 0) and a rear bearing.

    Bearing friction heat grows with speed: `front_w_per_krpm`·n/1000 W at the nose,
    `rear_w_per_krpm`·n/1000 W at the rear. Convection to the ambient along the
    rotor, faster when it turns (`h_w_m2k` + `h_speed_w_m2k_per_krpm`·n/1000). The
    true axial error is α ∫ (T − T_init) dx. Sensors: `T_xi` at `xi_mm` from the
    nose and `T_amb` (ambient); true signal `err_z_um`.
    """

    axes = ("z",)
    DEFAULTS: dict[str, Any] = {
        "length_mm": 165.0,
        "radius_mm": 40.0,
        "nodes": 33,
        "alpha_per_k": 13.6e-6,
        "front_w_per_krpm": 1.0,
        "rear_w_per_krpm": 0.35,
        "h_w_m2k": 30.0,
        "h_speed_w_m2k_per_krpm": 0.0,
        "xi_mm": None,
        "dt_s": 1.0,
        "noise_c": 0.02,
    }

    def __init__(self, scenario: Scenario, params: dict[str, Any] | None = None) -> None:
        p = dict(self.DEFAULTS)
        unknown = set(params or {}) - set(p)
        if unknown:
            raise ValueError(f"unknown spindle plant params: {', '.join(sorted(unknown))}")
        p.update(params or {})
        self.p = p
        self.scenario = scenario
        self.rng = np.random.default_rng(scenario.seed)
        t_amb0 = scenario.ambient.at(0.0)
        self.rod = Rod(
            p["length_mm"] / 1000.0,
            int(p["nodes"]),
            p["radius_mm"] / 1000.0,
            h_w_m2k=p["h_w_m2k"],
            dt_s=p["dt_s"],
            t_init_c=t_amb0,
        )
        self.xi_mm = float(p["xi_mm"]) if p["xi_mm"] is not None else self.steady_state_xi_mm()
        self.sensors = Pt100Bank(2, self.rng, noise_c=p["noise_c"])
        self.signal_names = ["T_xi", "T_amb", "speed_rpm", "err_z_um"]
        self.t_s = 0.0
        self._heat = np.zeros(self.rod.n)
        self.correction_um = np.zeros(1)

    def steady_state_xi_mm(self, speed_rpm: float = 10000.0) -> float:
        """ξ of the steady-state profile at `speed_rpm` (mean-value point, SPEC §3.3)."""
        from compd.models.xi_spindle import find_xi

        rod = Rod(
            self.rod.length_m, self.rod.n, self.rod.radius_m, h_w_m2k=self.p["h_w_m2k"],
            dt_s=3600.0, t_init_c=0.0,
        )
        heat = self._heat_for(speed_rpm, rod.n)
        rod.set_h(self._h_for(speed_rpm))
        for _ in range(200):
            rod.step(0.0, heat)
        return find_xi(rod.x_m * 1000.0, rod.T)

    def _heat_for(self, speed_rpm: float, n: int) -> np.ndarray:
        heat = np.zeros(n)
        krpm = speed_rpm / 1000.0
        heat[0] = self.p["front_w_per_krpm"] * krpm
        heat[-1] = self.p["rear_w_per_krpm"] * krpm
        return heat

    def _h_for(self, speed_rpm: float) -> float:
        return self.p["h_w_m2k"] + self.p["h_speed_w_m2k_per_krpm"] * speed_rpm / 1000.0

    def advance_to(self, t_s: float) -> None:
        """Step the plant until its time reaches `t_s` (whole steps of dt)."""
        dt = self.rod.dt_s
        while self.t_s + dt <= t_s + 1e-9:
            seg = self.scenario.segment_at(self.t_s)
            self.rod.set_h(self._h_for(seg.speed_rpm))
            self._heat[:] = self._heat_for(seg.speed_rpm, self.rod.n)
            self.rod.step(self.scenario.ambient.at(self.t_s), self._heat)
            self.t_s += dt

    def true_error_um(self) -> np.ndarray:
        return np.array([self.rod.growth_um(self.p["alpha_per_k"])])

    def sample(self) -> np.ndarray:
        """Readings in `signal_names` order: measured temperatures, speed, true error."""
        true_c = np.array(
            [self.rod.temperature_at(self.xi_mm / 1000.0), self.scenario.ambient.at(self.t_s)]
        )
        meas = self.sensors.read(true_c, self.t_s)
        seg = self.scenario.segment_at(self.t_s)
        return np.array([meas[0], meas[1], seg.speed_rpm, self.true_error_um()[0]])
