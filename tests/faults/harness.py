"""The fault-injection harness: compd's pipeline (App from a config) against hil_sim devices over
real protocols, a fault switched on mid-run, and what the machine saw measured cycle by cycle.

A run is short and on the wall clock (the devices answer in real time): warm-up until the
correction has settled, the fault from `FAULT_S`, optionally cleared at `CLEAR_S`, end at
`duration_s`. Per cycle the harness records the guard's output, enable bit and axis state,
and the word on the (emulated) PCI-1756 card. `FaultRun.run()` returns the measurements the
matrix table shows; `record()` writes them as JSON for `python -m compd.commissioning.faultdoc`.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from compd.codec import decode
from compd.config import load_config
from compd.core.clock import WallClock
from compd.cycle.limiter import AxisState
from compd.daemon.app import App
from tests.faults.matrix import MATRIX
from tests.logcapture import log_lines

RESULTS_ENV = "COMPD_FAULTS_OUT"  # a folder: each row writes <row>.json there (else tmp_path)
PERIOD_S = 0.01
SLEW_UM_PER_S = 20.0
RAMP_UM_PER_S = 20.0
FAULT_S = 0.6  # the correction (−8.98 µm at 24 °C) has settled by then at 20 µm/s
CLEAR_S = 1.4
MIN_S = 1.0  # a run lasts at least this long, and 0.3 s past its last action
MAX_S = 10.0  # … and stops once the axis has settled (see FaultRun.settled), at most after this
SENSOR = "T_xi"
T0_C = 20.0
WANT_UM = -13.6e-6 * 165.0 * 1000.0 * (24.0 - T0_C)  # the correction at 24 °C


class JumpClock(WallClock):
    """Monotonic time plus an offset a test can jump (a suspend or a stall seen by the loop)."""

    fork_safe = False  # the offset lives in the test's process: the I/O workers stay threads of it

    def __init__(self) -> None:
        super().__init__(0.0002)
        self.offset_s = 0.0

    def now(self) -> float:
        return time.monotonic() + self.offset_s

    def wait_until(self, deadline_s: float) -> None:
        super().wait_until(deadline_s - self.offset_s)


def base_config(source: dict[str, Any], policy: str, **guard: Any) -> dict[str, Any]:
    """One PT100 → ξ-point spindle model → guard → PCI-1756 (emulated card)."""
    signals = {SENSOR: {"min": 0.0, "max": 80.0, "max_rate_per_s": 2.0, **guard.pop("limits", {})}}
    return {
        "loop": {"period_s": PERIOD_S},
        "sources": [source],
        "model": {
            "kind": "xi_spindle",
            "inputs": [SENSOR],
            "outputs": ["z"],
            "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0, "t0_c": T0_C},
        },
        "guard": {
            "max_slew_um_per_s": SLEW_UM_PER_S,
            "ramp_um_per_s": RAMP_UM_PER_S,
            "recovery_s": 0.3,
            "fault_policy": policy,
            "stale_after_s": 0.3,
            "signals": signals,
            **guard,
        },
        "sink": {"kind": "pci1756", "heartbeat_bit": 16},
        "log": {"path": "log.csv", "period_s": 0.05, "flush_s": 0.1},
        "status": {"period_s": 0.1},
    }


def modbus_tcp_source(port: int, **kw: Any) -> dict[str, Any]:
    return {
        "kind": "modbus",
        "name": "pt",
        "transport": "tcp",
        "host": "127.0.0.1",
        "port": port,
        "poll_period_s": 0.02,
        "timeout_s": 0.1,
        "stale_after_s": 0.3,
        "reconnect_min_s": 0.05,
        "reconnect_max_s": 0.2,
        "channels": [{"name": SENSOR, "address": 0}],
        **kw,
    }


@dataclass
class Measured:
    """What one run measured (the columns of the matrix table)."""

    max_step_um: float  # largest change of the applied (enabled) correction in one cycle
    allowed_step_um: float  # slew (or ramp) × the nominal period
    max_step_ratio: float  # largest step ÷ (rate × that cycle's dt): ≤ 1 means never too fast
    time_to_safe_s: float | None  # fault switched on → the axis in its configured safe state
    recovered: bool
    samples_lost: int
    event: str | None  # "T_xi bad: burnout" from the guard's event list
    logged: bool  # the same event as a key=value log record with sensor and reason
    word_valid: bool
    policy_ok: bool
    running: bool
    cycles: int
    fault_t_s: float | None
    # the word itself: its largest step between two enabled cycles (LSB); its pace (m steps
    # ÷ (m·lsb/slew) of licensed time, ≤ 1); the largest |word − guarded correction| while
    # enabled, against the codec's band (+ what the correction moves in two cycles)
    word_max_step_lsb: int = 0
    word_pace_ratio: float = 0.0
    word_max_error_um: float = 0.0
    word_band_um: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class Trace:
    t: list[float] = field(default_factory=list)
    out: list[float] = field(default_factory=list)
    enable: list[bool] = field(default_factory=list)
    state: list[int] = field(default_factory=list)
    word: list[int] = field(default_factory=list)
    jumps: list[bool] = field(default_factory=list)
    target: list[float] = field(default_factory=list)
    dt: list[float] = field(default_factory=list)  # the time the guard licensed this cycle


class FaultRun:
    """One matrix row: a config, a schedule of actions (the fault), a run, the measurements."""

    def __init__(
        self, tmp_path: Path, cfg: dict[str, Any], *, duration_s: float = MAX_S, clock: WallClock | None = None
    ) -> None:
        self.tmp_path = tmp_path
        self.cfg = cfg
        self.policy = cfg["guard"]["fault_policy"]
        self.expect_recovery = False  # rows whose fault clears by itself (clock jump); a "clear" action implies it
        self.duration_s = duration_s
        self.clock = clock
        self.actions: list[tuple[float, str, Callable[[], None]]] = []
        self.times: dict[str, float] = {}  # label → loop time the action ran
        self.trace = Trace()
        self.app: App | None = None
        self.summary: dict[str, Any] = {}
        self.records: list[Any] = []  # the run's log lines (tests.logcapture)

    def at(self, t_s: float, label: str, action: Callable[[], None]) -> FaultRun:
        """Run `action` (on a helper thread) `t_s` after the loop started; `label` 'fault' marks
        the fault switched on."""
        self.actions.append((t_s, label, action))
        return self

    # ------------------------------------------------------------------ run
    def run(self, sensor: str = SENSOR, reasons: tuple[str, ...] = (), kind: str = "bad") -> Measured:
        """Run; the row's event is the guard event (`sensor`, `kind`, one of `reasons`)."""
        path = self.tmp_path / "c.yaml"
        path.write_text(yaml.safe_dump(self.cfg))
        app = self.app = App(load_config(path), duration_s=self.duration_s)
        if self.clock is not None:
            app.clock = app.loop.clock = self.clock
        started = threading.Event()
        t0 = [0.0]
        tr = self.trace
        guard = app.guard
        card = app.sink.card
        port = app.sink.cfg.word_port
        n_jumps = [0]

        def hook(loop: Any, now: float) -> None:
            if not started.is_set():
                t0[0] = time.monotonic()
                started.set()
            elif len(self.times) == len(self.actions) and self.settled(now):
                loop.stop()  # the outcome is decided: no need to wait for MAX_S
            jumps = sum(1 for e in guard.events if e[2] == "jump")
            tr.jumps.append(jumps != n_jumps[0])
            n_jumps[0] = jumps
            tr.t.append(now)
            tr.out.append(float(guard.out_um[0]))
            tr.enable.append(bool(guard.enable[0]))
            tr.state.append(int(guard.state[0]))
            tr.target.append(float(guard.target_um[0]))
            tr.dt.append(float(guard.dt_s))
            tr.word.append(card.read_do_word(port))

        app.loop.cycle_hooks.append(hook)
        stop = threading.Event()

        def scheduler() -> None:
            if not started.wait(10):
                return
            for t_s, label, action in sorted(self.actions, key=lambda a: a[0]):
                if stop.wait(max(t0[0] + t_s - time.monotonic(), 0.0)):
                    return
                action()
                self.times[label] = app.clock.now()  # after: a clock jump counts from its new time

        th = threading.Thread(target=scheduler, name="fault-schedule")
        th.start()
        running = True
        # the event lines come from the service (a process of its own on the wall clock): read
        # them where the journal would, on stderr
        with log_lines() as records:
            try:
                self.summary = app.run()
            except Exception:
                running = False
                raise
            finally:
                stop.set()
                th.join(10)
        self.records = records
        return self._measure(sensor, reasons, kind, running)

    def settled(self, now: float) -> bool:
        """All actions done, 0.3 s past the last, MIN_S run, and the axis either back at the
        model's correction (NORMAL, within 0.25 µm of its target) or, unless the fault is gone, in its safe state."""
        tr = self.trace
        if not tr.t or now - tr.t[0] < MIN_S or (self.times and now - max(self.times.values()) < 0.3):
            return False
        k = len(tr.t) - 1
        if tr.state[k] == AxisState.NORMAL:
            return abs(tr.out[k] - tr.target[k]) <= 0.25
        if self.expect_recovery or "clear" in self.times:  # the fault is gone (cleared, or by itself): wait for NORMAL
            return False
        return tr.state[k] == AxisState.FAULT and self._safe(k) and (self.policy != "ramp_to_zero" or tr.out[k] == 0.0)

    # -------------------------------------------------------------- measure
    def _measure(self, sensor: str, reasons: tuple[str, ...], kind: str, running: bool) -> Measured:
        app = self.app
        assert app is not None
        tr = self.trace
        rate = max(SLEW_UM_PER_S, RAMP_UM_PER_S)
        max_step = 0.0
        ratio = 0.0
        for k in range(1, len(tr.t)):
            if not tr.enable[k]:
                continue  # not applied: `disable` drops the correction at once by design
            dt = PERIOD_S if tr.jumps[k] else tr.t[k] - tr.t[k - 1]
            step = abs(tr.out[k] - tr.out[k - 1])
            max_step = max(max_step, step)
            if step > 0:
                ratio = max(ratio, step / (rate * dt) if dt > 0 else math.inf)
        word_valid = all(math.isfinite(o) for o in tr.out)
        for w, en in zip(tr.word, tr.enable, strict=True):
            if not 0 <= w <= 0xFFFF:
                word_valid = False
                continue
            code = decode(w)[0]
            if code.magnitude > 63:
                word_valid = False
            # (its distance from the correction is word_max_error_um, against the codec's band
            # plus the trail a late cycle licenses: see _measure_word)
            if code.enable and not en:
                word_valid = False
        word = self._measure_word()
        t_fault = self.times.get("fault")
        time_to_safe = None
        policy_ok = True
        if t_fault is not None:
            for k, t in enumerate(tr.t):
                if t < t_fault or tr.state[k] != AxisState.FAULT:
                    continue
                if self._safe(k):
                    time_to_safe = t - t_fault
                    break
            policy_ok = self._policy_held()
        events = [(s, e, r) for _, s, e, r in app.guard.events if s == sensor and e == kind]
        hit = next(((s, e, r) for s, e, r in events if not reasons or r in reasons), None)
        event = f"{hit[0]} {hit[1]}: {hit[2]}" if hit else None
        log_event, key = {"bad": ("sensor_bad", "sensor"), "jump": ("clock_jump", "clock")}[kind]
        logged = hit is not None and any(
            getattr(r, "event", None) == log_event
            and getattr(r, key, None) == sensor
            and getattr(r, "reason", None) == hit[2]
            for r in self.records
        )
        log_counts = self.summary.get("log") or {}
        m = Measured(
            max_step_um=max_step,
            allowed_step_um=rate * PERIOD_S,
            max_step_ratio=ratio,
            time_to_safe_s=time_to_safe,
            recovered=bool(tr.state) and tr.state[-1] == AxisState.NORMAL,
            samples_lost=int(log_counts.get("rows_dropped", 0)),
            event=event,
            logged=logged,
            word_valid=word_valid,
            policy_ok=policy_ok,
            # still cycling 0.3 s after the last action (the run stops itself once settled)
            running=running
            and bool(tr.t)
            and tr.t[-1] - tr.t[0] >= max([MIN_S, *(t - tr.t[0] + 0.3 for t in self.times.values())]) - 2 * PERIOD_S,
            cycles=len(tr.t),
            fault_t_s=None if t_fault is None else t_fault - tr.t[0],
            **word,
        )
        return m

    def _measure_word(self) -> dict[str, Any]:
        """The word on the card, cycle by cycle, against the codec's promises.

        * one LSB a cycle at most;
        * pace: every LSB paid from the time the guard licensed (slew·dt/LSB a cycle), a
          settled word (on the code nearest the correction) banking at most one LSB plus
          that cycle's refill; the ratio LSB stepped ÷ budget there is ≤ 1;
        * distance from the guarded correction ≤ the band (max(dead-band, LSB)), plus what
          the correction moves in two cycles, plus what a stall licensed beyond one LSB a
          cycle while the word catches up one LSB a cycle.
        """
        app = self.app
        assert app is not None
        tr = self.trace
        enc = app.encoder
        lsb = enc.lsb_um
        rate = SLEW_UM_PER_S / lsb  # LSB per second
        max_step = 0
        pace = 0.0
        over = -math.inf  # largest |word − correction| beyond what that cycle allowed
        budget = 0.0
        behind = 0.0  # LSB licensed beyond one a cycle, not yet caught up
        allowed_um = enc.band_um + 2 * SLEW_UM_PER_S * PERIOD_S
        for k in range(len(tr.t)):
            code = decode(tr.word[k])[0]
            v = code.direction * code.magnitude if code.enable else 0
            if not tr.enable[k]:
                budget = behind = 0.0
                continue
            gain = rate * tr.dt[k]
            budget += gain
            behind = max(0.0, behind + gain - 1.0)
            if k and tr.enable[k - 1]:
                prev = decode(tr.word[k - 1])[0]
                step = abs(v - (prev.direction * prev.magnitude if prev.enable else 0))
                if step:
                    max_step = max(max_step, step)
                    pace = max(pace, step / budget if budget > 0 else math.inf)
                    budget = max(0.0, budget - step)
            c = tr.out[k]
            goal = (
                0
                if abs(c) <= enc.deadband_um
                else max(-63, min(63, math.floor(abs(c) / lsb + 0.5))) * (1 if c > 0 else -1)
            )
            if v == goal:  # settled: the codec banks no more than this
                budget = min(budget, 1.0 + gain)
            over = max(over, abs(v * lsb - c) - (allowed_um + behind * lsb))
        return {
            "word_max_step_lsb": max_step,
            "word_pace_ratio": pace,
            # reported as the distance against the plain allowance (band + two cycles): a
            # row with stalls shows max(distance − stall allowance) on top of it
            "word_max_error_um": allowed_um + over if over > -math.inf else 0.0,
            "word_band_um": allowed_um,
        }

    def _safe(self, k: int) -> bool:
        tr = self.trace
        if self.policy == "hold":
            return True
        if self.policy == "ramp_to_zero":
            return tr.out[k] == 0.0
        return not tr.enable[k] and tr.out[k] == 0.0 and not decode(tr.word[k])[0].enable

    def _policy_held(self) -> bool:
        """In every FAULT cycle the axis did what its policy says."""
        tr = self.trace
        for k in range(1, len(tr.t)):
            if tr.state[k] != AxisState.FAULT or tr.state[k - 1] != AxisState.FAULT:
                continue
            if self.policy == "hold" and tr.out[k] != tr.out[k - 1]:
                return False
            if self.policy == "ramp_to_zero" and abs(tr.out[k]) > abs(tr.out[k - 1]):
                return False
            if self.policy == "disable" and (tr.enable[k] or tr.out[k] != 0.0):
                return False
        return True


