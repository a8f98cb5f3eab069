"""FANUC PMC sink (paper 003): the word on X addresses with a strobe, or the shift directly.

A FANUC external machine coordinate shift is absolute and a single change larger
than the PMC's limit raises an alarm, so this sink never changes an axis by more
than `max_step_um` per update, and updates no faster than `min_update_s` (at least
two PMC scans, so the ladder sees every strobe edge). What the machine should apply
is the codec's word (dead-band and saturation included); the sink walks its output
toward it in steps: one per call on a PMC with its own clock (the daemon's cycle never
waits), and on the PMC in process (which runs on the loop's time) every step the time
since the PMC's last call allows, each two scans after the one before — a replay's row
after 10 s may move the shift as far as the daemon's cycles would have in those 10 s.

`mode: word` writes X(word), X(word)+1 (low byte first) and toggles the strobe bit;
`mode: shift` writes the commanded shift per axis (signed µm) into R registers.
With `host` the PMC is reached over Modbus TCP, written from a background thread so
the cycle never waits on the network; without, it is the software PLC's PMC
(compd.plc), run in process on the loop's clock (replay, demo). Both are reached
through the same link interface, so the sink has one code path.

At its open, and whenever its link is restored, the sink writes nothing until it has read
back what the PMC applies (registers 404/405) and, in word mode, the strobe's level (so the
next word makes an edge): its steps start from the shift the machine applies, never from 0
(compd.sinks.base, "what the device holds").
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from compd.codec import MAX_MAG, codes_from_word, word_bytes, word_from_codes
from compd.core.config import SinkConfig
from compd.io.device_time import DeviceTime, LoopTime, WallTime
from compd.io.modbus_link import ModbusLink
from compd.plc.fanuc_pmc import LSB_NM, FanucPmc
from compd.plc.link import VirtualLink
from compd.sinks.base import SAFE_TIMEOUT_S, Sink

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
    max_step_um: float = Field(5.0, ge=0.01, le=1000, description="largest change of an axis per update")
    min_update_s: float = Field(0.02, ge=0.001, le=60, description="time between updates (>= 2 PMC scans)")
    x_word: int = Field(0, ge=0, le=65534, description="register of the X byte holding the word's low byte")
    x_strobe: int = Field(2, ge=0, le=65535, description="register of the X byte holding the strobe")
    strobe_bit: int = Field(0, ge=0, le=7)
    r_command: int = Field(202, ge=0, le=65534, description="register of axis 1's commanded shift (shift mode)")
    status_address: int = Field(400, ge=0, le=65530, description="scan counter lo, hi, alarm, reset, applied 1, 2")
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
        self._scans_at_delivery: int | None = None
        self._fresh = True  # the next word sets the target (the first after a sync)

    def bind(self, axes: list[str], lsb_um: float) -> None:
        super().bind(axes, lsb_um)
        self._max_step_lsb = max(1, int(math.floor(self.cfg.max_step_um / lsb_um + 1e-9)))

    def _sync_ranges(self) -> list[tuple[int, int]]:
        """What is read back at every connect: the status block (applied shift at +4, +5) and, in
        word mode, the word's X bytes and the strobe's."""
        cfg = self.cfg
        ranges = [(cfg.status_address, 8)]
        if cfg.mode == "word":
            ranges += [(cfg.x_word, 2), (cfg.x_strobe, 1)]
        return ranges

    def _connect(self) -> ModbusLink | VirtualLink:
        """The link to the PMC: the one in this process (told the codec's LSB), or Modbus TCP."""
        cfg = self.cfg
        if self.pmc is not None:
            self.pmc.write_registers(LSB_NM, [int(round(self.lsb_um * 1000))])
            return VirtualLink(
                self.pmc, self.time, status=(cfg.status_address, 8), name="fanuc_pmc", sync=self._sync_ranges()
            )
        return ModbusLink(
            cfg.host or "",
            cfg.port,
            device_id=cfg.device_id,
            timeout_s=cfg.timeout_s,
            status=(cfg.status_address, 8),
            name="fanuc_pmc",
            sync=self._sync_ranges(),
        )

    def open(self, now_s: float) -> None:
        """Connect; nothing is written until the PMC's applied shift is read back (`sync`)."""
        self.time.set(now_s)
        self.link = self._connect()
        self.link.start()

    def take_held(self, regs: list[int], now_s: float) -> None:
        """The PMC's applied shift is where the steps start (the word's codes nearest to it) and
        what the guard and word start from; in word mode the strobe's level is taken too (the next
        word toggles it from there). Alarms latched by an earlier run are reset on the first."""
        cfg = self.cfg
        lsb = self.lsb_um
        held = {}
        for a in range(2):
            v = regs[4 + a]
            um = float(v - 0x10000 if v & 0x8000 else v)
            q = int(math.floor(abs(um) / lsb + 0.5)) * (1 if um >= 0 else -1)
            self.sent_lsb[a] = self.target_lsb[a] = max(-MAX_MAG, min(MAX_MAG, q))
            if a < len(self.axes):
                held[self.axes[a]] = um
        self._held_um = held
        if cfg.mode == "word":
            self._strobe = (regs[10] >> cfg.strobe_bit) & 1
        assert self.link is not None
        self.link.status = regs[:8]  # the status block, read with it: what the PMC applies is known from now
        self._next_update_s = -math.inf
        self._fresh = True
        self._dirty = False
        if cfg.reset_alarm_on_start and not self.syncs:
            self.link.submit(cfg.status_address + 3, [1])
            self._dirty = True  # a replay's next settle lets the PMC scan it

    def device_key(self) -> Any:
        return None if self.cfg.host is None else ("modbus", self.cfg.host, self.cfg.port)

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
        if self.time.catch_up:  # in process: the scan counter as the step lands, to count scans from
            self._scans_at_delivery = self._scans()

    def write(self, word: int, corr_um: np.ndarray, enable: np.ndarray, changed: bool, now_s: float) -> None:
        self.writes += 1
        if self.link is None or not self.link.synced():  # what the PMC applies not yet read back
            self.time.set(now_s)
            return
        if changed or self._fresh:
            self.target_lsb = list(codes_from_word(word))
            self._fresh = False
        if self.sent_lsb != self.target_lsb and now_s >= self._next_update_s:
            if self.time.catch_up:
                self._catch_up(now_s)
            elif self.link is not None and (self.link.state != "up" or self.link.pending()):
                pass  # the last step not yet acknowledged: no further step (the PMC never gets a jump)
            else:  # a PMC on its own clock: one step per call, the cycle never waits
                self.time.set(now_s)
                self.sent_lsb = step_toward(self.sent_lsb, self.target_lsb, self._max_step_lsb)
                self._deliver(now_s)
        self.time.set(now_s)

    def _catch_up(self, now_s: float) -> None:
        """The PMC on the loop's time: every step the time since its last call allows, from
        where its time stands up to `now_s`: each at most `max_step_um`, one per
        `min_update_s`, and two PMC scans after the one before (a replay's row after dt
        moves the shift as far as the daemon's cycles in that dt would have)."""
        t = self.time
        while self.sent_lsb != self.target_lsb:
            due = max(t.now_s, self._next_update_s)
            if due > now_s:
                break
            t.wait(due - t.now_s)
            if self.updates:  # a step only once the PMC has scanned twice since the last
                self._wait_scans(self._scans_at_delivery, 2)
                if t.now_s > now_s:
                    break
            self.sent_lsb = step_toward(self.sent_lsb, self.target_lsb, self._max_step_lsb)
            self._deliver(t.now_s)

    def _scans(self) -> int | None:
        """The PMC's scan counter now (None when it does not answer)."""
        assert self.link is not None
        regs = self.link.read_now(self.cfg.status_address, 2)
        return None if regs is None else regs[0] | regs[1] << 16

    def _wait_scans(self, since: int | None, scans: int) -> list[int] | None:
        """Let the PMC's time pass until it has scanned `scans` times since the counter read
        `since` (at most 2 s of wall time over Modbus); its status registers then, or None."""
        assert self.link is not None
        addr = self.cfg.status_address
        deadline = time.monotonic() + 2.0
        while since is not None and time.monotonic() < deadline:
            regs = self.link.read_now(addr, 8)
            if regs is not None and (regs[0] | regs[1] << 16) >= since + scans:
                return regs
            self.time.wait(POLL_S)
        return None

    def settle(self, now_s: float) -> None:
        """Let the PMC act on what was written (replay): once every write is acknowledged,
        wait until the PMC has scanned twice since the last write (in process: since it was
        delivered, on the loop's time; over Modbus: from now, polling the scan counter) and
        take its status from then."""
        self.time.set(now_s)
        if self.link is None or not self._dirty:
            return
        self.link.flush()
        since = self._scans_at_delivery if self.time.catch_up else self._scans()
        regs = self._wait_scans(since, 2)
        if regs is not None:
            self.link.status = regs
        self._dirty = False

    def safe(self) -> bool:
        """Walk the shift back to zero in allowed steps (the PMC would alarm on one jump),
        one step per `min_update_s` of the PMC's time; True when every step was acknowledged."""
        if self.link is None or not self.syncs:
            return True  # nothing was ever written to the PMC on this sink: nothing of ours to take back
        self.link.ensure_serving()
        ok = True
        for _ in range(10_000):
            # from what the PMC applies (read back when the link is new: a fresh one, or one
            # restored while the walk went on); unknown, nothing may be written
            if not self.resync(SAFE_TIMEOUT_S, self.time.now_s):
                return False
            if self.sent_lsb == [0, 0]:
                break
            self.sent_lsb = step_toward(self.sent_lsb, [0, 0], self._max_step_lsb)
            self._deliver(self.time.now_s)
            ok = self.link.flush(SAFE_TIMEOUT_S) and ok
            self.time.wait(self.cfg.min_update_s)
        self.target_lsb = [0, 0]
        self.time.wait(2 * self.cfg.scan_s)  # the last step's two scans
        return ok

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

    def commanded_um(self, out: np.ndarray) -> None:
        """The shift the codec's word commands (the target the sink steps toward), µm."""
        for a in range(min(2, out.shape[0])):
            out[a] = self.target_lsb[a] * self.lsb_um

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
        """`Sink.write_rows`; with the PMC in process only the rows in which something can
        change are run: a new word, a step still to make. In the others the PMC, two scans
        past its last write, applies what it applied the row before."""
        # over Modbus every row, as the PMC keeps its own time; and every row for a subclass
        # whose `write` does more (it may tell the device something every row)
        if self.pmc is None or type(self).write is not FanucPmcSink.write:
            super().write_rows(t_s, words, changed, corr_um, enable, applied_um, commanded_um, terms, positions_mm)
            return
        tl, wl, cl = t_s.tolist(), words.tolist(), changed.tolist()
        n = len(tl)
        if n == 0:
            return
        applied = np.zeros(applied_um.shape[1])
        commanded = np.zeros(commanded_um.shape[1])
        ran = np.zeros(n, dtype=bool)
        skipped = False
        for i in range(n):
            if not (cl[i] or self.writes == 0 or self._dirty or self.sent_lsb != self.target_lsb):
                self.writes += 1
                skipped = True
                continue
            if skipped:  # the PMC's time where the skipped rows' calls would have left it
                self.time.set(tl[i - 1])
                skipped = False
            now = tl[i]
            self.write(wl[i], corr_um[i], enable[i], cl[i], now)
            self.settle(now)
            self.applied_um(applied)
            self.commanded_um(commanded)
            applied_um[i] = applied
            commanded_um[i] = commanded
            ran[i] = True
        self.time.set(tl[-1])
        last = np.maximum.accumulate(np.where(ran, np.arange(n), 0))
        applied_um[:] = applied_um[last]
        commanded_um[:] = commanded_um[last]

    def flush(self, timeout_s: float) -> bool:
        return self.link is None or self.link.drain(timeout_s)

    def device_info(self) -> dict[str, Any]:
        """The word's LSB (the shift registers hold whole µm), its full scale 63 LSB, and
        the step rate: `max_step_um` per `min_update_s`."""
        cfg = self.cfg
        where = "in process" if cfg.host is None else f"at {cfg.host}:{cfg.port}"
        res = self.lsb_um if cfg.mode == "word" else max(1.0, self.lsb_um)
        return {
            "device": f"fanuc_pmc {where}",
            "resolution_um": res,
            "max_abs_um": MAX_MAG * self.lsb_um,
            "max_rate_um_per_s": cfg.max_step_um / cfg.min_update_s,
        }

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
