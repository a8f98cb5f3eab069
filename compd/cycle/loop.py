"""The fixed-period cycle: absolute schedule, fixed stage order, timing statistics.

Stages run in the pipeline's order: read → model → guard → codec → sink. Each
cycle's deadline is start + k·period (never "sleep(period)"); the loop records its
lateness (wake-up time − deadline) in a fixed histogram, every stage's time and
worst time, and counts misses (a cycle that started more than half a period late
or ran past its deadline). A cycle that overran is counted; when the loop is more
than half a period behind, the deadlines already past are skipped (and counted)
instead of bursting to catch up.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from compd.codec import Encoder
from compd.core.clock import Clock
from compd.core.frame import Frame
from compd.cycle.adapt import Adapter
from compd.cycle.guard import Guard
from compd.cycle.inhibit import Inhibit
from compd.cycle.shadow import Shadow
from compd.io import activity
from compd.io.child import hosting
from compd.io.histogram import bin_percentiles
from compd.io.mailbox import shared_buffer
from compd.models.base import Model, ModelStage
from compd.sinks.base import Sink
from compd.sources.base import Source

log = logging.getLogger("compd.loop")

STAGES = ("read", "model", "guard", "codec", "sink")
HIST_US = 20000  # lateness histogram: 1 µs bins up to 20 ms, last bin = overflow


class TimingStats:
    """Lateness histogram, stage times and miss count; no allocation per cycle."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.stage_names = STAGES  # the stages' order in stage_*_ns (what the service names them by)
        # the histograms and stage times in memory shared with the service's process, which
        # reads them beside the cycle's status record (compd.cycle.statusblock)
        n = len(STAGES)
        self._buf = shared_buffer(8 * (2 * HIST_US + 3 * n))
        words = memoryview(self._buf).cast("q")
        self.hist = words[:HIST_US]
        self.cycles = 0
        self.misses = 0
        self.skipped = 0
        self.late_max_s = 0.0
        self.compute_hist = words[HIST_US : 2 * HIST_US]
        self.stage_last_ns = words[2 * HIST_US : 2 * HIST_US + n]
        self.stage_max_ns = words[2 * HIST_US + n : 2 * HIST_US + 2 * n]
        self.stage_sum_ns = words[2 * HIST_US + 2 * n :]
        self.compute_max_ns = 0
        self.gc_runs = 0
        self.gc_max_ns = 0
        self.between_max_s = 0.0  # the work between cycles (hooks, collection, the service's share)
        self.between_overruns = 0  # ... times it ended past the next deadline (that cycle then late)
        self.late_max_cycle = -1

    def record(self, lateness_s: float, compute_ns: int) -> None:
        self.cycles += 1
        us = int(lateness_s * 1e6)
        if us < 0:
            us = 0
        self.hist[us if us < HIST_US else HIST_US - 1] += 1
        if lateness_s > self.late_max_s:
            self.late_max_s = lateness_s
            self.late_max_cycle = self.cycles
        cu = compute_ns // 1000
        self.compute_hist[cu if cu < HIST_US else HIST_US - 1] += 1
        if compute_ns > self.compute_max_ns:
            self.compute_max_ns = compute_ns

    def stage(self, i: int, d_ns: int) -> None:
        self.stage_last_ns[i] = d_ns
        self.stage_sum_ns[i] += d_ns
        if d_ns > self.stage_max_ns[i]:
            self.stage_max_ns[i] = d_ns

    def lateness_us(self) -> dict[str, float]:
        p50, p99, p999 = bin_percentiles(self.hist, (0.5, 0.99, 0.999))
        return {"p50": p50, "p99": p99, "p999": p999, "max": round(self.late_max_s * 1e6, 1)}

    def compute_us(self) -> dict[str, float]:
        p50, p99 = bin_percentiles(self.compute_hist, (0.5, 0.99))
        return {"p50": p50, "p99": p99, "max": round(self.compute_max_ns / 1000, 1)}

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
            "gc_runs": self.gc_runs,
            "gc_max_us": self.gc_max_ns / 1000,
            "between_max_us": round(self.between_max_s * 1e6, 1),
            "between_overruns": self.between_overruns,
            "late_max_cycle": self.late_max_cycle,
            "lateness_us": self.lateness_us(),
            "cycle_compute_us": self.compute_us(),
            "stages": self.stages(),
        }


