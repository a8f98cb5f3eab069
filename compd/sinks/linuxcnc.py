"""LinuxCNC sink: compd's correction as each axis's external offset, through HAL (`axis.L.eoffset-counts`).

LinuxCNC applies per axis an external offset of counts × scale, blended by its motion controller
within the axis's limits (`[AXIS_L] OFFSET_AV_RATIO`), and says what it applies on
`axis.L.eoffset`. compd is a HAL userspace component (compd.sinks.hal_link: its pins, how they
are netted, when the link is up); this sink turns the guarded correction of each axis into
counts: the offset applied has the correction's sign and size.

Counts act like a jog wheel (LinuxCNC moves the offset by Δcounts × scale while the offset is
enabled and the machine on and homed). So the sink never reckons from counts alone: at every
connect the link reads back the counts on compd's pin and the offset LinuxCNC applies, and the
sink counts from there (compd.sinks.base, "what the device holds"): counts = counts read +
round((correction − offset read) / count_um). It turns the offset's enable on before it moves a
count (a write of its own, sent first). The safe output walks the counts to an offset of 0 at `safe_ramp_um_per_s` and
waits until `axis.L.eoffset` reads 0 (within a count), then the component leaves HAL.

With `in_process: true` (replay, tests) the offsets are compd.plc.eoffsets' emulation on the
loop's clock, through the same link interface.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.core.config import SinkConfig
from compd.io.device_time import DeviceTime, LoopTime, WallTime
from compd.io.hal_modules import available
from compd.io.modbus_link import ModbusLink
from compd.plc.eoffsets import (
    APPLIED,
    BLOCK,
    COUNTS,
    ENABLE,
    FLAGS,
    LIMITED,
    Eoffsets,
    regs_s32,
    s32_regs,
)
from compd.plc.link import VirtualLink
from compd.plc.siemens_nc import regs_f32
from compd.sinks.base import SAFE_TIMEOUT_S, Sink
from compd.sinks.hal_link import HalRegisters

if TYPE_CHECKING:
    from compd.models.base import Model

HAL_NAME = r"^[A-Za-z][A-Za-z0-9_-]*$"
AXIS_LETTERS = ("x", "y", "z", "a", "b", "c", "u", "v", "w")
SAFE_WAIT_S = 30.0  # the safe output waits this long for LinuxCNC to apply an offset of 0


class LinuxcncConfig(SinkConfig):
    """compd's HAL component in LinuxCNC (docs/linuxcnc.md)."""

    component: str = Field("compd", pattern=HAL_NAME, description="the HAL component's name (its pins' prefix)")
    axes: list[Literal["x", "y", "z", "a", "b", "c", "u", "v", "w"]] | None = Field(
        None,
        min_length=1,
        description="LinuxCNC's axes this sink drives (its axis letters; default: the model's"
        " outputs); every model output is one of them",
    )
    units: Literal["mm", "inch"] = Field("mm", description="the machine's linear units ([TRAJ] LINEAR_UNITS)")
    count_um: float = Field(0.1, gt=0, le=100, description="the offset of one count, um (eoffset-scale in units)")
    safe_ramp_um_per_s: float = Field(
        50.0, gt=0, le=10000, description="how fast the safe output takes the offset to 0"
    )
    status_period_s: float = Field(0.02, ge=0.001, le=1, description="how often the link reads what LinuxCNC applies")
    in_process: bool = Field(
        False, description="LinuxCNC's external offsets emulated in this process (replay, tests): no LinuxCNC needed"
    )

    @model_validator(mode="after")
    def _linuxcnc_here(self) -> LinuxcncConfig:
        if not self.in_process:
            why = available()
            if why is not None:
                raise ValueError(why)
        if self.axes is not None and len(set(self.axes)) != len(self.axes):
            raise ValueError("an axis is named twice")
        return self

    def driven_axes(self) -> tuple[list[str], str] | None:
        return (list(self.axes), "axes") if self.axes else None


