"""Siemens temperature compensation sink (paper 001): K0, tanβ, P0 per axis.

The NC applies ΔK = K0 + tanβ·(P − P0) and spreads every change over its IPO cycles
(MD32760). This sink writes SD43900 K0 (mm) from the guarded correction of each
axis; when the model's `linear_terms()` gives them — per output the error's slope
(µm/mm) and reference position P0 (mm), its outputs being the error at P0 — it
writes SD43910 tanβ = −slope/1000 and SD43920 P0 too, and sets MD32750 bit 1
(position dependent) as well as bit 0. Writes go out when a value moved by
`min_change_um` and no faster than `min_update_s`. With `host` the NC's data is reached
over Modbus TCP; without, it is the software PLC's NC (compd.plc), in process on the
loop's clock. Both through the same link interface: the sink has one code path.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from pydantic import Field

from compd.config import SinkConfig
from compd.plc.siemens_nc import APPLIED, BLOCK, K0, TYPE, f32_regs, regs_f32
from compd.sinks.base import LinkState, Sink
from compd.sinks.device_time import DeviceTime, LoopTime, WallTime

if TYPE_CHECKING:
    from compd.models.base import Model
    from compd.plc.link import VirtualLink
    from compd.plc.siemens_nc import SiemensNc
    from compd.sinks.modbus_link import ModbusLink


class SiemensConfig(SinkConfig):
    """The NC's data over Modbus TCP (or the software PLC's NC in process)."""

    host: str | None = Field(None, description="NC gateway over Modbus TCP; none = the software PLC's NC in process")
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    axes: dict[str, Annotated[int, Field(ge=0, le=63)]] | None = Field(
        None, description="model output → NC axis index (default: in order)"
    )
    min_change_um: float = Field(0.1, ge=0, le=100, description="smaller changes are not sent")
    min_update_s: float = Field(0.05, ge=0.001, le=60)
    ipo_s: float = Field(0.004, ge=0.0005, le=0.1, description="in-process NC: IPO cycle")
    velo_factor: float = Field(1e-5, gt=0, le=1, description="in-process NC: MD32760 (fraction)")


class SiemensSink(Sink):
    """K0 (and tanβ, P0 for position-dependent models) per axis."""

    Config = SiemensConfig

    def __init__(self, cfg: SiemensConfig, base_dir: str = ".", nc: SiemensNc | None = None) -> None:
        super().__init__(cfg, base_dir)
        self.cfg: SiemensConfig = cfg
        # the NC in this process (given, or the software PLC's when no host is set) runs on
        # the loop's time; one over Modbus on its own
        if nc is None and cfg.host is None:
            from compd.plc.siemens_nc import SiemensNc

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

    def bind_model(self, model: Model) -> None:
        """The model (for its output names and its linear terms, where it has them)."""
        self.model = model
        self.outputs = list(model.outputs)
        m = self.cfg.axes or {a: i for i, a in enumerate(self.outputs)}
        self.nc_axis = [m.get(a, -1) for a in self.outputs]
        self.sent_k0_um = np.full(len(self.outputs), np.nan)

    def device_key(self) -> Any:
        return None if self.cfg.host is None else ("modbus", self.cfg.host, self.cfg.port)

    def link_state(self) -> LinkState:
        return "closed" if self.link is None else self.link.state  # type: ignore[return-value]

    def _connect(self) -> ModbusLink | VirtualLink:
        """The link to the NC's data (the status block: every axis the sink writes)."""
        count = BLOCK * (max(self.nc_axis, default=0) + 1)
        if self.nc is not None:
            from compd.plc.link import VirtualLink

            status = (0, min(count, BLOCK * self.nc.n))
            return VirtualLink(self.nc, self.time, status=status, name="siemens")
        from compd.sinks.modbus_link import ModbusLink

        return ModbusLink(self.cfg.host or "", self.cfg.port, device_id=self.cfg.device_id, status=(0, count), name="siemens")

    def open(self, now_s: float) -> None:
        self.time.set(now_s)
        self.link = self._connect()
        self.link.start()
        # a model may offer linear terms only in some modes; output-test binds no model
        linear = self.model is not None and self.model.linear_terms() is not None
        for ax in self.nc_axis:
            if ax >= 0:
                self.link.submit(BLOCK * ax + TYPE, [3 if linear else 1])

    def write(
        self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float
    ) -> None:
        self.time.set(now_s)
        self.writes += 1
        if now_s < self._next_s or not self.outputs or self.link is None:
            return
        terms = self.model.linear_terms()
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
            self._next_s = now_s + self.cfg.min_update_s

    def settle(self, now_s: float) -> None:
        """Every write acknowledged; the NC's IPO cycles up to `now_s` (in process) have run
        when the status is next read."""
        self.time.set(now_s)
        if self.link is not None:
            self.link.flush()

    def safe(self) -> None:
        """K0 = 0 (and tanβ = 0): the NC ramps ΔK away at its own MD32760 rate."""
        if self.link is None:
            return
        for ax in self.nc_axis:
            if ax >= 0:
                self.link.submit(BLOCK * ax + K0, f32_regs(0.0) + f32_regs(0.0))
        self.link.flush()

    def applied_um(self, out: np.ndarray) -> None:
        """ΔK the NC applies now, for the word's axes (high byte first), µm."""
        regs = self.link.status if self.link is not None else None
        out[:] = np.nan
        if regs is None:
            return
        for slot, name in enumerate(self.axes[: out.shape[0]]):
            if name in self.outputs:
                ax = self.nc_axis[self.outputs.index(name)]
                if ax >= 0 and BLOCK * ax + APPLIED + 1 < len(regs):
                    out[slot] = 1000.0 * regs_f32(regs[BLOCK * ax + APPLIED], regs[BLOCK * ax + APPLIED + 1])

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
        return {"device": f"siemens_nc {where}", "resolution_um": self.cfg.min_change_um,
                "max_abs_um": None, "max_rate_um_per_s": rate}

    def close(self) -> None:
        """Stop the link; what it last knew of the NC stays readable (the run's summary)."""
        if self.link is not None:
            self.link.stop()

    def get_status(self) -> dict[str, Any]:
        st = {**super().get_status(), "updates": self.updates, "k0_um": self.sent_k0_um.tolist()}
        if self.link is not None:
            st["link_stats"] = self.link.get_status()  # writes, errors, bad replies
        return st
