"""Siemens temperature compensation sink (paper 001): K0, tanβ, P0 per axis.

The NC applies ΔK = K0 + tanβ·(P − P0) and spreads every change over its IPO cycles
(MD32760). This sink writes SD43900 K0 (mm) from the guarded correction of each
axis; when the model's `linear_terms()` gives them — per output the error's slope
(µm/mm) and reference position P0 (mm), its outputs being the error at P0 — it
writes SD43910 tanβ = −slope/1000 and SD43920 P0 too, and sets MD32750 bit 1
(position dependent) as well as bit 0. Writes go out when a value moved by
`min_change_um` and no faster than `min_update_s`. With `host` the NC's data is reached
over Modbus TCP; without, it is the software PLC's NC (compd.plc), in process on the
loop's clock. Both through the same link interface: the sink has one code path. In
process a write lands where the NC's time stands (the last call's), so the NC ramps
toward it over the time up to the call (a replay's row after dt: not one row late).

At its open, and whenever its link is restored, the sink reads back the NC's data (K0 and
the ΔK it applies, per axis) before it writes anything: the guard starts from the ΔK the NC
applies (compd.sinks.base, "what the device holds"), so the first K0 sent is within one slew
step of it, never a jump to 0 that the NC would ramp away at its own rate.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from pydantic import Field

from compd.core.config import SinkConfig
from compd.io.device_time import DeviceTime, LoopTime, WallTime
from compd.io.modbus_link import ModbusLink
from compd.plc.link import VirtualLink
from compd.plc.siemens_nc import APPLIED, BLOCK, K0, TARGET, TYPE, SiemensNc, f32_regs, regs_f32
from compd.sinks.base import SAFE_TIMEOUT_S, Sink

if TYPE_CHECKING:
    from compd.models.base import Model


class SiemensConfig(SinkConfig):
    """The NC's data over Modbus TCP (or the software PLC's NC in process)."""

    host: str | None = Field(None, description="NC gateway over Modbus TCP; none = the software PLC's NC in process")
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    axes: dict[str, Annotated[int, Field(ge=0, le=63)]] | None = Field(
        None,
        description="the axes this sink drives, each → its NC axis index; every model output is one of them"
        " (default: the model's outputs, in order)",
    )
    min_change_um: float = Field(0.1, ge=0, le=100, description="smaller changes are not sent")
    min_update_s: float = Field(0.05, ge=0.001, le=60)
    ipo_s: float = Field(0.004, ge=0.0005, le=0.1, description="in-process NC: IPO cycle")
    velo_factor: float = Field(1e-5, gt=0, le=1, description="in-process NC: MD32760 (fraction)")

    def driven_axes(self) -> tuple[list[str], str] | None:
        """`axes` declares the axes this sink drives (a model output it does not name would reach no NC axis)."""
        return (list(self.axes), "axes") if self.axes else None


class SiemensSink(Sink):
    """K0 (and tanβ, P0 for position-dependent models) per axis."""

    Config = SiemensConfig
    sends_linear_terms = True

    def __init__(self, cfg: SiemensConfig, base_dir: str = ".", nc: SiemensNc | None = None) -> None:
        super().__init__(cfg, base_dir)
        self.cfg: SiemensConfig = cfg
        # the NC in this process (given, or the software PLC's when no host is set) runs on
        # the loop's time; one over Modbus on its own
        if nc is None and cfg.host is None:
            n = max(2, len(cfg.axes or {}), max((cfg.axes or {}).values(), default=0) + 1)
            nc = SiemensNc(n, ipo_s=cfg.ipo_s, velo_factor=cfg.velo_factor)
        self.nc = nc
        self.time: DeviceTime = LoopTime() if nc is not None else WallTime()
        self.model: Model | None = None
        self.outputs: list[str] = []
        self.nc_axis: list[int] = []
        self.sent_k0_um: np.ndarray = np.zeros(0)
        self._next_s = -math.inf
        self.updates = 0
        self._row_terms: list[tuple[float, float]] | None = None

    def bind_model(self, model: Model) -> None:
        """The model (for its output names and its linear terms, where it has them)."""
        self.model = model
        self.outputs = list(model.outputs)
        m = self.cfg.axes or {a: i for i, a in enumerate(self.outputs)}
        self.nc_axis = [m.get(a, -1) for a in self.outputs]
        self.sent_k0_um = np.full(len(self.outputs), np.nan)

    def device_key(self) -> Any:
        return None if self.cfg.host is None else ("modbus", self.cfg.host, self.cfg.port)

    def _connect(self) -> ModbusLink | VirtualLink:
        """The link to the NC's data (the status block: every axis the sink writes)."""
        count = BLOCK * (max(self.nc_axis, default=0) + 1)
        if self.nc is not None:
            status = (0, min(count, BLOCK * self.nc.n))
            return VirtualLink(self.nc, self.time, status=status, name="siemens", sync=[status])
        return ModbusLink(
            self.cfg.host or "",
            self.cfg.port,
            device_id=self.cfg.device_id,
            status=(0, count),
            name="siemens",
            sync=[(0, count)],
        )

    def open(self, now_s: float) -> None:
        """Connect; nothing is written until the NC's data is read back (`sync`)."""
        self.time.set(now_s)
        self.link = self._connect()
        self.link.start()

    def take_held(self, regs: list[int], now_s: float) -> None:
        """The ΔK each axis's NC applies is where the guard starts (`held_um`); K0 is sent anew
        from the next write on (with the compensation type: MD32750)."""
        held = {}
        for name, ax in zip(self.outputs, self.nc_axis, strict=True):
            if ax >= 0 and BLOCK * ax + APPLIED + 1 < len(regs):
                um = 1000.0 * regs_f32(regs[BLOCK * ax + APPLIED], regs[BLOCK * ax + APPLIED + 1])
                if math.isfinite(um):
                    held[name] = um
        self._held_um = held
        self.sent_k0_um[:] = np.nan
        self._next_s = -math.inf
        # a model may offer linear terms only in some modes; output-test binds no model
        assert self.link is not None
        linear = self.model is not None and self.model.linear_terms() is not None
        for ax in self.nc_axis:
            if ax >= 0:
                self.link.submit(BLOCK * ax + TYPE, [3 if linear else 1])

    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        t = self.time
        if not t.catch_up:
            t.set(now_s)
        self.writes += 1
        if now_s < self._next_s or not self.outputs or self.link is None or not self.link.synced():
            t.set(now_s)
            return
        if t.catch_up:
            # the NC on the loop's time: the values go out where its time stands (the last
            # call's), or as soon after as min_update_s allows, and the NC's IPO cycles ramp
            # toward them over the time up to now (a replay's row after dt: what the daemon's
            # cycles in that dt would have sent, the NC following at its own rate)
            t.wait(max(0.0, self._next_s - t.now_s))
        terms = self._linear_terms()
        sent = False
        for i, ax in enumerate(self.nc_axis):
            if ax < 0:
                continue
            k0 = float(corr_um[i]) if enable[i] else 0.0
            if abs(k0 - self.sent_k0_um[i]) < self.cfg.min_change_um:  # NaN (first time): send
                continue
            regs = f32_regs(k0 / 1000.0)
            if terms is not None:
                slope_um_per_mm, p0_mm = terms[i]
                regs += f32_regs(-slope_um_per_mm / 1000.0) + f32_regs(p0_mm)
            self.link.submit(BLOCK * ax + K0, regs)
            self.sent_k0_um[i] = k0
            sent = True
        if sent:
            self.updates += 1
            self._next_s = (t.now_s if t.catch_up else now_s) + self.cfg.min_update_s
        t.set(now_s)

    def set_positions(self, positions_mm: np.ndarray) -> None:
        """The NC in this process told where its axes stand (the model's outputs' positions, mm):
        the position-dependent term tanβ·(P − P0) is taken there, as on the machine."""
        if self.nc is None:
            return
        for i, ax in enumerate(self.nc_axis):
            if ax >= 0 and i < len(positions_mm):
                p = float(positions_mm[i])
                if p == p:
                    self.nc.set_position(ax, p)

    def _linear_terms(self) -> list[tuple[float, float]] | None:
        """The model's linear terms now (in `write_rows`: those of the row being written)."""
        if self._row_terms is not None:
            return self._row_terms
        assert self.model is not None
        return self.model.linear_terms()

    def settle(self, now_s: float) -> None:
        """Every write acknowledged; the NC's IPO cycles up to `now_s` (in process) have run
        when the status is next read."""
        self.time.set(now_s)
        if self.link is not None:
            self.link.flush()

    def safe(self) -> bool:
        """K0 = 0 (and tanβ = 0): the NC ramps ΔK away at its own MD32760 rate."""
        if self.link is None or not self.syncs:
            return True  # nothing was ever written to the NC on this sink: nothing of ours to take back
        self.link.ensure_serving()
        if not self.resync(SAFE_TIMEOUT_S, self.time.now_s):
            return False  # the NC does not answer: nothing can reach it
        for ax in self.nc_axis:
            if ax >= 0:
                self.link.submit(BLOCK * ax + K0, f32_regs(0.0) + f32_regs(0.0))
        return self.link.flush(SAFE_TIMEOUT_S)

    def applied_um(self, out: np.ndarray) -> None:
        """ΔK the NC applies now, for the word's axes (high byte first), µm."""
        self._status_um(out, APPLIED)

    def commanded_um(self, out: np.ndarray) -> None:
        """The ΔK the NC ramps toward (K0 + tanβ·(P − P0), its target), for the word's axes, µm."""
        self._status_um(out, TARGET)

    def _status_um(self, out: np.ndarray, off: int, regs: list[int] | None = None) -> None:
        """A float32 of each word axis's block in the NC's status (mm; `regs`, else read now),
        in µm; NaN where none."""
        if regs is None:
            regs = self.link.status if self.link is not None else None
        out[:] = np.nan
        if regs is None:
            return
        for slot, name in enumerate(self.axes[: out.shape[0]]):
            if name in self.outputs:
                ax = self.nc_axis[self.outputs.index(name)]
                if ax >= 0 and BLOCK * ax + off + 1 < len(regs):
                    out[slot] = 1000.0 * regs_f32(regs[BLOCK * ax + off], regs[BLOCK * ax + off + 1])

    def write_rows(
        self,
        t_s: np.ndarray,
        words: np.ndarray,
        changed: np.ndarray,
        corr_um: np.ndarray,
        enable: np.ndarray,
        applied_um: np.ndarray,
        commanded_um: np.ndarray,
        terms: list[list[tuple[float, float]] | None] | None = None,
        positions_mm: np.ndarray | None = None,
    ) -> None:
        """`Sink.write_rows`, each write with its row's linear terms (`terms`). With the NC in
        process only the rows in which something can change are run: a K0 that moved by
        `min_change_um` when an update is due, an NC still ramping. In the others the NC,
        on its target, applies what it applied the row before."""
        tl = t_s.tolist()
        n = len(tl)
        if n == 0:
            return
        axes = [(i, ax) for i, ax in enumerate(self.nc_axis) if ax >= 0]
        corr, en = corr_um.tolist(), enable.tolist()
        applied = np.zeros(applied_um.shape[1])
        commanded = np.zeros(commanded_um.shape[1])
        ran = np.zeros(n, dtype=bool)
        min_change = self.cfg.min_change_um
        # only with the NC in process may rows be skipped; a subclass whose `write` does more
        # (e.g. tells the NC the axis position of each row) gets every row
        skip = self.nc is not None and type(self).write is SiemensSink.write
        if positions_mm is not None:  # a moving axis moves the NC's target: every row runs
            skip = False
        settled = False  # the NC on its target after the last row run
        skipped = False
        sent: list[float] = []
        try:
            for r in range(n):
                now = tl[r]
                if settled and self.writes:
                    due = now >= self._next_s and any(
                        not abs((corr[r][i] if en[r][i] else 0.0) - sent[i]) < min_change for i, _ in axes
                    )
                    if not due:  # what `write` would skip, on an NC that stays on its target
                        self.writes += 1
                        skipped = True
                        continue
                if skipped:  # the NC's time where the skipped rows' calls would have left it
                    self.time.set(tl[r - 1])
                    skipped = False
                self._row_terms = terms[r] if terms is not None else None
                if positions_mm is not None:
                    self.set_positions(positions_mm[r])
                self.write(int(words[r]), corr_um[r], enable[r], bool(changed[r]), now)
                self.settle(now)
                regs = self.link.status if self.link is not None else None
                self._status_um(applied, APPLIED, regs)
                self._status_um(commanded, TARGET, regs)
                applied_um[r] = applied
                commanded_um[r] = commanded
                ran[r] = True
                settled = skip and self.nc is not None and self.nc.settled()
                sent = self.sent_k0_um.tolist()
        finally:
            self._row_terms = None
        self.time.set(tl[-1])
        last = np.maximum.accumulate(np.where(ran, np.arange(n), 0))
        applied_um[:] = applied_um[last]
        commanded_um[:] = commanded_um[last]

    def flush(self, timeout_s: float) -> bool:
        return self.link is None or self.link.drain(timeout_s)

    @classmethod
    def in_process_config(cls, cfg: SinkConfig) -> SinkConfig:
        """The software PLC's NC in process, with this section's axes, IPO cycle and MD32760."""
        return cfg.model_copy(update={"host": None})

    def device_info(self) -> dict[str, Any]:
        """K0 is a float32 in mm (no word, no ±63 LSB): a change reaches the NC once it is
        `min_change_um`; the NC ramps ΔK at MD32760 × max velocity (the in-process NC's)."""
        where = "in process" if self.cfg.host is None else f"at {self.cfg.host}:{self.cfg.port}"
        rate = None
        if self.nc is not None:
            rate = 1000.0 * self.nc.cap_mm(0) / self.nc.ipo_s
        return {
            "device": f"siemens_nc {where}",
            "resolution_um": self.cfg.min_change_um,
            "max_abs_um": None,
            "max_rate_um_per_s": rate,
        }

    def close(self) -> None:
        """Stop the link; what it last knew of the NC stays readable (the run's summary)."""
        if self.link is not None:
            self.link.stop()

    def get_status(self) -> dict[str, Any]:
        st = {**super().get_status(), "updates": self.updates, "k0_um": self.sent_k0_um.tolist()}
        if self.link is not None:
            st["link_stats"] = self.link.get_status()  # writes, errors, bad replies
        return st