class Loop:
    """Runs the pipeline on a clock.

    Built from a config by `compd.daemon.app.App`; `compd.commissioning.replay` builds one directly.
    """

    def __init__(
        self,
        *,
        period_s: float,
        clock: Clock,
        frame: Frame,
        sources: list[Source],
        model: Model,
        guard: Guard,
        encoder: Encoder,
        sink: Sink,
        observers: list[Callable[[Loop, float], None]] | None = None,
        cycle_hooks: list[Callable[[Loop, float], None]] | None = None,
        adapter: Adapter | None = None,
        inhibit: Inhibit | None = None,
    ) -> None:
        self.period_s = period_s
        self.clock = clock
        self.frame = frame
        self.sources = sources
        self.model = model
        self.guard = guard
        self.encoder = encoder
        self.sink = sink
        # the word walks no faster than its axes' slew limits (the encoder knows its axes)
        encoder.set_slew([float(guard.slew_um_per_s[a]) for a in encoder.axes], period_s)
        self.observers = observers or []
        self.cycle_hooks = cycle_hooks or []
        n_out = len(model.outputs)
        self.x = np.zeros(len(model.inputs))
        self._good = np.zeros(len(model.inputs), dtype=bool)
        self.pred_um = np.full(n_out, math.nan)
        self.adapter = adapter  # probe-updated offset (and gain) per axis, or None
        self.inhibit = inhibit  # the machine's inhibit and referenced signals, or None
        self.pred_adapted_um = np.full(n_out, math.nan)  # what the guard gets: pred + the adapter's
        self.applied_um = np.zeros(n_out)
        self._word_applied = np.zeros(2)
        self.stats = TimingStats(period_s)
        self.stage = ModelStage(model)  # the model's start, update period and degraded mode
        self._stop = False
        self.t_start_s = 0.0
        self.now_s = 0.0
        self.word = 0
        self.on_model_state: Callable[[dict[str, Any]], None] | None = None
        self.gc_period_s = 1.0
        self.gil_switch_interval_s = 0.0001
        self.primed = False
        self.safe_delivered: bool | None = None  # whether the device acknowledged the safe output (close)
        # device I/O workers in processes of their own (on a clock a child can read), kept
        # off the CPUs the cycle is pinned to
        self.io_process = False
        self.cycle_cpus: frozenset[int] = frozenset()
        # what the daemon's service needs from the loop, handed over after each cycle (compd.cycle.publish)
        self.publisher: Any = None
        self.shadow: Shadow | None = None  # a candidate model beside the active one (compd.cycle.shadow)
        self._probe_seq = 0

    @property
    def word_axes(self) -> list[int]:
        """The word's axes, high byte first, as indices into the model's outputs (the encoder's)."""
        return self.encoder.axes

    def stop(self) -> None:
        """Ask the loop to finish after the current cycle (signal-safe)."""
        self._stop = True

    def io_hosting(self) -> contextlib.AbstractContextManager[None]:
        """Where the I/O workers of devices opened inside run (compd.io.child.hosting)."""
        return hosting(self.io_process and self.clock.fork_safe, self.cycle_cpus)

    def open(self, adopted: frozenset[int] | set[int] = frozenset()) -> None:
        """Open the sources and the sink (those whose id() is in `adopted` are open already)."""
        now = self.clock.now()
        opened: list[Any] = []
        with self.io_hosting():
            try:
                for s in self.sources:
                    if id(s) in adopted:
                        continue
                    opened.append(s)
                    s.open(now)
                    s.start_polling(self.clock)  # a PolledSource's own worker, on the loop clock
                if id(self.sink) not in adopted:
                    opened.append(self.sink)
                    self.sink.open(now)
            except BaseException:  # one device failed: close the ones opened (and it), leave no worker
                for stage in reversed(opened):
                    with contextlib.suppress(Exception):
                        stage.close()
                raise

    def close(self, keep: frozenset[int] | set[int] = frozenset()) -> None:
        """Safe output first, then release everything — except what a reloaded
        pipeline took over (ids in `keep`), which stays open and untouched."""
        keep_sink = id(self.sink) in keep
        try:
            if not keep_sink:
                self.guard.safe()
                self.safe_delivered = self.sink.safe()
                if not self.safe_delivered:
                    log.error(
                        "the safe output was not acknowledged by the sink's device: the last correction"
                        " may still be applied at the machine",
                        extra={"event": "safe_not_delivered"},
                    )
        finally:
            if not keep_sink:
                self.sink.close()
            for s in self.sources:
                if id(s) not in keep:
                    s.close()

    def resume(self) -> None:
        """Clear a stop request (after a config reload was rejected)."""
        self._stop = False

    def run(self, duration_s: float | None = None, max_cycles: int | None = None) -> TimingStats:
        """Run cycles until stopped, `duration_s` of loop time, or `max_cycles`."""
        clock = self.clock
        period = self.period_s
        stats = self.stats
        perf = time.perf_counter_ns
        if self.stats.cycles == 0 and not self.primed:
            # One priming cycle outside the schedule: first-use work (model start,
            # first device writes, lazy imports) happens here, not in cycle 1.
            self._cycle(clock.now(), perf)
            self.primed = True
        # Garbage collection: everything allocated at start-up is frozen out of the
        # collector's view; automatic collection is off, and a young-generation
        # collection runs only at a safe point (right after a cycle, when at least
        # half a period is left before the next deadline), about every gc_period_s.
        gc.collect()
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        # Polling threads run Python too: a thread holding the GIL keeps it for up to
        # the switch interval (5 ms by default) after the cycle thread wakes. On wall
        # time the interval is cut so the cycle waits at most that long.
        switch_was = sys.getswitchinterval()
        if not clock.simulated:
            sys.setswitchinterval(self.gil_switch_interval_s)
        # The schedule starts only now: a full collection above can take tens of ms,
        # and taken before it, t0 would make cycle 1 late by exactly that.
        t0 = clock.now()
        self.t_start_s = t0
        end = t0 + duration_s if duration_s is not None else math.inf
        k = 0
        half = period * 0.5
        jump_s = max(20.0 * period, 0.5)
        prev_now = t0
        # elapsed time beside the loop clock, to tell a stall (the clock moved as elapsed time
        # did) from a clock step (Clock.elapsed_s)
        elapsed = clock.elapsed_s
        e0 = prev_e = elapsed()
        stepped = 0.0  # loop-clock time the clock stepped by: kept out of its rate
        next_gc = t0 + self.gc_period_s
        simulated = clock.simulated
        margin = clock.spin_margin_s
        late_spans = activity.ring("cycle")  # None unless the bench records who runs when
        slow_spans = activity.ring(activity.SLOW)  # ... and the cycles whose work took that long
        late_ns = activity.late_threshold_ns()
        try:
            while not self._stop:
                deadline = t0 + k * period
                if deadline > end or (max_cycles is not None and stats.cycles >= max_cycles):
                    break
                clock.wait_until(deadline)
                now = clock.now()
                now_e = elapsed()
                lateness = now - deadline
                # a stall or a clock step: the output never steps for either. Late for this
                # deadline, far from the last cycle (a jump or a stall during the last cycle's
                # work is absorbed by the skip below, which then waits for a deadline in the new
                # time), or time went backwards. A stall moved the loop clock as far as elapsed
                # time (× the clock's rate so far); a step moved it by something else
                gap = now - prev_now
                if lateness > jump_s or gap > jump_s or gap < 0.0:
                    ran = prev_e - e0
                    rate = (prev_now - t0 - stepped) / ran if ran >= 0.1 else 1.0
                    if Guard.clock_stepped(gap, now_e - prev_e, rate, simulated, jump_s):
                        stepped += gap - max(rate, 0.0) * (now_e - prev_e)
                        self.guard.clock_jump(now, period)
                    else:
                        self.guard.stall(now, period, lateness, gap)
                prev_now = now
                prev_e = now_e
                c0 = perf()
                if late_spans is not None and lateness * 1e9 > late_ns:
                    late_spans.mark(c0 - int(lateness * 1e9), c0)
                self._cycle(now, perf)
                compute = perf() - c0
                stats.record(lateness, compute)
                if slow_spans is not None and compute > late_ns:
                    slow_spans.mark(c0, c0 + compute)
                done = clock.now()
                if lateness > half or done > deadline + period:
                    stats.misses += 1
                k += 1
                if done > t0 + k * period + half:  # far behind: skip to the next future deadline
                    behind = int((done - t0) / period) + 1
                    stats.skipped += behind - k
                    k = behind
                for hook in self.cycle_hooks:
                    hook(self, now)
                if done >= next_gc and t0 + k * period - clock.now() > half:
                    g0 = perf()
                    gc.collect(0)
                    g_ns = perf() - g0
                    if g_ns > stats.gc_max_ns:
                        stats.gc_max_ns = g_ns
                    stats.gc_runs += 1
                    next_gc = done + self.gc_period_s
                pub = self.publisher
                if pub is not None:  # the service's share, in the room left before the next deadline
                    pub.after_cycle(math.inf if simulated else t0 + k * period - clock.now() - margin)
                if not simulated:  # the work between cycles, from the end of this one
                    after = clock.now()
                    if after - done > stats.between_max_s:
                        stats.between_max_s = after - done
                    if done < t0 + k * period < after:
                        stats.between_overruns += 1
        finally:
            sys.setswitchinterval(switch_was)
            gc.unfreeze()
            if gc_was_enabled:
                gc.enable()
        return stats

    def step(self, now_s: float) -> None:
        """One cycle at loop time `now_s`, outside the schedule, for a caller that paces the
        cycle itself (replay drives the clock; `compd output-test` its ramp)."""
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
        if now >= self.stage.next_s:
            np.take(frame.values, self.guard.input_idx, out=self.x)
            self.model_step(ok, now)
        pred = self.pred_um
        if self.adapter is not None:  # the sink's applied correction only when a probe waits
            self.adapter.read_positions(frame.values)
            waiting = bool(self.adapter.inbox)  # what a probe needs (allocates) only when one waits
            self.adapter.apply(
                pred,
                now,
                self.pred_adapted_um,
                self.applied() if waiting else None,
                self.model.linear_terms() if waiting else None,
            )
            if self.shadow is not None and self.adapter.probe_seq != self._probe_seq:  # scored on the same probes
                self._probe_seq = self.adapter.probe_seq
                self.shadow.probed(self.adapter.probe_um, pred, now)
            pred = self.pred_adapted_um
        t2 = perf()
        self.sync_output(now)  # what the machine applies, when the sink has just read it back
        if self.inhibit is not None:
            self.inhibit.evaluate(frame, now, self.guard.hold)
        self.guard.update(pred, ok or self.degraded, now, degraded=self.degraded)
        if self.adapter is not None:
            self.adapter.record(self.pred_um, self.guard.out_um)
        t3 = perf()
        g = self.guard
        wa = self.word_axes
        if len(wa) == 2:
            changed = self.encoder.update(g.out_um[wa[0]], g.out_um[wa[1]], g.enable[wa[0]], g.enable[wa[1]], g.dt_s)
        else:
            changed = self.encoder.update(g.out_um[wa[0]], 0.0, g.enable[wa[0]], False, g.dt_s)
        self.word = self.encoder.word
        t4 = perf()
        self.sink.write(self.word, g.out_um, g.enable, changed, now)
        t5 = perf()
        t6 = t5
        if self.shadow is not None:  # after the output: a candidate never delays what drives the machine
            self.shadow.step(now)
            t6 = perf()
        st.stage(0, t1 - t)
        st.stage(1, t2 - t1 + t6 - t5)  # the model stage's time includes the shadow's
        st.stage(2, t3 - t2)
        st.stage(3, t4 - t3)
        st.stage(4, t5 - t4)
        for obs in self.observers:
            obs(self, now)

    def sync_output(self, now_s: float) -> bool:
        """When the sink has just learned what its device holds (`Sink.sync`: at its open, after
        its link was restored), the guard's output and the word start from it, so the output
        walks on from what the machine applies and never steps. Every cycle (a few hundred ns
        when nothing is new); a replay or `output-test` calls it before its first row."""
        if not self.sink.sync(now_s):
            return False
        held = self.sink.held_um()
        for a, name in enumerate(self.guard.axes):
            if name in held:
                self.guard.seed(a, held[name], now_s)
        for slot, name in enumerate(self.encoder.axis_names):
            if name in held:
                self.encoder.seed(slot, held[name])
        return True

    def model_step(self, ok: bool, now: float) -> None:
        """The cycle's model stage, when the model is due, on `x` (this cycle's inputs; `ok`:
        all good), by the stage's rule (compd.models.base.ModelStage); the prediction in
        `pred_um`, the model's memory handed on when it changed. (A replay calls it for the rows
        it steps the model on.)"""
        if not ok:
            np.equal(self.frame.quality[self.guard.input_idx], 0, out=self._good)
        if self.stage.step(self.x, self._good, ok, now, self.pred_um) and self.on_model_state is not None:
            self.on_model_state(self.model.get_state())

    @property
    def model_started(self) -> bool:
        """The model has started (its first good input vector came)."""
        return self.stage.started

    @property
    def degraded(self) -> bool:
        """The model's last step predicted from a reduced set of inputs."""
        return self.stage.degraded

    def applied(self) -> np.ndarray:
        """What the machine applies per model output (µm), from the sink."""
        self.sink.applied_um(self._word_applied)
        self.applied_um.fill(0.0)
        for slot, axis in enumerate(self.word_axes):
            self.applied_um[axis] = self._word_applied[slot]
        return self.applied_um
