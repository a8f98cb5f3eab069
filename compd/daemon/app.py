"""Builds a running pipeline from a validated config: wiring, log, console, summary."""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from compd.config import Config
from compd.core.clock import SimClock
from compd.core.errors import BadInput
from compd.core.scoring import RunningScore
from compd.cycle.loop import Loop
from compd.cycle.pipeline import from_config
from compd.daemon.host import LogSpec, Service, StateSpec
from compd.service.state import load_saved, params_digest
from compd.sinks.base import SAFE_TIMEOUT_S

log = logging.getLogger("compd")


CATCH_UP_PERIODS = 2.0  # the slew a late cycle may spend: two periods' worth (jitter), never the whole pause


class LogObserver:
    """Hands a log row to `push` every `period_s` of loop time and on every change of the
    word (the service's data log writes it: compd/daemon/host.py)."""

    def __init__(self, loop: Loop, push: Callable[[tuple[float, ...]], Any], period_s: float) -> None:
        self.columns = self.columns_of(loop)
        self.push = push
        self.period_s = period_s
        self._next_s = -math.inf
        self._last_word = -1
        self.adapter = loop.adapter
        self._probe_seq = loop.adapter.probe_seq if loop.adapter is not None else 0
        self._blank = (math.nan,) * (2 * len(loop.model.outputs))
        self._shadow = loop.shadow

    @staticmethod
    def columns_of(loop: Loop) -> list[str]:
        outs = loop.model.outputs
        return (
            ["t_s"]
            + list(loop.frame.names)
            + [f"pred_{a}_um" for a in outs]
            # each contribution's share of a sum of contributions (compd.cycle.contributions)
            + [f"pred_{a}_{name}_um" for name, a in loop.model.part_names]
            + [f"corr_{a}_um" for a in outs]
            + [f"applied_{a}_um" for a in outs]
            + ["word"]
            # the shadow model's prediction on the axes it serves (compd.cycle.shadow)
            + ([f"shadow_{a}_um" for a in loop.shadow.model.outputs] if loop.shadow is not None else [])
            # a probe's whole thermal error and where it was measured, blank between probes
            + ([f"probe_{a}_um" for a in outs] + [f"probe_pos_{a}_mm" for a in outs] if loop.adapter else [])
        )

    def __call__(self, loop: Loop, now: float) -> None:
        ad = self.adapter
        probed = ad is not None and ad.probe_seq != self._probe_seq  # a probe this cycle: a row now
        if now < self._next_s and loop.word == self._last_word and not probed:
            return
        if now >= self._next_s:
            self._next_s = now + self.period_s
        self._last_word = loop.word
        row = (
            (now,)
            + tuple(loop.frame.values.tolist())
            + tuple(loop.pred_um.tolist())
            + tuple(loop.model.part_um.tolist())
            + tuple(loop.guard.out_um.tolist())
            + tuple(loop.applied().tolist())
            + (float(loop.word),)
        )
        if self._shadow is not None:
            row += tuple(self._shadow.out.tolist())
        if ad is not None:
            if probed:
                self._probe_seq = ad.probe_seq
                row += tuple(ad.probe_um.tolist()) + tuple(ad.probe_pos_mm.tolist())
            else:
                row += self._blank
        self.push(row)


class CompensationSummary:
    """The run's before/after score (compd.core.scoring), fed every cycle.

    Only where the sources publish the true error `err_<axis>_um` (simulator,
    replay of a measured log); residual = error + applied correction.
    """

    def __init__(self, loop: Loop) -> None:
        self.pairs: list[tuple[int, int]] = []
        for a, axis in enumerate(loop.model.outputs):
            name = f"err_{axis}_um"
            if name in loop.frame.index:
                self.pairs.append((a, loop.frame.index[name]))
        self.score = RunningScore(len(loop.model.outputs))

    def __call__(self, loop: Loop, now: float) -> None:
        if not self.pairs:
            return
        applied = loop.applied()
        if not np.all(np.isfinite(applied)):
            return  # the sink does not know yet what the machine applies (remote status not read)
        values = loop.frame.values
        for a, i in self.pairs:  # a true error not sampled yet (or lost) is skipped
            self.score.add(a, float(values[i]), float(applied[a]))

    def result(self, axes: list[str]) -> dict[str, dict[str, float]]:
        return {axes[a]: self.score.result(a) for a, _ in self.pairs}


