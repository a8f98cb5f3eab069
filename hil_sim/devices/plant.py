"""A live plant for the closed loop: steps a scenario at a speedup, feeds its PT100 transmitters,
publishes its clock over Modbus and applies to its true error the correction the emulated CNC applied.

The plant runs on its own thread: plant time = wall time since start × `speedup`
(whole steps of the plant's `dt_s`). Before every step it reads what the CNC
applies now — the FANUC PMC's external machine coordinate shift (µm) or the
Siemens NC's ΔK (mm) per axis — and sets it as the plant's `correction_um`, so
`residual_um()` = true error + applied correction is what a laser interferometer
reads. For a Siemens NC it also writes the axis position (`pos_<axis>_mm`) that the
NC's position-dependent term uses. A CNC whose `clock` is `plant` is advanced on
plant time (its scans and IPO cycles run as fast as the machine), otherwise on its
own wall-time thread. Every `log_period_s` of plant time a row goes to the residual
log: `t_s`, then per axis `err_<a>_um` (true error), `applied_<a>_um`, `residual_<a>_um`.

With `lockstep` the plant does not follow wall time at all: it holds its time until a
client (compd's lockstep plant clock) writes registers 4–5, the plant time it may run
to; that write steps the plant (and its CNC, on plant time) up to that time, publishes
its signals once, and only then is acknowledged. compd writes it after a cycle's sink
writes have been acknowledged by the CNC, so every run of the same scenario and seed
sees the same inputs at the same plant times, however busy the machine is.

Probing (opt-in, `probe_every_s`): every `probe_every_s` of plant time the machine runs
its probing cycle on the next axis of `probe_axes` (round robin; default every axis
the CNC corrects): it measures the deviation a probe on the compensated machine sees,
true error + the correction the CNC applies now (the residual) + N(0, `probe_sigma_um`²)
(seeded by `probe_seed`), plus the `probe_outliers` (plant time, µm) due by then, at the
axis's position where the plant has one (`pos_<axis>_mm`), and publishes it through the
CNC's probe-result block (`publish_probe`, with the CNC's axis index and σ). `probes`
keeps what was published (plant time, axis, deviation, the residual without noise).

Register map (holding registers, read-only, unit id 1):

| register | data |
|---|---|
| 0, 1 | plant time, ms, uint32 (high word first) |
| 2 | state: 0 waiting for the first clock read (`start: on_clock_read`), 1 running, 2 finished |
| 3 | speedup (plant seconds per wall second), uint16; 0 in lockstep |
| 4, 5 | lockstep only, writable: run to this plant time, ms, uint32 (high word first) |
| 16 + 2·i | signal i of the plant (`signal_names`: PT100 readings, extras such as `speed_rpm` and `pos_<axis>_mm`,\
 true errors `err_<axis>_um`), float32 high word first |
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from compd.core.scoring import score_residual

SIGNAL_BASE = 16


def f32_words(v: float) -> list[int]:
    b = struct.pack(">f", v)
    return [int.from_bytes(b[0:2], "big"), int.from_bytes(b[2:4], "big")]


class PlantDevice:
    """The plant, its stepping thread and its register map."""

    def __init__(
        self,
        plant: Any,
        *,
        speedup: float = 600.0,
        start: str = "immediate",
        log_path: str | Path | None = None,
        log_period_s: float = 60.0,
        duration_s: float | None = None,
        wall_step_s: float = 0.002,
        lockstep: bool = False,
        probe_every_s: float | None = None,
        probe_axes: Sequence[str] | None = None,
        probe_sigma_um: float = 0.3,
        probe_outliers: Sequence[Sequence[float]] = (),
        probe_seed: int = 0,
    ) -> None:
        if not speedup > 0:
            raise ValueError("plant: speedup must be > 0")
        if start not in ("immediate", "on_clock_read"):
            raise ValueError("plant: start must be immediate or on_clock_read")
        self.plant = plant
        self.speedup = float(speedup)
        self.start_mode = start
        self.log_path = Path(log_path) if log_path else None
        self.log_period_s = float(log_period_s)
        self.duration_s = float(duration_s) if duration_s is not None else plant.scenario.duration_s
        self.wall_step_s = wall_step_s
        self.names = list(plant.signal_names)
        self.register_count = SIGNAL_BASE + 2 * len(self.names)
        self._regs = [0] * self.register_count
        self.lockstep = bool(lockstep)
        self._regs[3] = 0 if self.lockstep else min(int(round(self.speedup)), 0xFFFF)
        self._step_lock = threading.Lock()  # lockstep: one release at a time
        self._next_log_s = plant.t_s
        self._values = np.zeros(len(self.names))
        self._lock = threading.Lock()
        self._go = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.state = 0
        self.cnc: Any = None
        self.cnc_kind = ""
        self.cnc_axes: list[int] = []
        self.cnc_on_plant_clock = False
        self._pos_idx: list[int] = []
        self.rows: list[list[float]] = []
        self.steps = 0
        self._init_probing(probe_every_s, probe_axes, probe_sigma_um, probe_outliers, probe_seed)
        self._publish()

    def _init_probing(
        self,
        every_s: float | None,
        axes: Sequence[str] | None,
        sigma_um: float,
        outliers: Sequence[Sequence[float]],
        seed: int,
    ) -> None:
        if every_s is not None and not every_s > 0:
            raise ValueError("plant: probe_every_s must be > 0")
        if not sigma_um >= 0:
            raise ValueError("plant: probe_sigma_um must be >= 0")
        unknown = [a for a in (axes or []) if a not in self.plant.axes]
        if unknown:
            raise ValueError(f"plant: probe_axes names {unknown[0]!r}, not an axis of the plant {self.plant.axes}")
        try:
            self._outliers = sorted((float(t), float(um)) for t, um in outliers)
        except (TypeError, ValueError):
            raise ValueError("plant: probe_outliers must be a list of [plant time s, um]") from None
        self.probe_every_s = float(every_s) if every_s is not None else None
        self._probe_axes = list(axes) if axes else None
        self.probe_sigma_um = float(sigma_um)
        self._probe_rng = np.random.default_rng(seed)
        self._next_probe_s = self.plant.t_s + (self.probe_every_s or 0.0)
        self._probe_turn = 0
        extras = list(self.plant.extra_names)
        self._probe_pos = {a: extras.index(f"pos_{a}_mm") for a in self.plant.axes if f"pos_{a}_mm" in extras}
        # published: (plant time, axis, deviation µm, residual µm without noise and outlier)
        self.probes: list[tuple[float, str, float, float]] = []

    # ------------------------------------------------------------------ wiring
    def attach_cnc(self, cnc: Any, kind: str, axes: dict[str, int] | None, on_plant_clock: bool) -> None:
        """The CNC whose applied correction reaches the plant; `axes` maps plant axis → CNC axis."""
        axes = axes or {a: i for i, a in enumerate(self.plant.axes)}
        unknown = set(axes) - set(self.plant.axes)
        if unknown:
            raise ValueError(
                f"plant: cnc_axes names {sorted(unknown)[0]!r}, not an axis of the plant {self.plant.axes}"
            )
        self.cnc, self.cnc_kind, self.cnc_on_plant_clock = cnc, kind, on_plant_clock
        self.cnc_axes = [axes.get(a, -1) for a in self.plant.axes]
        extras = list(self.plant.extra_names)
        self._pos_idx = [extras.index(f"pos_{a}_mm") if f"pos_{a}_mm" in extras else -1 for a in self.plant.axes]
        if on_plant_clock and kind != "linuxcnc_hal":
            cnc.start_at(self.plant.t_s)
        if self._probe_axes is None:
            self._probe_axes = [a for a, k in zip(self.plant.axes, self.cnc_axes, strict=True) if k >= 0]
        off = [a for a in self._probe_axes if self.cnc_axes[self.plant.axes.index(a)] < 0]
        if self.probe_every_s is not None and off:
            raise ValueError(f"plant: probe_axes names {off[0]!r}, which cnc_axes does not map to the CNC")

    def feed_for(self, channels: Sequence[str]) -> Callable[[], list[float]]:
        """A transmitter feed: the plant's latest readings of `channels` (°C)."""
        missing = [c for c in channels if c not in self.names]
        if missing:
            raise ValueError(f"plant: no signal {missing[0]!r} (signals: {', '.join(self.names)})")
        idx = [self.names.index(c) for c in channels]

        def feed() -> list[float]:
            with self._lock:
                return [float(self._values[i]) for i in idx]

        return feed

    # ------------------------------------------------------------ Modbus map
    def read_registers(self, address: int, count: int) -> list[int] | None:
        if address < 0 or address + count > self.register_count:
            return None
        if address <= 1 and self.start_mode == "on_clock_read":
            self._go.set()
        with self._lock:
            return self._regs[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> bool:
        if not self.lockstep or address != 4 or len(values) != 2:
            return False
        self.run_to(((values[0] << 16) | values[1]) / 1000.0)
        return True

    def run_to(self, t_s: float) -> None:
        """Lockstep: step up to plant time `t_s` (not past the duration), then publish once."""
        p = self.plant
        with self._step_lock:
            with self._lock:
                self._regs[4:6] = [(int(round(t_s * 1000.0)) >> 16) & 0xFFFF, int(round(t_s * 1000.0)) & 0xFFFF]
            moved = False
            while p.t_s < t_s - 1e-9 and p.t_s + p.dt_s <= self.duration_s + 1e-9 and not self._stop.is_set():
                self._step()
                moved = True
            if p.t_s + p.dt_s > self.duration_s + 1e-9:
                self.state = 2
            if moved or self._regs[2] != self.state:
                self._publish()

    # ------------------------------------------------------------- stepping
    def _applied_um(self) -> np.ndarray:
        out = np.zeros(len(self.plant.axes))
        cnc = self.cnc
        if cnc is None:
            return out
        if self.cnc_kind == "fanuc_pmc":
            vals = cnc.applied_um()
            scale = 1.0
        else:  # the Siemens NC's ΔK, LinuxCNC's axis.L.eoffset: mm
            vals = cnc.applied_mm()
            scale = 1000.0
        for a, k in enumerate(self.cnc_axes):
            if 0 <= k < len(vals):
                out[a] = scale * vals[k]
        return out

    def _publish(self) -> None:
        p = self.plant
        meas = p.sensors.read(p.sensor_temperatures_c(), p.t_s)
        vals = np.concatenate([meas, p.extras(), p.true_error_um()])
        ms = int(round(p.t_s * 1000.0)) & 0xFFFFFFFF
        regs = [(ms >> 16) & 0xFFFF, ms & 0xFFFF]
        sig = []
        for v in vals:
            sig += f32_words(float(v))
        with self._lock:
            self._values[:] = vals
            self._regs[0:2] = regs
            self._regs[2] = self.state
            self._regs[SIGNAL_BASE:] = sig

    def _log_row(self) -> None:
        p = self.plant
        err = p.true_error_um()
        app = p.correction_um
        self.rows.append([p.t_s, *err, *app, *(err + app)])

    def _step(self) -> None:
        p, cnc = self.plant, self.cnc
        if cnc is not None:
            if self.cnc_on_plant_clock:
                cnc.advance_to(p.t_s)
            if self.cnc_kind == "siemens_nc" and max(self._pos_idx, default=-1) >= 0:
                ex = p.extras()
                for a, k in enumerate(self.cnc_axes):
                    if k >= 0 and self._pos_idx[a] >= 0:
                        cnc.set_position(k, float(ex[self._pos_idx[a]]))
            p.correction_um[:] = self._applied_um()
            if self.probe_every_s is not None and p.t_s + 1e-9 >= self._next_probe_s:
                self._probe()
        if p.t_s + 1e-9 >= self._next_log_s:
            self._log_row()
            self._next_log_s += self.log_period_s
        p.advance_to(p.t_s + p.dt_s)
        self.steps += 1

    def _probe(self) -> None:
        """The machine's probing cycle on the next axis: the residual plus noise, through the CNC."""
        p = self.plant
        assert self.probe_every_s is not None and self._probe_axes
        self._next_probe_s += self.probe_every_s * max(1, int((p.t_s - self._next_probe_s) // self.probe_every_s) + 1)
        axis = self._probe_axes[self._probe_turn % len(self._probe_axes)]
        self._probe_turn += 1
        a = p.axes.index(axis)
        residual = float(p.true_error_um()[a] + p.correction_um[a])
        extra = 0.0
        while self._outliers and self._outliers[0][0] <= p.t_s + 1e-9:
            extra += self._outliers.pop(0)[1]
        dev = residual + float(self._probe_rng.normal(0.0, self.probe_sigma_um)) + extra
        pos = float(p.extras()[self._probe_pos[axis]]) if axis in self._probe_pos else None
        sigma = self.probe_sigma_um if self.probe_sigma_um > 0 else None
        self.cnc.publish_probe(self.cnc_axes[a], dev, pos, sigma)
        self.probes.append((p.t_s, axis, dev, residual))

    def _run(self) -> None:
        p = self.plant
        self._go.wait()
        if self._stop.is_set():
            return
        self.state = 1
        wall0, t0 = time.monotonic(), p.t_s
        self._next_log_s = t0
        while not self._stop.is_set():
            target = min(t0 + (time.monotonic() - wall0) * self.speedup, self.duration_s)
            while p.t_s + p.dt_s <= target + 1e-9 and not self._stop.is_set():
                self._step()
            if p.t_s + p.dt_s > self.duration_s + 1e-9:
                self.state = 2
            self._publish()
            if self.state == 2:
                self._stop.wait(0.05)
            else:
                self._stop.wait(self.wall_step_s)

    def start(self) -> PlantDevice:
        if self.probe_every_s is not None and self.cnc is None:
            raise ValueError("plant: probe_every_s needs a cnc to publish the probe results through")
        if self.lockstep:  # no thread: writes of registers 4-5 step the plant
            self.state = 1
            self._publish()
            return self
        if self.start_mode == "immediate":
            self._go.set()
        self._thread = threading.Thread(target=self._run, name=f"plant-{self.plant.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._go.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None
        self.write_log()

    def write_log(self) -> None:
        """The residual log (CSV) of what ran so far."""
        if self.log_path is None:
            return
        axes = self.plant.axes
        cols = ["t_s"] + [f"err_{a}_um" for a in axes] + [f"applied_{a}_um" for a in axes]
        cols += [f"residual_{a}_um" for a in axes]
        data = np.array(self.rows) if self.rows else np.zeros((0, len(cols)))
        with open(self.log_path, "w", encoding="utf-8", newline="") as fh:
            np.savetxt(fh, data, fmt="%.6g", delimiter=",", header=",".join(cols), comments="")

    def where(self) -> str:
        pace = "in lockstep" if self.lockstep else f"at {self.speedup:g}x"
        return f"{self.plant.name} {pace}, {self.duration_s / 3600:.2f} h"


def residual_report(
    path: str | Path, t_from_s: float = 0.0, t_to_s: float | None = None
) -> dict[str, dict[str, float]]:
    """RMS and max |error| without (true error) and with compensation (residual) per axis, from a
    residual log; rows with `t_from_s` ≤ t ≤ `t_to_s`."""
    with open(path, encoding="utf-8") as fh:
        cols = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    t = data[:, 0]
    sel = (t >= t_from_s) & (t <= (np.inf if t_to_s is None else t_to_s))
    out = {}
    for c in cols:
        if c.startswith("err_"):
            a = c[4:-3]
            out[a] = score_residual(data[sel, cols.index(c)], data[sel, cols.index(f"residual_{a}_um")])
    return out
