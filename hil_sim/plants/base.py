"""What every simulated machine shares: parameters, the time loop, PT100 readings, residuals."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from hil_sim.pt100 import Pt100Bank, SensorLag
from hil_sim.scenario import Scenario, Segment

# Parameters every plant accepts (merged under the plant's own DEFAULTS).
COMMON: dict[str, Any] = {
    "dt_s": 1.0,  # plant step (implicit Euler: stable at any step)
    "noise_c": 0.02,  # PT100 white noise, °C (1 σ)
    "resolution_c": 0.1,  # transmitter quantization, °C
    "tolerance": True,  # class-A offsets drawn per sensor
    "drift_sensor": None,  # name of the sensor that drifts (plant default if None in DEFAULTS)
    "drift_c_per_h": 0.02,  # its drift, °C/h
    # each sensor element's first-order lag behind its point, s: one number for all, or
    # {sensor: s} (others 0); 0 = the element is at its point's temperature (no lag)
    "sensor_lag_s": 0.0,
    # {sensor: [fraction, neighbour]}: the element reads (1 − fraction) of its point and
    # fraction of a neighbour: another sensor's point, a lumped body `name`, or a rod's
    # point `name@x_mm` (bodies of the plant's thermal network); None = none
    "sensor_crosstalk": None,
}

# params checked by the plant once its sensors are known (not by the number check)
_SENSOR_MODEL = ("sensor_lag_s", "sensor_crosstalk")


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
                raise ValueError(f"unknown {self.name} plant param {key!r} (known: {', '.join(sorted(p))})")
            default = p[key]
            if key in _SENSOR_MODEL:
                pass  # a number or a mapping by sensor name: checked in _sensor_model()
            elif isinstance(default, bool):
                if not isinstance(value, bool):
                    raise ValueError(f"{self.name} plant param {key}: must be true or false")
            elif isinstance(default, int | float) and (
                isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)
            ):
                raise ValueError(f"{self.name} plant param {key}: must be a number, got {value!r}")
            p[key] = value
        if not p["dt_s"] > 0:
            raise ValueError(f"{self.name} plant param dt_s: must be > 0")
        self.p = p
        self.scenario = scenario
        self.speed_from: Callable[[], float] | None = None  # the controller's spindle speed (rpm), when it runs
        self.rng = np.random.default_rng(scenario.seed)
        self.t_s = 0.0
        self.dt_s = float(p["dt_s"])
        self.sensor_names: list[str] = []
        self.extra_names: list[str] = []
        self._build()
        self.signal_names = list(self.sensor_names) + list(self.extra_names) + [f"err_{a}_um" for a in self.axes]
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
        self._sensor_model()

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
        """What the machine does now: the scenario's segment, its speed the controller's when
        `speed_from` is set (a real controller runs the program: hil_sim.devices.linuxcnc_hal)."""
        seg = self.scenario.segment_at(self.t_s)
        if self.speed_from is None:
            return seg
        return replace(seg, speed_rpm=max(0.0, float(self.speed_from())))

    def advance_to(self, t_s: float) -> None:
        """Step the plant until its time reaches `t_s` (whole steps of dt); the sensor
        elements' lag (`sensor_lag_s`) steps with it."""
        dt = self.dt_s
        lag = self._lag
        while self.t_s + dt <= t_s + 1e-9:
            # the elements see their surroundings as at the step's start, held over the step
            # (as the network sees the ambient): a step of T reaches 63 % exactly at τ_s
            target = None if lag is None else self._blend(self.true_temperatures_c())
            self._step(self.segment(), self.scenario.ambient.at(self.t_s))
            self.t_s += dt
            if target is not None:
                lag.step(target)

    # --- the sensor elements: cross-talk and lag ------------------------------------
    def _sensor_model(self) -> None:
        """Read `sensor_lag_s` and `sensor_crosstalk` (names checked against the sensors)."""
        p, names = self.p, self.sensor_names
        self._xt: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._lag: SensorLag | None = None
        xt = p["sensor_crosstalk"]
        if xt:
            if not isinstance(xt, dict):
                raise ValueError(f"{self.name} plant param sensor_crosstalk: a mapping sensor: [fraction, neighbour]")
            rows, fracs, nb_sensor, nb_nodes = [], [], [], []
            for sensor, spec in xt.items():
                where = f"{self.name} plant param sensor_crosstalk.{sensor}"
                if sensor not in names:
                    raise ValueError(f"{where}: not a sensor (sensors: {', '.join(names)})")
                if not (isinstance(spec, list | tuple) and len(spec) == 2):
                    raise ValueError(f"{where}: [fraction, neighbour]")
                frac, nb = spec
                if isinstance(frac, bool) or not isinstance(frac, int | float) or not 0 <= frac < 1:
                    raise ValueError(f"{where}: the fraction must be a number in [0, 1)")
                rows.append(names.index(sensor))
                fracs.append(float(frac))
                j, w = self._neighbour(str(nb), where)
                nb_sensor.append(j)
                nb_nodes.append(w)
            self._xt = (np.array(rows), np.array(fracs), np.array(nb_sensor), np.array(nb_nodes))
        lag = p["sensor_lag_s"]
        if isinstance(lag, dict):
            unknown = [k for k in lag if k not in names]
            if unknown:
                raise ValueError(
                    f"{self.name} plant param sensor_lag_s.{unknown[0]}: not a sensor (sensors: {', '.join(names)})"
                )
            values = [lag.get(n, 0.0) for n in names]
        elif isinstance(lag, bool) or not isinstance(lag, int | float):
            raise ValueError(f"{self.name} plant param sensor_lag_s: seconds, or a mapping sensor: seconds")
        else:
            values = [lag] * len(names)
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{self.name} plant param sensor_lag_s: lags are numbers >= 0 s, got {v!r}")
        if any(v > 0 for v in values):
            self._lag = SensorLag(np.array(values, float), self.dt_s, self._blend(self.true_temperatures_c()))

    def _neighbour(self, spec: str, where: str) -> tuple[int, np.ndarray]:
        """(sensor index or −1, node weights) of a cross-talk neighbour."""
        net = getattr(self, "net", None)
        n = 0 if net is None else net.n
        if spec in self.sensor_names:
            return self.sensor_names.index(spec), np.zeros(n)
        body, at, x = spec.partition("@")
        if net is not None and body in net.bodies:
            if at:
                if body not in net.x_m:
                    raise ValueError(f"{where}: {body!r} is a lumped body (no @x_mm)")
                try:
                    x_mm = float(x)
                except ValueError:
                    raise ValueError(f"{where}: {spec!r}: the position after @ is in mm") from None
                return -1, net.probe(body, x_mm / 1000.0)
            if len(net.bodies[body]) != 1:
                raise ValueError(f"{where}: {body!r} is a rod: name a point, {body}@X_MM")
            return -1, np.eye(n)[int(net.bodies[body][0])]
        bodies = ", ".join(sorted(net.bodies)) if net is not None else "none"
        raise ValueError(f"{where}: {spec!r} is neither a sensor nor a body (bodies: {bodies})")

    def _blend(self, true_c: np.ndarray) -> np.ndarray:
        """What the elements' surroundings are at: their points blended with their neighbours."""
        if self._xt is None:
            return true_c
        rows, frac, nb_sensor, nb_nodes = self._xt
        nb = np.where(nb_sensor >= 0, true_c[np.maximum(nb_sensor, 0)], nb_nodes @ self.net.T)
        out = np.array(true_c, float)
        out[rows] = (1.0 - frac) * true_c[rows] + frac * nb
        return out

    def sensor_temperatures_c(self) -> np.ndarray:
        """What the sensor elements are at (°C), in `sensor_names` order: their points
        (`true_temperatures_c`) blended with their neighbours and lagged; exactly
        `true_temperatures_c()` when `sensor_crosstalk` and `sensor_lag_s` are off."""
        now = self._blend(self.true_temperatures_c())
        if self._lag is None:
            return now
        return np.where(self._lag.lagged, self._lag.state_c, now)  # τ_s = 0: the point now

    def residual_um(self) -> np.ndarray:
        """What an interferometer reads with the correction applied: true error + correction."""
        return self.true_error_um() + self.correction_um

    def true_row(self) -> np.ndarray:
        """All signals without sensor errors (true temperatures)."""
        return np.concatenate([self.true_temperatures_c(), self.extras(), self.true_error_um()])

    def sample(self) -> np.ndarray:
        """Readings in `signal_names` order: measured temperatures, extras, true errors."""
        meas = self.sensors.read(self.sensor_temperatures_c(), self.t_s)
        return np.concatenate([meas, self.extras(), self.true_error_um()])

    def record(self, times_s: np.ndarray, on_row: Callable[[int, float], None] | None = None) -> np.ndarray:
        """Run to each of `times_s` (ascending) and return rows of `signal_names`.

        The sensor elements' temperatures (`sensor_temperatures_c`) are taken per row, the
        PT100 model is applied to the whole batch at the end (same statistics as
        `sample()`). `on_row(k, t_s)` is called after row k is taken, plant at t_s.
        """
        times = np.asarray(times_s, float)
        rows = np.empty((times.size, len(self.signal_names)))
        for k, t in enumerate(times):
            self.advance_to(t)
            rows[k] = np.concatenate([self.sensor_temperatures_c(), self.extras(), self.true_error_um()])
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
