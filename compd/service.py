"""What runs beside the loop when compd is a daemon: systemd notify, status file, metrics, event log.

`Service` is built with the App (opens nothing) and started by `App.run` after
the devices are open. The cycle carries only `WatchdogObserver` (READY after the
first cycle, a watchdog ping at half of $WATCHDOG_USEC). Everything else happens
on one background thread about once a second: snapshot the loop, write the
status file, feed the metrics, log new guard events and late cycles, send
STATUS= to systemd. At the end it writes a last snapshot (state `stopped`).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

from compd import (
    activity,
    logsetup,  # noqa: F401  (installs the library's NullHandler)
)
from compd import status as status_mod
from compd.control import ControlServer, socket_path
from compd.errors import BadInput
from compd.metrics import MetricsServer
from compd.notify import Notifier, WatchdogObserver, watchdog_interval_s
from compd.realtime import apply_realtime

log = logging.getLogger("compd.service")

_EVENT_LEVEL = {"bad": logging.WARNING, "fault": logging.WARNING, "jump": logging.WARNING}
_EVENT_NAME = {
    "bad": "sensor_bad",
    "good": "sensor_good",
    "fault": "axis_fault",
    "recovering": "axis_recovering",
    "normal": "axis_normal",
    "jump": "clock_jump",
    "held": "axis_held",  # the machine inhibits the axis, or it waits for its reference
    "released": "axis_released",
}


def status_path(cfg: Any, env: dict[str, str] | None = None) -> Path | None:
    """The status file: `status.path` (relative to the config), else $RUNTIME_DIRECTORY/status.json."""
    env = dict(os.environ) if env is None else env
    if cfg.top.status.path:
        return cfg.resolve_path(cfg.top.status.path)
    runtime = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    return Path(runtime) / "status.json" if runtime else None


def daemon_status_path(cfg: Any) -> Path:
    """Where the daemon of `cfg` writes its status, as another process finds it: `status.path`,
    else where the systemd units put it (RuntimeDirectory `compd` for compd.yaml, `compd/NAME`
    for the instance compd@NAME)."""
    found = status_path(cfg, env={})
    if found is not None:
        return found
    stem = Path(cfg.file).stem
    return Path(status_mod.DEFAULT_PATH if stem == "compd" else f"/run/compd/{stem}/status.json")


class _TailLogger(ABC):
    """Logs what a bounded event deque gained since the last flush (the cycle appends to it;
    flush runs off the cycle, on a copy, and finds where it left off by identity)."""

    def __init__(self) -> None:
        self._last: Any = None
        self.logged = 0

    @abstractmethod
    def _events(self) -> list[Any]:
        """A copy of the event deque, oldest first."""

    @abstractmethod
    def _log(self, ev: Any) -> None:
        """One event as a log line."""

    def flush(self) -> int:
        events = self._events()
        start = 0
        if self._last is not None:
            for i in range(len(events) - 1, -1, -1):
                if events[i] is self._last:
                    start = i + 1
                    break
        for ev in events[start:]:
            self._log(ev)
        if events:
            self._last = events[-1]
        n = len(events) - start
        self.logged += n
        return n


class EventLogger(_TailLogger):
    """Turns the guard's new events (since the last call) into log lines. A sensor that went
    bad because its device is not answering (comms_lost, no_data, stale) gets its source's last error
    as the cause: "T_xi bad: comms_lost (source adam: connect: could not open port …)"."""

    def __init__(self, guard: Any, sources: Any = ()) -> None:
        super().__init__()
        self.guard = guard
        self.sources = list(sources)

    def _cause(self, signal: str) -> str | None:
        """`source NAME: its last error` of the source that publishes `signal`, if it has one."""
        for src in self.sources:
            try:
                if signal in src.signal_names():
                    err = src.get_status().get("last_error")
                    return f"source {src.name}: {err}" if err else None
            except Exception:  # a source's status must not stop the event log
                return None
        return None

    def _events(self) -> list[Any]:
        return list(self.guard.events)

    def _log(self, ev: Any) -> None:
        t, subject, event, reason = ev
        kind = "sensor" if event in ("bad", "good") else ("clock" if event == "jump" else "axis")
        extra = {"event": _EVENT_NAME.get(event, event), kind: subject, "reason": reason, "t_s": t}
        cause = self._cause(subject) if event == "bad" and reason in ("comms_lost", "no_data", "stale") else None
        if cause is not None:
            extra["cause"] = cause
        log.log(
            _EVENT_LEVEL.get(event, logging.INFO),
            "%s %s: %s%s",
            subject,
            event,
            reason,
            "" if cause is None else f" ({cause})",
            extra=extra,
        )


class ProbeEventLogger(_TailLogger):
    """Turns the adapter's new events (probes accepted, rejected, ignored; faults) into log lines."""

    def __init__(self, adapter: Any) -> None:
        super().__init__()
        self.adapter = adapter

    def _events(self) -> list[Any]:
        return [] if self.adapter is None else list(self.adapter.events)  # a copy: the cycle appends

    def _log(self, ev: dict[str, Any]) -> None:
        kind, axis = ev.get("event"), ev.get("axis")
        extra = {"event": f"probe_{kind}", "axis": axis, "t_s": ev.get("t_s"), "source": ev.get("source")}
        if kind in ("accepted", "rejected"):
            extra.update({k: ev.get(k) for k in ("error_um", "measured_um", "innovation_um",
                                                   "innovation_sigma_um", "offset_um")})
            log.log(
                logging.INFO if kind == "accepted" else logging.WARNING,
                "probe %s %s: error %.2f um, innovation %.2f um (sigma %.2f um), offset now %.2f um",
                axis, kind, ev["error_um"], ev["innovation_um"], ev["innovation_sigma_um"], ev["offset_um"],
                extra=extra,
            )
        elif kind == "fault":
            extra["event"] = "adapt_fault"
            extra["reason"] = ev.get("why")
            log.warning("probe %s fault: %s", axis, ev.get("why"), extra=extra)
        else:  # unknown_axis, no_prediction, no_correction_known: the probe was not used
            extra["event"] = "probe_ignored"
            extra["reason"] = kind
            log.warning("probe %s ignored: %s", axis, kind, extra=extra)


