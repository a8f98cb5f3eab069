"""FANUC PMC sink (paper 003): the word on X addresses with a strobe, or the shift directly.

A FANUC external machine coordinate shift is absolute and a single change larger
than the PMC's limit raises an alarm, so this sink never changes an axis by more
than `max_step_um` per update, and updates no faster than `min_update_s` (at least
two PMC scans, so the ladder sees every strobe edge). What the machine should apply
is the codec's word (dead-band and saturation included); the sink walks its output
toward it in steps.

`mode: word` writes X(word), X(word)+1 (low byte first) and toggles the strobe bit;
`mode: shift` writes the commanded shift per axis (signed µm) into R registers.
With `host` the PMC is reached over Modbus TCP, written from a background thread so
the cycle never waits on the network; without, it is the software PLC's PMC
(compd.plc), run in process on the loop's clock (replay, demo). Both are reached
through the same link interface, so the sink has one code path.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.codec import codes_from_word, word_bytes, word_from_codes
from compd.config import SinkConfig
from compd.sinks.base import LinkState, Sink
from compd.sinks.device_time import DeviceTime, LoopTime, WallTime

if TYPE_CHECKING:
    from compd.plc.fanuc_pmc import FanucPmc
    from compd.plc.link import VirtualLink
    from compd.sinks.modbus_link import ModbusLink

POLL_S = 0.002  # between two reads of the scan counter while waiting for the PMC to scan


def step_toward(sent: list[int], target: list[int], max_step: int) -> list[int]:
    """Move each value toward its target by at most `max_step` (integers, LSB)."""
    out = []
    for s, t in zip(sent, target, strict=True):
        d = t - s
        out.append(s + (max_step if d > max_step else (-max_step if d < -max_step else d)))
    return out


class FanucPmcConfig(SinkConfig):
    """Where the PMC is and how its memory is laid out (defaults: the software PLC's PMC map)."""

    mode: Literal["word", "shift"] = Field("word", description="word + strobe on X, or R shift registers")
    host: str | None = Field(None, description="PMC over Modbus TCP; none = the software PLC's PMC in process")
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    timeout_s: float = Field(0.25, ge=0.001, le=30)
    max_step_um: float = Field(
        5.0, ge=0.01, le=1000, description="largest change of an axis per update"
    )
    min_update_s: float = Field(
        0.02, ge=0.001, le=60, description="time between updates (>= 2 PMC scans)"
    )
    x_word: int = Field(0, ge=0, le=65534, description="register of the X byte holding the word's low byte")
    x_strobe: int = Field(2, ge=0, le=65535, description="register of the X byte holding the strobe")
    strobe_bit: int = Field(0, ge=0, le=7)
    r_command: int = Field(
        202, ge=0, le=65534, description="register of axis 1's commanded shift (shift mode)"
    )
    status_address: int = Field(
        400, ge=0, le=65530, description="scan counter lo, hi, alarm, reset, applied 1, 2"
    )
    reset_alarm_on_start: bool = True
    scan_s: float = Field(0.008, ge=0.0005, le=1, description="in-process PMC: scan time")
    step_limit_um: int = Field(10, ge=1, le=1000, description="in-process PMC: its step limit (D0)")

    @model_validator(mode="after")
    def _check(self) -> FanucPmcConfig:
        if self.mode == "word" and self.x_strobe in (self.x_word, self.x_word + 1):
            raise ValueError("x_strobe must not be one of the word's two X bytes")
        if self.host is None and self.max_step_um > self.step_limit_um:
            raise ValueError("max_step_um exceeds the in-process PMC's step_limit_um: every update would alarm")
        return self


class FanucPmcSink(Sink):
    """Steps the machine's shift toward the codec's word, within the PMC's step limit."""

    Config = FanucPmcConfig

    def __init__(self, cfg: FanucPmcConfig, base_dir: str = ".", pmc: FanucPmc | None = None) -> None:
        super().__init__(cfg, base_dir)
        self.cfg: FanucPmcConfig = cfg
        # the PMC in this process (given, or the software PLC's when no host is set) runs on
        # the loop's time; one over Modbus on its own
        if pmc is None and cfg.host is None:
            from compd.plc.fanuc_pmc import FanucPmc

            pmc = FanucPmc(scan_s=cfg.scan_s, step_limit_um=cfg.step_limit_um)
        self.pmc = pmc
        self.time: DeviceTime = LoopTime() if pmc is not None else WallTime()
        self.sent_lsb = [0, 0]
        self.target_lsb = [0, 0]
        self._strobe = 0
        self._next_update_s = -math.inf
        self.updates = 0
        self._dirty = False
        self._max_step_lsb = 1

    def bind(self, axes: list[str], lsb_um: float) -> None:
        super().bind(axes, lsb_um)
        self._max_step_lsb = max(1, int(math.floor(self.cfg.max_step_um / lsb_um + 1e-9)))

    def _connect(self) -> ModbusLink | VirtualLink:
        """The link to the PMC: the one in this process (told the codec's LSB), or Modbus TCP."""
        cfg = self.cfg
        if self.pmc is not None:
            from compd.plc.fanuc_pmc import LSB_NM
            from compd.plc.link import VirtualLink

            self.pmc.write_registers(LSB_NM, [int(round(self.lsb_um * 1000))])
            return VirtualLink(self.pmc, self.time, status=(cfg.status_address, 8), name="fanuc_pmc")
        from compd.sinks.modbus_link import ModbusLink

        return ModbusLink(
            cfg.host or "",
            cfg.port,
            device_id=cfg.device_id,
            timeout_s=cfg.timeout_s,
            status=(cfg.status_address, 8),
            name="fanuc_pmc",
        )

    def open(self, now_s: float) -> None:
        cfg = self.cfg
        self.time.set(now_s)
        self.link = self._connect()
        self.link.start()
        if cfg.reset_alarm_on_start:
            self.link.submit(cfg.status_address + 3, [1])
        self._deliver(now_s)

    def device_key(self) -> Any:
        return None if self.cfg.host is None else ("modbus", self.cfg.host, self.cfg.port)

    def link_state(self) -> LinkState:
        return "closed" if self.link is None else self.link.state  # type: ignore[return-value]

    def _deliver(self, now_s: float) -> None:
        cfg = self.cfg
        link = self.link
        assert link is not None
        c1, c2 = self.sent_lsb
        if cfg.mode == "word":
            high, low = word_bytes(word_from_codes(c1, c2))
            self._strobe ^= 1
            regs = [low, high]  # X(word) holds the low byte
            if cfg.x_strobe == cfg.x_word + 2:
                link.submit(cfg.x_word, regs + [self._strobe << cfg.strobe_bit])
            else:
                link.submit(cfg.x_word, regs)
                link.submit(cfg.x_strobe, [self._strobe << cfg.strobe_bit])
        else:
            lsb = self.lsb_um
            link.submit(cfg.r_command, [int(round(c1 * lsb)), int(round(c2 * lsb))])
        self.updates += 1
        self._dirty = True
        self._next_update_s = now_s + cfg.min_update_s

    def write(
        self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float
    ) -> None:
        self.time.set(now_s)
        if changed or self.writes == 0:
            self.target_lsb = list(codes_from_word(word))
        self.writes += 1
        if self.sent_lsb != self.target_lsb and now_s >= self._next_update_s:
            self.sent_lsb = step_toward(self.sent_lsb, self.target_lsb, self._max_step_lsb)
            self._deliver(now_s)

    def settle(self, now_s: float) -> None:
        """Let the PMC act on what was written (replay): once every write is acknowledged,
        wait until the PMC has scanned twice and take its status from then (in process the
        wait runs its scans on the loop's time; over Modbus it polls the scan counter)."""
        self.time.set(now_s)
        if self.link is None or not self._dirty:
            return
        self.link.flush()
        addr = self.cfg.status_address
        first = self.link.read_now(addr, 8)
        deadline = time.monotonic() + 2.0
        while first is not None and time.monotonic() < deadline:
            regs = self.link.read_now(addr, 8)
            if regs is not None and (regs[0] | regs[1] << 16) >= (first[0] | first[1] << 16) + 2:
                self.link.status = regs
                break
            self.time.wait(POLL_S)
        self._dirty = False

    def safe(self) -> None:
        """Walk the shift back to zero in allowed steps (the PMC would alarm on one jump),
        one step per `min_update_s` of the PMC's time."""
        self.target_lsb = [0, 0]
        if self.link is None:
            return
        for _ in range(10_000):
            if self.sent_lsb == [0, 0]:
                break
            self.sent_lsb = step_toward(self.sent_lsb, [0, 0], self._max_step_lsb)
            self._deliver(self.time.now_s)
            self.link.flush()
            self.time.wait(self.cfg.min_update_s)
        self.time.wait(2 * self.cfg.scan_s)  # the last step's two scans

    def status_registers(self) -> list[int] | None:
        """scan lo, scan hi, alarm, reset, applied 1, applied 2, alarm count 1, 2."""
        return self.link.status if self.link is not None else None

    def applied_um(self, out: np.ndarray) -> None:
        regs = self.status_registers()
        if regs is None:
            out[:] = np.nan
            return
        for a in range(min(2, out.shape[0])):
            v = regs[4 + a]
            out[a] = float(v - 0x10000 if v & 0x8000 else v)

    def flush(self, timeout_s: float) -> bool:
        return self.link is None or self.link.drain(timeout_s)

    def device_info(self) -> dict[str, Any]:
        """The word's LSB (the shift registers hold whole µm), its full scale 63 LSB, and
        the step rate: `max_step_um` per `min_update_s`."""
        from compd.codec import MAX_MAG

        cfg = self.cfg
        where = "in process" if cfg.host is None else f"at {cfg.host}:{cfg.port}"
        res = self.lsb_um if cfg.mode == "word" else max(1.0, self.lsb_um)
        return {"device": f"fanuc_pmc {where}", "resolution_um": res, "max_abs_um": MAX_MAG * self.lsb_um,
                "max_rate_um_per_s": cfg.max_step_um / cfg.min_update_s}

    def close(self) -> None:
        """Stop the link; what it last knew of the PMC stays readable (the run's summary)."""
        if self.link is not None:
            self.link.stop()

    def get_status(self) -> dict[str, Any]:
        regs = self.status_registers()
        st: dict[str, Any] = {
            **super().get_status(),
            "mode": self.cfg.mode,
            "updates": self.updates,
            "sent_um": [c * self.lsb_um for c in self.sent_lsb],
            "target_um": [c * self.lsb_um for c in self.target_lsb],
        }
        if self.link is not None:
            st["link_stats"] = self.link.get_status()  # writes, errors, bad replies
        if regs is not None:
            st["alarm"] = regs[2]
            st["scans"] = regs[0] | (regs[1] << 16)
            st["alarm_count"] = regs[6:8]
        return st