def record(row: str, m: Measured, tmp_path: Path) -> Path:
    """Write one row's measurements (plus its matrix text) as JSON; returns the file."""
    spec = MATRIX[row]
    out_dir = Path(os.environ.get(RESULTS_ENV) or tmp_path)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = {
        "row": row,
        "order": list(MATRIX).index(row),
        "fault": spec.fault,
        "transport": spec.transport,
        "policy": spec.policy,
        "expected": spec.expected,
        **m.__dict__,
    }
    file = out_dir / f"{row}.json"
    file.write_text(json.dumps(data, indent=1, default=str))
    return file


def check(m: Measured, *, fault: bool = True, recovered: bool | None = None) -> None:
    """The assertions every row shares (never throw the axis)."""
    assert m.running, "compd stopped"
    assert m.word_valid, "an invalid word reached the card"
    assert m.max_step_ratio <= 1.0 + 1e-6, f"the correction moved faster than the slew: {m}"
    assert m.word_max_step_lsb <= 1, f"the word stepped by more than one LSB: {m}"
    assert m.word_pace_ratio <= 1.0 + 1e-6, f"the word stepped faster than the slew allows: {m}"
    assert m.word_max_error_um <= m.word_band_um + 1e-9, (
        f"the word stayed further than the dead-band from the correction: {m}"
    )
    if fault:
        assert m.policy_ok, f"the configured policy was not applied: {m}"
        assert m.time_to_safe_s is not None, f"the axis never reached its safe state: {m}"
        assert m.event is not None and m.logged, f"the event was not logged with sensor and reason: {m}"
    if recovered is not None:
        assert m.recovered == recovered, m