class Service:
    """Notify, status, metrics and event logging for one App."""

    def __init__(self, app: Any, observe: bool = False) -> None:
        self.app = app
        self.loop = app.loop
        top = app.cfg.top
        self.observe = observe
        self.period_s = top.status.period_s
        self.path = status_path(app.cfg)
        self.metrics = MetricsServer(top.metrics.bind, top.metrics.port) if top.metrics.enabled else None
        self.metrics_url: str | None = None
        self._metrics_cfg = (top.metrics.bind, top.metrics.port) if top.metrics.enabled else None
        self._metrics_adopted = False
        self.realtime = top.loop.realtime
        self.events = EventLogger(self.loop.guard, self.loop.sources)
        self.probe_events = ProbeEventLogger(self.loop.adapter)
        spath = socket_path(app.cfg) if self.loop.adapter is not None else None
        self.control = ControlServer(spath, self.loop) if spath is not None else None
        self._control_adopted = False
        self.notifier: Notifier | None = None
        self.watchdog: WatchdogObserver | None = None
        self.state = "starting"
        self.status_errors = 0
        self._misses = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self.realtime_result: list[tuple[bool, str]] = []

    # ------------------------------------------------------------------ life
    def adopt(self, previous: Service) -> None:
        """Config reload: keep the running metrics endpoint when its bind and port are unchanged."""
        if self._metrics_cfg is not None and self._metrics_cfg == previous._metrics_cfg and previous.metrics_url:
            self.metrics = previous.metrics
            self.metrics_url = previous.metrics_url
            self._metrics_adopted = True
        pc = previous.control
        if self.control is not None and pc is not None and pc.path == self.control.path and pc._sock is not None:
            self.control = pc  # the same socket goes on; `start` points it at this loop
            self._control_adopted = True

    def open_control(self) -> None:
        """Bind the probe socket (BadInput if it cannot); a kept one is already bound."""
        if self.control is not None and not self._control_adopted:
            self.control.open()

    def close_control(self) -> None:
        """Undo `open_control` (a reload that failed later): a kept socket stays."""
        if self.control is not None and not self._control_adopted:
            self.control.close()

    def open_metrics(self) -> None:
        """Bind the metrics endpoint (BadInput if it cannot); a kept one is already bound."""
        if self.metrics is None or self._metrics_adopted:
            return
        self.metrics_url = self.metrics.start()
        log.info("metrics on %s", self.metrics_url, extra={"event": "metrics", "url": self.metrics_url})

    def close_metrics(self) -> None:
        """Undo `open_metrics` (a reload that failed later): a kept endpoint stays."""
        if self.metrics is not None and not self._metrics_adopted:
            self.metrics.stop()

    def check_status_free(self) -> None:
        """BadInput when another compd that is alive writes this status file: two instances on
        one file overwrite each other's state (and `compd status` shows either)."""
        if self.path is None:
            return
        try:
            data = status_mod.read_status(self.path)
        except BadInput:
            return  # none yet, or not a status file: this daemon overwrites it
        pid = data.get("pid")
        if pid == os.getpid() or not status_mod.liveness(data)[0]:
            return  # a reload of this daemon, or one that has stopped
        msg = (f"{self.path} is the status file of a running compd (pid {pid}, config {data.get('config')});"
               " give each config its own status.path")
        if self.app.cfg.top.status.path:
            raise self.app.cfg.doc.error(msg, ("status", "path"))
        raise BadInput(msg, file=str(self.path))

    def start(self) -> None:
        """Start the status thread, hook the watchdog; then real-time options (after `open_metrics`)."""
        app = self.app
        log.info(
            "compd starting: %s, model %s, sink %s%s",
            app.cfg.file,
            self.loop.model.kind,
            self.loop.sink.cfg.kind,
            " (observe mode: output held disabled)" if self.observe else "",
            extra={"event": "start", "config": app.cfg.file, "period_s": self.loop.period_s,
                   "observe": self.observe, "pid": os.getpid()},
        )
        if self.metrics is not None and self.metrics_url is None:
            self.open_metrics()
        self.notifier = Notifier.from_env()
        if self.notifier is not None:
            wd = watchdog_interval_s()
            status = "observe mode: output held disabled" if self.observe else "compensating"
            self.watchdog = WatchdogObserver(self.notifier, wd, status)
            self.loop.observers.append(self.watchdog)
        if self.control is not None:
            self.control.loop = self.loop
        elif self.loop.adapter is not None:
            log.warning("no probe socket: `compd probe` cannot reach this daemon (set adapt.socket_path or status.path)",
                        extra={"event": "probe_socket", "path": None})
        self.state = "running"
        self._tick()
        self._thread = threading.Thread(target=self._run, name="compd-status", daemon=True)
        self._thread.start()
        self.realtime_result = apply_realtime(self.realtime) if not self.loop.clock.simulated else []
        for ok, what in self.realtime_result:
            log.log(logging.INFO if ok else logging.WARNING, what, extra={"event": "realtime", "ok": ok})

    def stopping(self) -> None:
        """The loop has returned: tell systemd we are shutting down."""
        self.state = "stopping"
        if self.notifier is not None:
            self.notifier.send(STOPPING=1, STATUS="stopping: emitting the safe output")

    def stop(self, handing_over_to: Service | None = None) -> None:
        """After the safe output: last snapshot, close everything, log the summary line.

        Handing over to a reloaded pipeline's Service: no last snapshot (the status file
        is the new pipeline's, never a "stopped" between the two) and a metrics endpoint
        it kept stays up."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        try:
            if handing_over_to is None:
                self.state = "stopped"
                self._tick()
            else:
                self.events.flush()
                self.probe_events.flush()
        finally:
            if self.control is not None and (handing_over_to is None or handing_over_to.control is not self.control):
                self.control.close()
            if self.metrics is not None and (handing_over_to is None or handing_over_to.metrics is not self.metrics):
                self.metrics.stop()
            if self.notifier is not None:
                self.notifier.close()
        if handing_over_to is not None:
            return
        st = self.loop.stats
        log.info(
            "compd stopped after %d cycles, %d missed",
            st.cycles,
            st.misses,
            extra={"event": "stop", "cycles": st.cycles, "misses": st.misses},
        )

    # ------------------------------------------------------------- the thread
    def _run(self) -> None:
        spans = activity.ring("compd-status")  # None unless the bench records who runs when
        while not self._stop.wait(self.period_s):
            t0 = time.perf_counter_ns()
            try:
                self._tick()
            except Exception:  # the status thread must never take the daemon down
                self.status_errors += 1
                if self.status_errors <= 3:
                    log.exception("status update failed", extra={"event": "status_error"})
            if spans is not None:
                spans.mark(t0, time.perf_counter_ns())

    def snapshot(self) -> dict[str, Any]:
        extra = {
            "config": self.app.cfg.file,
            "status_period_s": self.period_s,
            "wall_uptime_s": time.monotonic() - self._t0,
            "metrics_url": self.metrics_url,
        }
        return status_mod.snapshot(self.loop, state=self.state, observe=self.observe, extra=extra)

    def _tick(self) -> None:
        self.events.flush()
        self.probe_events.flush()
        misses = self.loop.stats.misses
        if misses > self._misses:
            log.warning(
                "%d late cycles (%d in all)",
                misses - self._misses,
                misses,
                extra={"event": "late_cycles", "new": misses - self._misses, "misses": misses},
            )
            self._misses = misses
        if self.path is None and self.metrics is None and self.notifier is None:
            return
        snap = self.snapshot()
        if self.path is not None:
            try:
                status_mod.write_atomic(self.path, snap)
            except OSError as e:
                self.status_errors += 1
                if self.status_errors <= 3:
                    log.warning(
                        "cannot write status %s: %s", self.path, e.strerror or e,
                        extra={"event": "status_error"},
                    )
        if self.metrics is not None:
            self.metrics.update(snap, self.loop.stats)
        if self.notifier is not None and self.state == "running" and self.watchdog and self.watchdog.ready:
            states = " ".join(f"{a}={s['state']}" for a, s in snap["axes"].items())
            mode = "observe" if self.observe else "compensating"
            if snap["sink"]["link"] != "up":
                mode += f" (sink link {snap['sink']['link']}: output not reaching the machine)"
            self.notifier.send(
                STATUS=f"{mode}: word {snap['word']}, {states}, {snap['loop']['misses']} missed"
            )