class LinuxcncSink(Sink):
    """Each axis's correction as LinuxCNC's external offset (see the module)."""

    Config = LinuxcncConfig

    def __init__(self, cfg: LinuxcncConfig, base_dir: str = ".", device: Eoffsets | None = None) -> None:
        super().__init__(cfg, base_dir)
        self.cfg: LinuxcncConfig = cfg
        self.device = device
        self.time: DeviceTime = LoopTime() if cfg.in_process else WallTime()
        self.outputs: list[str] = []
        self.hal_axes: list[str] = []
        self.slot: list[int] = []  # per model output, its block in the map (-1: none)
        self.base_counts = np.zeros(0, dtype=np.int64)  # read back at the last sync, per hal axis
        self.base_um = np.zeros(0)
        self.sent_counts = np.zeros(0, dtype=np.int64)
        self.enabled: list[bool] = []
        self.updates = 0

    def bind_model(self, model: Model) -> None:
        """The model's outputs, each to its LinuxCNC axis."""
        self.outputs = list(model.outputs)
        self.hal_axes = list(self.cfg.axes or self.outputs)
        self.slot = [self.hal_axes.index(a) if a in self.hal_axes else -1 for a in self.outputs]
        n = len(self.hal_axes)
        self.base_counts = np.zeros(n, dtype=np.int64)
        self.base_um = np.zeros(n)
        self.sent_counts = np.zeros(n, dtype=np.int64)
        self.enabled = [False] * n

    def device_key(self) -> Any:
        return None if self.cfg.in_process else ("linuxcnc", self.cfg.component)

    def _connect(self) -> ModbusLink | VirtualLink:
        n = len(self.hal_axes)
        block = (0, BLOCK * n)
        if self.cfg.in_process:
            if self.device is None:
                self.device = Eoffsets(n, self.cfg.count_um)
            return VirtualLink(self.device, self.time, status=block, name="linuxcnc", sync=[block])
        device = HalRegisters(self.cfg.component, self.hal_axes, self.cfg.units, self.cfg.count_um)
        return ModbusLink(
            "", 0, status=block, status_period_s=self.cfg.status_period_s, name="linuxcnc", sync=[block], device=device
        )

    def open(self, now_s: float) -> None:
        """Start the link; nothing is written until what LinuxCNC applies is read back (`sync`)."""
        self.time.set(now_s)
        self.link = self._connect()
        self.link.start()

    def take_held(self, regs: list[int], now_s: float) -> None:
        """Counts on compd's pin and the offset LinuxCNC applies, per axis: the sink counts from them,
        the guard starts from the offset (`held_um`); the offset's enable is turned on (no count moves)."""
        held: dict[str, float] = {}
        for k, a in enumerate(self.hal_axes):
            b = BLOCK * k
            if b + FLAGS >= len(regs):
                continue
            counts = regs_s32(regs[b + COUNTS], regs[b + COUNTS + 1])
            um = regs_f32(regs[b + APPLIED], regs[b + APPLIED + 1])
            if not math.isfinite(um):
                continue
            self.base_counts[k], self.base_um[k], self.sent_counts[k] = counts, um, counts
            self.enabled[k] = bool(regs[b + ENABLE])
            held[a] = um
        self._held_um = held
        assert self.link is not None
        for k in range(len(self.hal_axes)):  # its own register: the queue never merges it into a count's write
            if not self.enabled[k]:
                self.link.submit(BLOCK * k + ENABLE, [1])
                self.enabled[k] = True

    def _counts(self, k: int, um: float) -> int:
        """The counts at which LinuxCNC applies `um` on axis k (from the last read-back)."""
        return int(self.base_counts[k] + round((um - self.base_um[k]) / self.cfg.count_um))

    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        self.time.set(now_s)
        self.writes += 1
        if self.link is None or not self.link.synced():
            return
        sent = False
        for i, k in enumerate(self.slot):
            if k < 0:
                continue
            um = float(corr_um[i]) if enable[i] else 0.0
            if not math.isfinite(um):
                continue
            counts = self._counts(k, um)
            if counts != self.sent_counts[k]:
                self.link.submit(BLOCK * k + COUNTS, s32_regs(counts))
                self.sent_counts[k] = counts
                sent = True
        if sent:
            self.updates += 1

    def settle(self, now_s: float) -> None:
        self.time.set(now_s)
        if self.link is not None:
            self.link.flush()

    def flush(self, timeout_s: float) -> bool:
        return self.link is None or self.link.drain(timeout_s)

    def _status_um(self, out: np.ndarray, regs: list[int] | None) -> None:
        out[:] = np.nan
        if regs is None:
            return
        for s, name in enumerate(self.axes[: out.shape[0]]):
            if name in self.hal_axes:
                b = BLOCK * self.hal_axes.index(name)
                if b + APPLIED + 1 < len(regs):
                    out[s] = regs_f32(regs[b + APPLIED], regs[b + APPLIED + 1])

    def applied_um(self, out: np.ndarray) -> None:
        """`axis.L.eoffset` as LinuxCNC last said it, for the word's axes, µm."""
        self._status_um(out, self.link.status if self.link is not None else None)

    def commanded_um(self, out: np.ndarray) -> None:
        """The offset the counts sent ask for, for the word's axes, µm."""
        out[:] = np.nan
        for s, name in enumerate(self.axes[: out.shape[0]]):
            if name in self.hal_axes and self.link is not None and self.link.synced():
                k = self.hal_axes.index(name)
                out[s] = self.base_um[k] + (self.sent_counts[k] - self.base_counts[k]) * self.cfg.count_um

    def limited(self) -> bool:
        """LinuxCNC limited the offsets' motion by a soft limit (`motion.eoffset-limited`)."""
        regs = self.link.status if self.link is not None else None
        if not regs:
            return False
        return any(
            regs[BLOCK * k + FLAGS] & LIMITED for k in range(len(self.hal_axes)) if BLOCK * k + FLAGS < len(regs)
        )

    def safe(self) -> bool:
        """Walk each axis's counts to an offset of 0 at `safe_ramp_um_per_s` and wait until LinuxCNC
        applies 0 (within one count); True when it does."""
        if self.link is None or not self.syncs:
            return True  # compd never wrote a count on this sink: nothing of its to take back
        self.link.ensure_serving()
        if not self.resync(SAFE_TIMEOUT_S, self.time.now_s):
            return False  # LinuxCNC does not answer (off, not homed): counts would not act
        step_s = max(self.cfg.status_period_s, 0.01)
        step_counts = max(1, int(self.cfg.safe_ramp_um_per_s * step_s / self.cfg.count_um))
        for k in range(len(self.hal_axes)):
            goal = self._counts(k, 0.0)
            while self.sent_counts[k] != goal:
                c = int(self.sent_counts[k])
                c += max(-step_counts, min(step_counts, goal - c))
                self.link.submit(BLOCK * k + COUNTS, s32_regs(c))
                self.sent_counts[k] = c
                if not self.link.flush(SAFE_TIMEOUT_S):
                    return False
                if not self.cfg.in_process:
                    time.sleep(step_s)
        return self._await_zero()

    def _await_zero(self) -> bool:
        """Until LinuxCNC says it applies 0 on every axis (within one count)."""
        deadline = time.monotonic() + SAFE_WAIT_S
        out = np.zeros(len(self.hal_axes))
        while True:
            assert self.link is not None
            regs = self.link.read_now(0, BLOCK * len(self.hal_axes))
            if regs is not None:
                for k in range(len(self.hal_axes)):
                    out[k] = regs_f32(regs[BLOCK * k + APPLIED], regs[BLOCK * k + APPLIED + 1])
                if np.all(np.abs(out) <= self.cfg.count_um * 1.5):
                    return True
            if self.cfg.in_process or time.monotonic() >= deadline:
                return False
            time.sleep(0.01)

    @classmethod
    def in_process_config(cls, cfg: SinkConfig) -> SinkConfig:
        """LinuxCNC's offsets emulated in this process, with this section's axes and count."""
        return cfg.model_copy(update={"in_process": True})

    def device_info(self) -> dict[str, Any]:
        """A count is the resolution; LinuxCNC blends the offset at its axis's OFFSET_AV_RATIO."""
        where = "in process" if self.cfg.in_process else f"HAL component {self.cfg.component}"
        return {
            "device": f"linuxcnc {where}",
            "resolution_um": self.cfg.count_um,
            "max_abs_um": None,
            "max_rate_um_per_s": None,
        }

    def close(self) -> None:
        """Stop the link (its worker releases the HAL component)."""
        if self.link is not None:
            self.link.stop()

    def get_status(self) -> dict[str, Any]:
        st = {
            **super().get_status(),
            "updates": self.updates,
            "counts": self.sent_counts.tolist(),
            "eoffset_limited": self.limited(),
        }
        if self.link is not None:
            st["link_stats"] = self.link.get_status()
        return st
