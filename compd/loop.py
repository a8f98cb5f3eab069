"""The fixed-period cycle: absolute schedule, fixed stage order, timing statistics.

Stages run in the order of SPEC §1: read → model → guard → codec → sink. Each
cycle's deadline is start + k·period (never "sleep(period)"); the loop records its
lateness (wake-up time − deadline) in a fixed histogram, every stage's time and
worst time, and counts misses (a cycle that started more than half a period late
or ran past its deadline). A cycle that overran is counted, then the schedule
skips the deadlines already past instead of bursting to catch up.
"""

from __future__ import annotations

import math
import time
from array import array
from collections.abc import Callable
from typing import Any

import numpy as np

from compd.codec import Encoder
from compd.frame import Frame
from compd.guard import Guard
from compd.models.base import Model
from compd.sinks.base import Sink
from compd.sources.base import Source

STAGES = ("read", "model", "guard", "codec", "sink")
HIST_US = 20000  # lateness histogram: 1 µs bins up to 20 ms, last bin = overflow


class TimingStats:
    """Lateness histogram, stage times and miss count; no allocation per cycle."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.hist = array("q", bytes(8 * HIST_US))
        self.cycles = 0
        self.misses = 0
        self.skipped = 0
        self.late_max_s = 0.0
        self.stage_last_ns = array("q", [0] * len(STAGES))
        self.stage_max_ns = array("q", [0] * len(STAGES))
        self.stage_sum_ns = array("q", [0] * len(STAGES))
        self.compute_hist = array("q", bytes(8 * HIST_US))
        self.compute_max_ns = 0

    def record(self, lateness_s: float, compute_ns: int) -> None:
        self.cycles += 1
        us = int(lateness_s * 1e6)
        if us < 0:
            us = 0
        self.hist[us if us < HIST_US else HIST_US - 1] += 1
        if lateness_s > self.late_max_s:
            self.late_max_s = lateness_s
        cu = compute_ns // 1000
        self.compute_hist[cu if cu < HIST_US else HIST_US - 1] += 1
        if compute_ns > self.compute_max_ns:
            self.compute_max_ns = compute_ns

    @staticmethod
    def _percentile(hist: array, q: float) -> float:
        total = sum(hist)
        if total == 0:
            return 0.0
        want = q * total
        acc = 0
        for i, c in enumerate(hist):
            acc += c
            if acc >= want:
                return float(i)
        return float(len(hist) - 1)

    def lateness_us(self) -> dict[str, float]:
        p = self._percentile
        return {
            "p50": p(self.hist, 0.5),
            "p99": p(self.hist, 0.99),
            "p999": p(self.hist, 0.999),
            "max": round(self.late_max_s * 1e6, 1),
        }

    def compute_us(self) -> dict[str, float]:
        p = self._percentile
        return {
            "p50": p(self.compute_hist, 0.5),
            "p99": p(self.compute_hist, 0.99),
            "max": round(self.compute_max_ns / 1000, 1),
        }

    def stages(self) -> dict[str, dict[str, float]]:
        n = max(self.cycles, 1)
        return {
            name: {
                "last_us": self.stage_last_ns[i] / 1000,
                "mean_us": self.stage_sum_ns[i] / n / 1000,
                "max_us": self.stage_max_ns[i] / 1000,
            }
            for i, name in enumerate(STAGES)
        }

    def as_dict(self) -> dict[str, Any]:
        return {
            "period_ms": self.period_s * 1000,
            "cycles": self.cycles,
            "misses": self.misses,
            "skipped": self.skipped,
            "lateness_us": self.lateness_us(),
            "cycle_compute_us": self.compute_us(),
            "stages": self.stages(),
        }


class Loop:
    """Runs the pipeline on a clock. Build it with `compd.app.build`."""

    def __init__(
        self,
        *,
        period_s: float,
        clock: Any,
        frame: Frame,
        sources: list[Source],
        model: Model,
        guard: Guard,
        encoder: Encoder,
        sink: Sink,
        word_axes: list[int],
        observers: list[Callable[[Loop, float], None]] | None = None,
        cycle_hooks: list[Callable[[Loop, float], None]] | None = None,
    ) -> None:
        self.period_s = period_s
        self.clock = clock
        self.frame = frame
        self.sources = sources
        self.model = model
        self.guard = guard
        self.encoder = encoder
        self.sink = sink
        self.word_axes = word_axes  # indices into model outputs for the high and low byte
        self.observers = observers or []
        self.cycle_hooks = cycle_hooks or []
        n_out = len(model.outputs)
        self.x = np.zeros(len(model.inputs))
        self.pred_um = np.full(n_out, math.nan)
        self.applied_um = np.zeros(n_out)
        self._word_applied = np.zeros(2)
        self.stats = TimingStats(period_s)
        self.model_started = False
        self._next_model_s = -math.inf
        self._stop = False
        self.t_start_s = 0.0
        self.now_s = 0.0
        self.word = 0

    def stop(self) -> None:
        """Ask the loop to finish after the current cycle (signal-safe)."""
        self._stop = True

    def open(self) -> None:
        now = self.clock.now()
        for s in self.sources:
            s.open(now)
            start_polling = getattr(s, "start_polling", None)
            if start_polling is not None:  # PolledSource: its own thread, on the loop clock
                start_polling(self.clock)
        self.sink.open(now)

    def close(self) -> None:
        """Safe output first, then release everything."""
        try:
            self.guard.safe()
            self.sink.safe()
        finally:
            self.sink.close()
            for s in self.sources:
                s.close()

    def run(self, duration_s: float | None = None, max_cycles: int | None = None) -> TimingStats:
        """Run cycles until stopped, `duration_s` of loop time, or `max_cycles`."""
        clock = self.clock
        period = self.period_s
        stats = self.stats
        perf = time.perf_counter_ns
        t0 = clock.now()
        self.t_start_s = t0
        end = t0 + duration_s if duration_s is not None else math.inf
        k = 0
        half = period * 0.5
        while not self._stop:
            deadline = t0 + k * period
            if deadline > end or (max_cycles is not None and stats.cycles >= max_cycles):
                break
            clock.wait_until(deadline)
            now = clock.now()
            lateness = now - deadline
            c0 = perf()
            self._cycle(now, perf)
            compute = perf() - c0
            stats.record(lateness, compute)
            done = clock.now()
            if lateness > half or done > deadline + period:
                stats.misses += 1
            k += 1
            nxt = t0 + k * period
            if done > nxt + period:  # overran by more than a cycle: skip what is past
                skip = int((done - nxt) / period)
                stats.skipped += skip
                k += skip
            for hook in self.cycle_hooks:
                hook(self, now)
        return stats

    def step(self, now_s: float) -> None:
        """One cycle at loop time `now_s`, outside the schedule (replay drives the clock)."""
        c0 = time.perf_counter_ns()
        self._cycle(now_s, time.perf_counter_ns)
        self.stats.record(0.0, time.perf_counter_ns() - c0)

    def _cycle(self, now: float, perf: Callable[[], int]) -> None:
        st = self.stats
        self.now_s = now
        frame = self.frame
        t = perf()
        for s in self.sources:
            s.read(frame, now)
        t1 = perf()
        ok = self.guard.check_inputs(frame, now)
        if now >= self._next_model_s:
            np.take(frame.values, self.guard.input_idx, out=self.x)
            if ok:
                if not self.model_started:
                    self.model.start(self.x, now)
                    self.model_started = True
                self.model.evaluate(self.x, now, self.pred_um)
                ups = self.model.update_period_s
                self._next_model_s = now + ups if ups > 0 else -math.inf
            else:
                self.pred_um.fill(math.nan)
        t2 = perf()
        self.guard.update(self.pred_um, ok, now)
        t3 = perf()
        g = self.guard
        wa = self.word_axes
        if len(wa) == 2:
            changed = self.encoder.update(g.out_um[wa[0]], g.out_um[wa[1]], g.enable[wa[0]], g.enable[wa[1]])
        else:
            changed = self.encoder.update(g.out_um[wa[0]], 0.0, g.enable[wa[0]], False)
        self.word = self.encoder.word
        t4 = perf()
        self.sink.write(self.word, g.out_um, g.enable, changed, now)
        t5 = perf()
        for i, (a, b) in enumerate(((t, t1), (t1, t2), (t2, t3), (t3, t4), (t4, t5))):
            d = b - a
            st.stage_last_ns[i] = d
            st.stage_sum_ns[i] += d
            if d > st.stage_max_ns[i]:
                st.stage_max_ns[i] = d
        for obs in self.observers:
            obs(self, now)

    def applied(self) -> np.ndarray:
        """What the machine applies per model output (µm), from the sink."""
        self.sink.applied_um(self._word_applied)
        self.applied_um.fill(0.0)
        for slot, axis in enumerate(self.word_axes):
            self.applied_um[axis] = self._word_applied[slot]
        return self.applied_um

    def get_status(self) -> dict[str, Any]:
        now = self.now_s
        return {
            "uptime_s": now - self.t_start_s,
            "word": f"0x{self.word:04X}",
            "axes": self.guard.get_status(),
            "prediction_um": dict(zip(self.model.outputs, map(float, self.pred_um), strict=True)),
            "signals": self.frame.snapshot(now),
            "loop": self.stats.as_dict(),
            "model": self.model.get_status(),
            "sink": self.sink.get_status(),
            "sources": [s.get_status() for s in self.sources],
            "faults": dict(self.guard.faults),
        }