class Console:
    """A compact live table: time, inputs, prediction, word, error without/with compensation."""

    def __init__(self, loop: Loop, period_s: float, out: TextIO = sys.stdout) -> None:
        self.period_s = period_s
        self.out = out
        self._next_s = -math.inf
        self.inputs = loop.model.inputs[:3]
        self.axes = loop.model.outputs
        self.err_idx = [loop.frame.index.get(f"err_{a}_um") for a in self.axes]
        # a name that carries its unit (speed_rpm, pos_y_mm, current_x_a) stands as it is
        cols = ["time"] + [n if n.endswith(("_rpm", "_mm", "_a", "_um")) else f"{n}/°C" for n in self.inputs]
        for a in self.axes:
            cols += [f"pred_{a}/µm"]
        cols += ["word"]
        for a, i in zip(self.axes, self.err_idx, strict=True):
            if i is not None:
                cols += [f"err_{a}/µm", f"comp_{a}/µm"]
        self.header = " ".join(f"{c:>11}" for c in cols)

    def __call__(self, loop: Loop, now: float) -> None:
        if now < self._next_s:
            return
        if self._next_s == -math.inf:
            print(self.header, file=self.out)
        self._next_s = now + self.period_s
        el = now - loop.t_start_s
        cells = [f"{int(el // 3600):d}:{int(el % 3600 // 60):02d}:{int(el % 60):02d}"]
        for n in self.inputs:
            cells.append(f"{loop.frame.values[loop.frame.index[n]]:.2f}")
        cells += [f"{p:.2f}" for p in loop.pred_um]
        cells.append(f"0x{loop.word:04X}")
        applied = loop.applied()
        for a, i in enumerate(self.err_idx):
            if i is not None:
                e = loop.frame.values[i]
                cells += [f"{e:.2f}", f"{e + applied[a]:.2f}"]
        print(" ".join(f"{c:>11}" for c in cells), file=self.out, flush=True)


