"""What every simulated machine shares: parameters, the time loop, PT100 readings, residuals."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from hil_sim.pt100 import Pt100Bank
from hil_sim.scenario import Scenario, Segment

# Parameters every plant accepts (merged under the plant's own DEFAULTS).
COMMON: dict[str, Any] = {
    "dt_s": 1.0,  # plant step (implicit Euler: stable at any step)
    "noise_c": 0.02,  # PT100 white noise, °C (1 σ)
    "resolution_c": 0.1,  # transmitter quantization, °C
    "tolerance": True,  # class-A offsets drawn per sensor
    "drift_sensor": None,  # name of the sensor that drifts (plant default if None in DEFAULTS)
    "drift_c_per_h": 0.02,  # its drift, °C/h
}


class Plant:
    """A machine stepped on its own clock `t_s`.

    Subclasses set `axes`, `DEFAULTS`, build their state in `_build()` (defining
    `sensor_names` and `extra_names`), and implement `_step`, `true_temperatures_c`,
    `extras` and `true_error_um`. Signals, in order: PT100 readings of
    `sensor_names`, then `extra_names` (speed, positions, currents), then
    `err_<axis>_um` (the true thermal error). `correction_um` is written by the
    closed loop: what the CNC applied; `residual_um()` = true error + correction is
    what a laser interferometer reads.
    """

    name = "plant"
    axes: tuple[str, ...] = ()
    DEFAULTS: dict[str, Any] = {}

    def __init__(self, scenario: Scenario, params: dict[str, Any] | None = None) -> None:
        p = {**COMMON, **self.DEFAULTS}
        for key, value in (params or {}).items():
            if key not in p:
                raise ValueError(
                    f"unknown {self.name} plant param {key!r} (known: {', '.join(sorted(p))})"
                )
            default = p[key]
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise ValueError(f"{self.name} plant param {key}: must be true or false")
            elif isinstance(default, int | float) and (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
            ):
                raise ValueError(f"{self.name} plant param {key}: must be a number, got {value!r}")
            p[key] = value
        if not p["dt_s"] > 0:
            raise ValueError(f"{self.name} plant param dt_s: must be > 0")
        self.p = p
        self.scenario = scenario
        self.rng = np.random.default_rng(scenario.seed)
        self.t_s = 0.0
        self.dt_s = float(p["dt_s"])
        self.sensor_names: list[str] = []
        self.extra_names: list[str] = []
        self._build()
        self.signal_names = (
            list(self.sensor_names) + list(self.extra_names) + [f"err_{a}_um" for a in self.axes]
        )
        drift = np.zeros(len(self.sensor_names))
        if p["drift_sensor"] is not None:
            if p["drift_sensor"] not in self.sensor_names:
                raise ValueError(
                    f"{self.name} plant param drift_sensor: {p['drift_sensor']!r} is not a sensor "
                    f"(sensors: {', '.join(self.sensor_names)})"
                )
            drift[self.sensor_names.index(p["drift_sensor"])] = p["drift_c_per_h"]
        self.sensors = Pt100Bank(
            len(self.sensor_names),
            self.rng,
            noise_c=p["noise_c"],
            resolution_c=p["resolution_c"],
            tolerance=p["tolerance"],
            drift_c_per_h=drift,
        )
        self.correction_um = np.zeros(len(self.axes))

    # --- subclass hooks -------------------------------------------------------------
    def _build(self) -> None:
        raise NotImplementedError

    def _step(self, seg: Segment, t_amb_c: float) -> None:
        """Advance the state by one `dt_s` under segment `seg` with ambient `t_amb_c`."""
        raise NotImplementedError

    def true_temperatures_c(self) -> np.ndarray:
        """True temperatures (°C) at the sensors, in `sensor_names` order."""
        raise NotImplementedError

    def extras(self) -> np.ndarray:
        """Speed, positions, currents now, in `extra_names` order."""
        return np.zeros(0)

    def true_error_um(self) -> np.ndarray:
        """True thermal error of each axis now (µm), in `axes` order."""
        raise NotImplementedError

    # --- shared ---------------------------------------------------------------------
    def ambient_c(self, t_s: float | None = None) -> float:
        return self.scenario.ambient.at(self.t_s if t_s is None else t_s)

    def segment(self) -> Segment:
        return self.scenario.segment_at(self.t_s)

    def advance_to(self, t_s: float) -> None:
        """Step the plant until its time reaches `t_s` (whole steps of dt)."""
        dt = self.dt_s
        while self.t_s + dt <= t_s + 1e-9:
            self._step(self.scenario.segment_at(self.t_s), self.scenario.ambient.at(self.t_s))
            self.t_s += dt

    def residual_um(self) -> np.ndarray:
        """What an interferometer reads with the correction applied: true error + correction."""
        return self.true_error_um() + self.correction_um

    def true_row(self) -> np.ndarray:
        """All signals without sensor errors (true temperatures)."""
        return np.concatenate([self.true_temperatures_c(), self.extras(), self.true_error_um()])

    def sample(self) -> np.ndarray:
        """Readings in `signal_names` order: measured temperatures, extras, true errors."""
        meas = self.sensors.read(self.true_temperatures_c(), self.t_s)
        return np.concatenate([meas, self.extras(), self.true_error_um()])

    def record(
        self, times_s: np.ndarray, on_row: Callable[[int, float], None] | None = None
    ) -> np.ndarray:
        """Run to each of `times_s` (ascending) and return rows of `signal_names`.

        The sensor model is applied to the whole batch at the end (same statistics as
        `sample()`). `on_row(k, t_s)` is called after row k is taken, plant at t_s.
        """
        times = np.asarray(times_s, float)
        rows = np.empty((times.size, len(self.signal_names)))
        for k, t in enumerate(times):
            self.advance_to(t)
            rows[k] = self.true_row()
            if on_row is not None:
                on_row(k, t)
        ns = len(self.sensor_names)
        rows[:, :ns] = self.sensors.read(rows[:, :ns], times[:, None])
        return rows

    def get_status(self) -> dict[str, Any]:
        return {
            "plant": self.name,
            "t_s": self.t_s,
            "true_error_um": self.true_error_um().tolist(),
            "residual_um": self.residual_um().tolist(),
        }