class App:
    """A loop and what hangs on it, from a config."""

    def __init__(
        self,
        cfg: Config,
        *,
        duration_s: float | None = None,
        out: TextIO = sys.stdout,
        observe: bool | None = None,
    ):
        self.cfg = cfg
        self.out = out
        top = cfg.top
        lp = top.loop
        self.observe = top.observe if observe is None else observe
        p, self.clock = from_config(cfg, observe=self.observe)
        self.sources, self.frame, self.model, self.guard = p.sources, p.frame, p.model, p.guard
        self.encoder, self.sink, self.loop = p.encoder, p.sink, p.loop
        # a late cycle licenses at most CATCH_UP_PERIODS of slew: after a pause of the process shorter
        # than the loop's stall threshold (0.5 s) the output goes on at the slew, never steps the gap's
        # worth at once (a longer one is a stall: one period, compd.cycle.guard.Guard.stall)
        self.guard.max_dt_s = CATCH_UP_PERIODS * lp.period_s
        self.loop.gil_switch_interval_s = lp.gil_switch_interval_s
        self.loop.io_process = lp.io == "process"
        self.loop.cycle_cpus = frozenset(lp.realtime.cpu_affinity or ())
        self.summary = CompensationSummary(self.loop)
        self.loop.observers.append(self.summary)
        self.logger: LogObserver | None = None
        self._adopted: set[int] = set()  # sources and sink taken over from the App before a reload
        self._released: set[int] = set()  # the previous App's sink, released for ours (same device)
        self._previous: App | None = None
        self._clock_adopted = False
        self._state_adopted = False
        self._model_carried = False  # a reload carried the running model's memory over
        self._adapt_carried = False  # ... and the adapter's estimate (same model, same params)
        if top.console.period_s > 0:
            self.loop.observers.append(Console(self.loop, top.console.period_s, out))
        self.duration_s = duration_s if duration_s is not None else lp.duration_s
        if self.duration_s is None and lp.clock == "sim":
            ends = [e for e in (s.end_s for s in self.sources) if e]
            if ends:
                self.duration_s = min(ends) - self.clock.now()
        self.service = Service(self, self.observe)  # notify, status, metrics, event log

    def restore_state(self) -> None:
        """Load persisted model state and the adapter's estimate (if any); the service writes
        the state file from then on (what the cycle hands it: `Publisher.model_state`).

        The adapter's estimate is restored only for the same model: kind, inputs, outputs
        (the file's own check) and params (a hash kept with it); a refit model starts
        from zero offset."""
        path = self.cfg.top.state.path
        if not path:
            return
        spath = self.cfg.resolve_path(path)
        m = self.model
        ad = self.loop.adapter
        digest = params_digest(self.cfg.model.params)
        pub = self.service.publisher
        self.service.state_spec = StateSpec(spath, m.kind, list(m.inputs), list(m.outputs), digest)
        if not self._state_adopted:  # (a reload of the same model and file carried its state over)
            saved = None if self._model_carried else load_saved(spath, m.kind, m.inputs, m.outputs)
            if saved is not None:
                m.set_state(saved.state, saved.elapsed_s)
                log.info(
                    "model state restored from %s (saved %.0f s ago)",
                    spath,
                    saved.elapsed_s,
                    extra={"event": "state_restored", "path": str(spath), "elapsed_s": round(saved.elapsed_s)},
                )
            if ad is not None and saved is not None and saved.adapt is not None and not self._adapt_carried:
                self._restore_adapt(saved.adapt, digest, spath)
        self.loop.on_model_state = pub.model_state
        if ad is not None:
            ad.on_state = pub.adapt_state
            pub.adapt_state(ad.get_state())

    def _restore_adapt(self, part: dict[str, Any], digest: str, spath: Path) -> None:
        import time

        ad = self.loop.adapter
        assert ad is not None
        if part.get("params_sha256") != digest:
            log.warning(
                "adaptation reset: the model's params changed since %s was saved",
                spath,
                extra={"event": "adapt_reset", "path": str(spath), "reason": "model params changed"},
            )
            return
        try:
            elapsed = max(time.time() - float(part["saved_unix_s"]), 0.0)
            if not math.isfinite(elapsed):
                raise ValueError(f"saved_unix_s is {part['saved_unix_s']!r}")
            ad.set_state(dict(part["axes"]), elapsed, self.clock.now())  # ValueError: a number not finite, P not PSD
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            ad.reset()
            log.warning(
                "adaptation state ignored: %s: %s",
                spath,
                e,
                extra={"event": "state_ignored", "path": str(spath), "reason": f"adapt: {e}"},
            )
            return
        log.info(
            "adaptation restored from %s (saved %.0f s ago)",
            spath,
            elapsed,
            extra={"event": "adapt_restored", "path": str(spath), "elapsed_s": round(elapsed)},
        )

    def adopt(self, previous: App) -> None:
        """Config reload: take over what did not change from the running App (no I/O).

        Sources and the sink whose config is unchanged are taken over still open;
        so are the plant clock, the metrics endpoint, the state file's writer and the
        data log when their settings are unchanged. The model's memory is carried over
        when the model is the same; and the guard starts from the correction the
        machine has now, so a reload never steps the output. `open` then opens the
        rest; if it fails, `previous` is left as it was and can go on running.
        """
        self._previous = previous
        if self.clock.simulated and previous.clock.simulated:  # time goes on where it was
            self.clock = self.loop.clock = SimClock(previous.clock.now(), self.cfg.loop.speedup)
        elif (
            previous.clock.kept_across_reload
            and type(self.clock) is type(previous.clock)
            and (self.cfg.loop.plant_clock == previous.cfg.loop.plant_clock)
        ):
            self.clock = self.loop.clock = previous.clock
            self._clock_adopted = True
        for i, (old, new) in enumerate(zip(previous.sources, self.sources, strict=False)):
            if old.cfg == new.cfg and old.signal_names() == new.signal_names():
                self.sources[i] = old
                self._adopted.add(id(old))
        self.loop.sources = self.sources
        pm, m = previous.model, self.model
        same_model = (pm.kind, pm.inputs, pm.outputs) == (m.kind, m.inputs, m.outputs)
        if same_model and previous.loop.model_started:
            m.set_state(pm.get_state(), 0.0)
            self._model_carried = True
        pa, ad = previous.loop.adapter, self.loop.adapter
        if (
            same_model
            and pa is not None
            and ad is not None
            and (params_digest(previous.cfg.model.params) == params_digest(self.cfg.model.params))
        ):
            try:
                ad.set_state(pa.get_state())
                self._adapt_carried = True
            except ValueError as e:  # another adapt.gain or slope_position: the estimate starts again
                ad.reset()
                log.warning(
                    "adaptation reset: the running estimate does not fit the new adapt section: %s",
                    e,
                    extra={"event": "adapt_reset", "reason": str(e)},
                )
        prev_state = previous.service.state_spec
        if (
            same_model
            and prev_state is not None
            and self.cfg.top.state.path
            and (self.cfg.resolve_path(self.cfg.top.state.path) == prev_state.path)
        ):
            self._state_adopted = True
        if previous.sink.cfg == self.sink.cfg and previous.observe == self.observe:
            self.sink = self.loop.sink = previous.sink
            self._adopted.add(id(self.sink))
            self.encoder.adopt(previous.encoder)  # the word goes on from what the machine has
            for a, axis in enumerate(m.outputs):
                if axis in pm.outputs:
                    b = pm.outputs.index(axis)
                    self.guard.out_um[a] = previous.guard.out_um[b]
                    self.guard.enable[a] = previous.guard.enable[b]
                    self.guard.state[a] = previous.guard.state[b]
        self.service.adopt(previous.service)

    def _take_over(self) -> None:
        """Point what was taken over at this pipeline (the previous one is stopped)."""
        for s in self.sources:
            if id(s) in self._adopted:
                s.bind(self.frame)
                if self.loop.adapter is not None:  # a probe source hands its probes to this adapter
                    s.bind_probes(self.loop.adapter.inbox)
        if id(self.sink) in self._adopted:
            self.sink.bind_model(self.model)

    def _give_back(self) -> None:
        """A reload failed: point what was taken over at the previous pipeline again and
        reopen the sink released for ours, so the previous App can resume as it was."""
        prev = self._previous
        assert prev is not None
        for s in prev.sources:
            s.bind(prev.frame)
            if prev.loop.adapter is not None:
                s.bind_probes(prev.loop.adapter.inbox)
        prev.sink.bind_model(prev.model)
        if id(prev.sink) in self._released:
            with prev.loop.io_hosting():
                prev.sink.open(prev.clock.now())
            self._released.clear()

    def _open_log(self) -> None:
        """The data log: rows from the cycle (`LogObserver`) to the service, which writes them."""
        top = self.cfg.top
        if not top.log.path:
            return
        path = self.cfg.resolve_path(top.log.path)
        self.logger = LogObserver(self.loop, self.service.publisher.row, top.log.period_s)
        self.service.log_spec = LogSpec(
            path, self.logger.columns, top.log.flush_s, top.log.rotate_bytes, top.log.rotate_s, top.log.keep
        )
        self.loop.observers.append(self.logger)

    def _release_clashing_sink(self) -> None:
        """The new sink talks to the device the previous one holds: release the old one
        first (what it wrote acknowledged, then closed) rather than open a second connection
        beside it. No safe output: the new sink reads back what the device applies and goes on
        from there (compd.sinks.base), so a reload neither steps the axis nor walks it to 0."""
        prev = self._previous
        if prev is None or id(self.sink) in self._adopted:
            return
        key = self.sink.device_key()
        if key is not None and key == prev.sink.device_key():
            try:
                prev.sink.flush(SAFE_TIMEOUT_S)
            finally:
                prev.sink.close()
                self._released.add(id(prev.sink))

    def open(self) -> None:
        """Start I/O: plant clock, metrics, state, log, the sources and sink not adopted,
        then the service and real-time options.

        On a reload (after `adopt`), every step that can fail runs before the previous
        App is touched; if one fails, what this App opened is closed again, what it took
        over is given back, and the exception propagates: the previous App resumes."""
        undo: list[Any] = []
        try:
            self.service.check_status_free()
            if not self._clock_adopted:  # connect before anything is stamped
                self.clock.start()
                undo.append(self.clock.stop)
            self.service.open_metrics()
            undo.append(self.service.close_metrics)
            self.service.open_control()
            undo.append(self.service.close_control)
            self.restore_state()
            self._open_log()
            self._release_clashing_sink()
            undo.append(lambda: self.loop.close(self._adopted))
            self.loop.open(self._adopted)
            self.clock.bind(self.sink, self.sources)  # a lockstep clock flushes the one, polls the others
            self._take_over()
            self.service.start()
        except BaseException as e:
            for step in reversed(undo):
                try:
                    step()
                except Exception:
                    log.exception("while undoing a failed open", extra={"event": "undo_error"})
            if self._previous is not None:
                self._give_back()
            if isinstance(e, BadInput) and not e.file:  # a device that cannot be opened: name its key
                raise self.cfg.doc.error(e.message, e.keys) from None
            raise
        self._previous = None

    def close(self, *, handing_over_to: App | None = None) -> None:
        """Stop I/O. Normally: safe output first, then release everything. When handing
        over to a reloaded App, what it took over stays open and untouched."""
        new = handing_over_to
        keep = (new._adopted | new._released) if new is not None else set()
        if new is None:
            self.service.stopping()
        try:
            self.loop.close(keep)
        finally:
            if self.service.state_spec is not None:  # the last state, written before the service stops
                pub = self.service.publisher
                if self.loop.adapter is not None:
                    pub.adapt_state(self.loop.adapter.get_state())
                if self.loop.model_started:
                    pub.model_state(self.model.get_state())
            self.service.stop(handing_over_to=new.service if new is not None else None)
            if not (new is not None and new.clock is self.clock):
                self.clock.stop()

    def summary_dict(self) -> dict[str, Any]:
        counts = self.service.counts()
        log_status = counts.get("log") if self.logger else None
        return {
            "loop": self.loop.stats.as_dict(),
            "compensation": self.summary.result(self.model.outputs),
            "faults": dict(self.guard.faults),
            "log_error": (log_status or {}).get("error") if self.logger else None,
            "log": log_status,  # rows written and dropped, rotations
            "sink": self.sink.get_status(),
            "realtime": self.service.realtime_result,
            "state_error": counts.get("state_error"),
            "observe": self.observe,
            # the sink's device acknowledged the safe output at the stop (None: not stopped, or handed over)
            "safe_delivered": self.loop.safe_delivered,
            # the probe adapter's estimate per axis (accepted and rejected probes), when configured
            "adaptation": self.loop.adapter.get_status() if self.loop.adapter is not None else None,
        }

    def run(self) -> dict[str, Any]:
        """Open, run until done or stopped, close with the safe output; returns a summary."""
        self.open()
        try:
            self.loop.run(self.duration_s)
        finally:
            self.close()
        return self.summary_dict()
