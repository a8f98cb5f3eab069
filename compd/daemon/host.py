"""What runs beside the loop in a daemon: status file, metrics, event log, data log, model state, probe socket.

Two halves, so that the cycle's interpreter runs no Python but the cycle's own:

* the cycle's side, `compd.cycle.publish.Publisher`: after every cycle the loop's thread writes
  its status record (compd/cycle/statusblock.py, shared memory) and hands over, as plain
  values in a shared-memory ring, the rest (the devices' accounts once a
  `status.period_s`, the guard's and the adapter's events, the data log's rows, the
  model's and the adapter's state) and takes the probes that came in;
* the service, `ServiceWork`: composes the status from the record every
  `status.period_s` (watching, every turn of its loop, that the record still moves: one
  that stopped is `stale` on every channel, compd.service.status) and writes the status
  file, serves and feeds the metrics, logs the events and late cycles, writes the data
  log and the model state, serves the probe socket, composes the STATUS= line for
  systemd. On the wall clock (`loop.io: process`, the
  default) it runs in a process of its own (`compd.io.child`), so none of this ever
  holds the GIL the cycle needs; on a simulated clock, and with `loop.io: thread`, on a
  thread of the daemon, fed the same way.

The daemon itself (`Service`) binds the metrics endpoint and the probe socket before
anything runs, so a busy port is refused at start-up with its config key, and keeps
them bound across a reload; the service serves what it inherited. Every message to
systemd leaves the daemon's main process (NotifyAccess=main): READY=1 and the
watchdog pings from the cycle (`WatchdogObserver`: a ping proves the cycle runs),
STOPPING=1 from the daemon, and the STATUS= line the service composes, which reaches
the cycle through shared memory.

A reload starts the new pipeline's service paused: it takes over the files and
sockets only when the old one has written its last rows and stopped (`go`). While the
reload builds the new pipeline the loop is paused and the old record says `reloading`
(`Service.reloading`), which the status tells from a dead cycle.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from compd.core.errors import BadInput
from compd.core.probe import Probe
from compd.cycle.publish import Publisher
from compd.cycle.realtime import apply_realtime, unshare_pages
from compd.cycle.statusblock import UNSEEN_S, Description, StatusBlock, compose, describe_static
from compd.io import activity
from compd.io.child import Child, ChildGone, Heartbeat
from compd.io.mailbox import shared_buffer
from compd.io.ring import MessageRing, SharedBlob
from compd.plant import spec as plant_spec
from compd.plant.remote_model import RemoteModels
from compd.plant.sandbox import listening_hint
from compd.plant.spec import OpcUaSpec, TelemetrySpec
from compd.service import logsetup  # noqa: F401  (installs the library's NullHandler)
from compd.service import status as status_mod
from compd.service.control import ControlServer, ProbeLink, socket_key, socket_path
from compd.service.logwriter import LogWriter
from compd.service.metrics import LATENESS_BOUNDS_US, MetricsServer
from compd.service.notify import Notifier, WatchdogObserver, watchdog_interval_s
from compd.service.state import StateWriter
from compd.service.status import lateness_buckets, status_path
from compd.service.threads import ServiceThread

if TYPE_CHECKING:
    from compd.config import Config
    from compd.core.frame import Frame
    from compd.cycle.loop import Loop
    from compd.models.base import Model

log = logging.getLogger("compd.service")

_EVENT_LEVEL = {"bad": logging.WARNING, "fault": logging.WARNING, "jump": logging.WARNING, "stall": logging.WARNING}
_EVENT_NAME = {
    "bad": "sensor_bad",
    "good": "sensor_good",
    "fault": "axis_fault",
    "recovering": "axis_recovering",
    "normal": "axis_normal",
    "jump": "clock_jump",  # the loop clock stepped (compd.cycle.guard.Guard.clock_jump)
    "stall": "loop_stall",  # the loop did not run for a while: woke late on a clock that did not step
    "held": "axis_held",  # the machine inhibits the axis, or it waits for its reference
    "released": "axis_released",
}

POLL_S = 0.02  # how often the service takes what the cycle handed over
OUTBOX_BYTES = 2 << 20  # cycle → service: ~5000 log rows (a stalled service; it takes them every 20 ms)
INBOX_BYTES = 64 << 10  # service → cycle: probes
STOP_TIMEOUT_S = 15.0  # a service that has not written its last rows by then is killed
OPCUA_RETRY_MIN_S = 5.0  # an OPC UA server that did not start is tried again after this, doubling ...
OPCUA_RETRY_MAX_S = 300.0  # ... up to this
SERVICE_STALL_S = 10.0  # a service process that has not taken a turn of its loop this long has stalled


def log_guard_event(t: float, subject: str, event: str, reason: str, cause: str | None = None) -> None:
    """One guard event as a log line: "T_xi bad: comms_lost (source adam: connect: …)"."""
    kind = "sensor" if event in ("bad", "good") else {"jump": "clock", "stall": "loop"}.get(event, "axis")
    extra = {"event": _EVENT_NAME.get(event, event), kind: subject, "reason": reason, "t_s": t}
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


def log_probe_event(ev: dict[str, Any]) -> None:
    """One adapter event (a probe accepted, rejected or ignored; a fault) as a log line."""
    kind, axis = ev.get("event"), ev.get("axis")
    extra = {"event": f"probe_{kind}", "axis": axis, "t_s": ev.get("t_s"), "source": ev.get("source")}
    if kind in ("accepted", "rejected"):
        extra.update(
            {k: ev.get(k) for k in ("error_um", "measured_um", "innovation_um", "innovation_sigma_um", "offset_um")}
        )
        if ev.get("reason") is not None:  # why it was rejected
            extra["reason"] = ev["reason"]
        log.log(
            logging.INFO if kind == "accepted" else logging.WARNING,
            "probe %s %s: error %.6g um, innovation %.2f um (sigma %.2f um), offset now %.2f um%s",
            axis,
            kind,
            ev["error_um"],
            ev["innovation_um"],
            ev["innovation_sigma_um"],
            ev["offset_um"],
            "" if ev.get("reason") is None else f": {ev['reason']}",
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


def check_status_free(cfg: Config) -> None:
    """BadInput when another compd that is alive (or whose cycle is stale: stopped, it may run
    again) writes the status file of `cfg`: two instances on one file overwrite each other's
    state (and `compd status` shows either)."""
    path = status_path(cfg)
    if path is None:
        return
    try:
        data = status_mod.read_status(path)
    except BadInput:
        return  # none yet, or not a status file: this daemon overwrites it
    pid = data.get("pid")
    if pid == os.getpid() or not status_mod.held(data):
        return  # a reload of this daemon, or one that has stopped
    msg = (
        f"{path} is the status file of a running compd (pid {pid}, config {data.get('config')});"
        " give each config its own status.path"
    )
    if cfg.top.status.path:
        raise cfg.doc.error(msg, ("status", "path"))
    raise BadInput(msg, file=str(path))


def check_status_folder(cfg: Config) -> None:
    """A config error naming `status.path` when the status file's folder is missing or not
    writable by this user (the file is written through a temporary file beside it)."""
    path = status_path(cfg)
    if path is None:
        return
    folder = path.parent
    why = (
        f"the folder {folder} of the status file does not exist"
        if not folder.is_dir()
        else f"the status file {path} cannot be written: its folder is not writable (uid {os.geteuid()})"
        if not os.access(folder, os.W_OK | os.X_OK)
        else None
    )
    if why is not None:
        raise cfg.doc.error(why, ("status", "path"))


@dataclass
class LogSpec:
    """The data log's file and its settings (config `log`)."""

    path: Path
    columns: list[str]
    flush_s: float
    rotate_bytes: int | None
    rotate_s: float | None
    keep: int


@dataclass
class StateSpec:
    """The model state file (config `state`) and the model it belongs to."""

    path: Path
    kind: str
    inputs: list[str]
    outputs: list[str]
    params_sha256: str | None


@dataclass
class ServiceSpec:
    """Everything the service needs besides what the cycle hands over: plain data."""

    config: str
    observe: bool
    status_path: Path | None
    log: LogSpec | None = None
    state: StateSpec | None = None
    adapt_axes: list[str] | None = None
    telemetry: TelemetrySpec | None = None  # MQTT Sparkplug B (config `telemetry`)
    opcua: OpcUaSpec | None = None  # the OPC UA server (config `opcua`)
    reload: bool = False  # this pipeline replaces another (a reload), not a start
    block: StatusBlock | None = None  # the cycle's status record (shared memory)
    description: Description | None = None  # what the record does not hold, at the start
    status_period_s: float = 1.0
    extra: dict[str, Any] | None = None  # into every status: config, status_period_s, metrics_url
    t0_s: float = 0.0  # monotonic time the daemon's service began (wall_uptime_s)


class _RingLink(ProbeLink):
    """The probe socket's way to the cycle: probes into the ring the cycle reads, verdicts
    from the adapter's events the cycle handed back."""

    def __init__(self, inbox: MessageRing, axes: list[str] | None) -> None:
        self._inbox = inbox
        self._axes = axes
        self._lock = threading.Lock()  # the socket's thread sends, the service's thread ... too
        self.events: deque[dict[str, Any]] = deque(maxlen=200)
        self.remote: Any = None  # compd.plant.remote_model.RemoteModels, when remote models are allowed

    @property
    def axes(self) -> list[str] | None:
        return self._axes

    def arm_model(self, window_s: float | None) -> dict[str, Any]:
        if self.remote is None:
            return super().arm_model(window_s)
        return self.remote.arm(window_s)

    def send(self, probe: Probe) -> None:
        with self._lock:
            self._inbox.put(probe)

    def outcome(self, tag: str) -> dict[str, Any] | None:
        for ev in reversed(list(self.events)):
            if ev.get("source") == tag:
                return ev
        return None


class ServiceWork:
    """The service (see the module): runs on what the cycle handed over. In a process of
    its own or on a thread; `go` opens its files and serves its sockets, `run` takes
    the messages until `finish`."""

    def __init__(
        self,
        spec: ServiceSpec,
        outbox: MessageRing,
        inbox: MessageRing,
        metrics: MetricsServer | None,
        control: ControlServer | None,
        status_line: SharedBlob | None = None,
    ) -> None:
        self.spec = spec
        self.outbox = outbox
        self.status_line = status_line  # STATUS= for systemd, sent by the cycle (NotifyAccess=main)
        self.link = _RingLink(inbox, spec.adapt_axes)
        self.metrics = metrics
        self.control = control
        self.log_writer: LogWriter | None = None
        self.state_writer: StateWriter | None = None
        self.status_errors = 0
        self.status_writes = 0
        self.messages = 0
        self.last_snapshot: dict[str, Any] | None = None
        self._misses = 0
        self._going = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one taker of the ring at a time (the thread, finish)
        self._thread: ServiceThread | None = None
        self._final: dict[str, Any] | None = None
        self.telemetry: Any = None  # compd.plant.telemetry.Telemetry
        self.remote: Any = None  # compd.plant.remote_model.RemoteModels
        self.opcua: Any = None  # compd.plant.opcua.OpcUaServer, started on the first snapshot
        self.opcua_error: str | None = None
        self._opcua_retry_s = 0.0  # monotonic time the next start may be tried
        self._opcua_attempts = 0
        self._opcua_next_s = 0.0
        self.beat = np.zeros(1, dtype=np.int64)  # counted at every turn of the loop (shared with the daemon)
        self.description = spec.description
        self._next_status_s = -1.0  # monotonic time the next status is due (-1: not serving yet)
        self._record_writes = -1  # the cycle's record's write count as last seen ...
        self._record_moved_s = 0.0  # ... and the monotonic time it was seen to change
        self._record_looked_s = 0.0  # ... and last looked at
        self._reading: Any = None  # the last consistent copy of the record
        self.cycle_stale = False  # the last status said the record is stale

    # ------------------------------------------------------------------ life
    def start(self, paused: bool) -> None:
        """Start taking messages on a thread; `paused`: only after `go`."""
        self._thread = ServiceThread("compd-service", self._run)
        self._thread.start()
        if not paused:
            self.go()

    def go(self) -> None:
        """Open the data log and the state file, serve the sockets, take messages."""
        if self._going.is_set():
            return
        spec = self.spec
        if spec.log is not None:
            lg = spec.log
            self.log_writer = LogWriter(
                lg.path, lg.columns, lg.flush_s, rotate_bytes=lg.rotate_bytes, rotate_s=lg.rotate_s, keep=lg.keep
            )
        if spec.state is not None:
            st = spec.state
            self.state_writer = StateWriter(st.path, st.kind, st.inputs, st.outputs, params_sha256=st.params_sha256)
        if self.metrics is not None:
            self.metrics.serve()
        if spec.telemetry is not None:
            self._start_telemetry(spec.telemetry)
        if self.control is not None:
            self.control.serve(self.link)
        self._next_status_s = 0.0  # the first status at once, from the record the cycle keeps writing
        self._going.set()

    def _start_telemetry(self, tspec: TelemetrySpec) -> None:
        """The MQTT client (its own thread) and, when allowed, the remote model handler."""
        from compd.plant.telemetry import Telemetry

        if tspec.remote is not None:
            self.remote = self.link.remote = RemoteModels(tspec.remote)
        remote = self.remote
        self.telemetry = Telemetry(
            tspec,
            commands=remote.handle if remote is not None else None,
            armed=remote.armed if remote is not None else None,
        )
        try:
            self.telemetry.start()
        except BadInput as e:
            log.error("telemetry off: %s", e, extra={"event": "telemetry_error", "reason": str(e)})
            self.telemetry = None
            return
        self.telemetry.event("reloaded" if self.spec.reload else "started", self.spec.config, "")
        if remote is not None:
            answer = remote.started()
            if answer is not None:
                self.telemetry.answer(answer)

    def finish(self) -> dict[str, Any]:
        """Take what is left, close the files (the last rows and state written), stop serving
        (the sockets stay bound: the daemon owns them); the final counts. Once."""
        if self._final is not None:
            return self._final
        self._stop.set()
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S)
            self._thread = None
        if self._going.is_set():
            self.step()
        if self.control is not None:
            self.control.stop_serving()
        if self.metrics is not None:
            self.metrics.stop_serving()
        if self.telemetry is not None:
            self.telemetry.event("stopping", self.spec.config, "")
            self.telemetry.stop()
        if self.opcua is not None:
            self.opcua.stop()
        if self.log_writer is not None:
            self.log_writer.close()
        if self.state_writer is not None:
            self.state_writer.close()
        self._final = self.counts()
        return self._final

    def counts(self) -> dict[str, Any]:
        return {
            "pid": os.getpid(),
            "messages": self.messages,
            "status_writes": self.status_writes,
            "status_errors": self.status_errors,
            "log": self.log_writer.get_status() if self.log_writer is not None else None,
            "state_error": self.state_writer.error if self.state_writer is not None else None,
            "state_writes": self.state_writer.writes if self.state_writer is not None else 0,
            "probes_served": self.control.served if self.control is not None else 0,
            "telemetry": self.telemetry.get_status() if self.telemetry is not None else None,
            "opcua": self.opcua.get_status() if self.opcua is not None else None,
        }

    # ------------------------------------------------------------- the thread
    def _run(self) -> None:
        spans = activity.ring("compd-service")  # None unless the bench records who runs when (a thread)
        while not self._stop.is_set():
            self.beat[0] += 1
            if self._going.is_set():
                t0 = time.perf_counter_ns()
                try:
                    self.record_age_s()
                    self.step()
                    if 0.0 <= self._next_status_s <= time.monotonic():
                        self.publish()
                except Exception:  # the service must never take the daemon down
                    self.status_errors += 1
                    if self.status_errors <= 3:
                        log.exception("service failed", extra={"event": "status_error"})
                if spans is not None:
                    spans.mark(t0, time.perf_counter_ns())
            self._stop.wait(POLL_S)

    def step(self) -> int:
        """Act on every message the cycle handed over since the last step; how many."""
        with self._lock:
            msgs = self.outbox.take()
            for msg in msgs:
                try:
                    self._handle(msg)
                except Exception:  # one message that fails never stops the others, nor the daemon
                    self.status_errors += 1
                    if self.status_errors <= 3:
                        log.exception("service: %s failed", msg[0], extra={"event": "status_error"})
            self.messages += len(msgs)
            return len(msgs)

    def _handle(self, msg: tuple[Any, ...]) -> None:
        what = msg[0]
        if what == "status_now":
            self.publish()
            return
        value = msg[1]
        if what == "devices":
            if self.description is not None:
                self.description.devices = value
                if value.get("model_state") is not None:
                    self.description.model = {**self.description.model, "state": value["model_state"]}
        elif what == "events":
            if self.description is not None:
                self.description.add_events(value)
            for ev in value:
                log_guard_event(*ev)
                if self.telemetry is not None:
                    _t, subject, event, reason, cause = ev
                    self.telemetry.event(
                        _EVENT_NAME.get(event, event), subject, reason if cause is None else f"{reason} ({cause})"
                    )
        elif what == "probe_events":
            for ev in value:
                self.link.events.append(ev)
                log_probe_event(ev)
        else:
            self._to_file(what, value)

    def _to_file(self, what: str, value: Any) -> None:
        """A data-log row, or a model or adapter state to persist."""
        if what == "row":
            if self.log_writer is not None:
                self.log_writer.push(value)
            return
        sw = self.state_writer
        if sw is None:
            return
        if what == "model_state":
            sw.submit(value)
        elif what == "adapt_state":
            sw.submit_adapt(value)

    def record_age_s(self) -> float:
        """Monotonic seconds the service has watched the cycle's record without seeing it change
        (its write count; looked at every turn of the service's loop, and at each status): not the
        loop's clock, which a simulated clock runs faster. A time the service itself did not run
        (a turn over UNSEEN_S late: a host so busy that neither got the CPU, or the service's
        thread beside a cycle starved alike) is not counted: it says nothing of the cycle."""
        now = time.monotonic()
        block = self.spec.block
        writes = block.writes if block is not None else 0
        unseen = now - self._record_looked_s - POLL_S
        self._record_looked_s = now
        if writes != self._record_writes:
            self._record_writes, self._record_moved_s = writes, now
        elif unseen > UNSEEN_S:
            self._record_moved_s = min(now, self._record_moved_s + unseen)
        return now - self._record_moved_s

    def publish(self) -> None:
        """Compose the status from the cycle's record now (compd.cycle.statusblock) and write it
        out: status file, metrics, STATUS= line, the plant; the next a period later. A record that
        has not moved for its `stale_after_s` is `stale` (compd.service.status.mark_stale)."""
        spec = self.spec
        description = self.description
        if spec.block is None or description is None:  # the service of a cycle hands both over
            return
        self._next_status_s = time.monotonic() + spec.status_period_s
        reading = spec.block.read()
        if reading is None:  # never written yet; or mid-write (a cycle stopped there): the last copy, aged
            reading = self._reading
            if reading is None:
                return
        self._reading = reading
        snap = compose(reading, description)
        snap.update(spec.extra or {})
        snap["wall_uptime_s"] = time.monotonic() - spec.t0_s
        age = self.record_age_s()
        limit = status_mod.stale_after_s(float(description.static["period_s"]), snap["state"])
        snap["record_age_s"] = round(age, 3)
        snap["stale_after_s"] = limit
        stale = limit is not None and age > limit
        if stale != self.cycle_stale:
            self._say_stale(stale, snap["state"], age)
        if stale:
            status_mod.mark_stale(snap)
        self._status(snap, lateness_buckets(reading, LATENESS_BOUNDS_US))

    def _say_stale(self, stale: bool, state: str, age_s: float) -> None:
        """The record went stale, or moves again: a log line and a telemetry event."""
        self.cycle_stale = stale
        if stale:
            reason = f"no record from the cycle for {age_s:.1f} s (its state {state}): stopped or hung?"
            log.warning(
                "the cycle is stale: %s",
                reason,
                extra={"event": "cycle_stale", "record_age_s": round(age_s, 3), "state": state},
            )
        else:
            reason = f"the cycle writes its record again (state {state})"
            log.info("%s", reason, extra={"event": "cycle_resumed", "state": state})
        if self.telemetry is not None:
            self.telemetry.event("cycle_stale" if stale else "cycle_resumed", "loop", reason)

    def _status(self, raw: dict[str, Any], buckets: Any) -> None:
        snap = status_mod.jsonable(raw)
        snap["service_pid"] = os.getpid()  # the daemon's pid when the service is a thread of it
        try:
            self._plant(snap)
        except Exception:  # the plant's side never costs the status file, metrics or STATUS= line
            self.status_errors += 1
            if self.status_errors <= 3:
                log.exception("service: telemetry/OPC UA failed", extra={"event": "status_error"})
        self.last_snapshot = snap
        misses = int(snap["loop"]["misses"])
        if misses > self._misses:
            log.warning(
                "%d late cycles (%d in all)",
                misses - self._misses,
                misses,
                extra={"event": "late_cycles", "new": misses - self._misses, "misses": misses},
            )
        self._misses = misses
        if self.metrics is not None:  # first: whoever sees this status file finds these metrics
            self.metrics.update_buckets(snap, buckets)
        path = self.spec.status_path
        if path is not None:
            try:
                status_mod.write_atomic(path, snap)
                self.status_writes += 1
            except OSError as e:
                self.status_errors += 1
                if self.status_errors <= 3:
                    log.warning("cannot write status %s: %s", path, e.strerror or e, extra={"event": "status_error"})
        if self.status_line is not None and snap["state"] == "running" and snap["loop"]["cycles"] > 0:
            states = " ".join(f"{a}={s['state']}" for a, s in snap["axes"].items())
            mode = "observe" if snap["observe"] else "compensating"
            if snap["sink"]["link"] != "up":
                mode += f" (sink link {snap['sink']['link']}: output not reaching the machine)"
            word = (
                f"word {snap['word']} held back, 0x0000 at the machine" if snap["observe"] else f"word {snap['word']}"
            )
            line = f"{mode}: {word}, {states}, {snap['loop']['misses']} missed"
            self.status_line.publish(line.encode("utf-8")[: self.status_line.capacity])

    def _plant(self, snap: dict[str, Any]) -> None:
        """The snapshot to the plant: a telemetry sample when one is due, the OPC UA values;
        their own status into the snapshot (the status file shows it)."""
        tel = self.telemetry
        if tel is not None:
            if self.remote is not None:
                late = self.remote.observe(snap)
                if late is not None:
                    tel.answer(late)
            tel.sample(snap)
            snap["telemetry"] = tel.get_status()
        ua = self.spec.opcua
        if ua is not None and time.monotonic() >= self._opcua_next_s:
            self._opcua_next_s = time.monotonic() + ua.cfg.period_s * 0.9
            self._opcua(ua, snap)
        if ua is not None:
            snap["opcua"] = self.opcua.get_status() if self.opcua is not None else {"error": self.opcua_error}

    def _opcua(self, ua: Any, snap: dict[str, Any]) -> None:
        """Update the OPC UA server, or start it: a start that fails (a slow host, a port taken)
        is said once per reason and tried again with back-off, never given up."""
        if self.opcua is not None:
            self.opcua.update(snap)
            return
        now = time.monotonic()
        if now < self._opcua_retry_s:
            return
        from compd.plant.opcua import OpcUaServer

        server = OpcUaServer(ua.cfg, ua.base_dir, ua.guard)
        try:
            url = server.start(snap)
        except BadInput as e:
            self._opcua_attempts += 1
            wait = min(OPCUA_RETRY_MAX_S, OPCUA_RETRY_MIN_S * 2 ** min(self._opcua_attempts - 1, 10))
            self._opcua_retry_s = time.monotonic() + wait
            if str(e) != self.opcua_error:
                log.error(
                    "OPC UA server off: %s; trying again in %.0f s",
                    e,
                    wait,
                    extra={"event": "opcua_error", "reason": str(e), "retry_in_s": wait},
                )
            self.opcua_error = str(e)
            return
        self.opcua, self.opcua_error, self._opcua_attempts = server, None, 0
        log.info("OPC UA on %s", url, extra={"event": "opcua", "url": url})
        hint = listening_hint("the OPC UA server", ua.cfg.bind)
        if hint is not None:  # the sandbox drops other hosts' packets unseen: said once, at the start
            log.warning("%s", hint, extra={"event": "opcua_sandbox", "url": url})


class _ServiceHost:
    """Where a `ServiceWork` runs: a child process (`process`) or a thread of the daemon.

    A child is watched by the daemon's supervisor (compd/io/supervisor.py) like an I/O
    worker: its heartbeat (a turn of its loop, every `POLL_S`) and its process; a service
    that died or stalled is reported (`service_lost`), killed and started again
    (`service_restarted`). The ring the cycle writes to is the daemon's: what was handed
    over while no service ran is taken by the new one (up to the ring's room)."""

    name = "service"
    lost_event = "service_lost"
    restarted_event = "service_restarted"

    def __init__(self, work: ServiceWork, process: bool, avoid_cpus: frozenset[int]) -> None:
        self.work = work
        self.process = process
        self.avoid_cpus = avoid_cpus
        self.child: Child | None = None
        self.final: dict[str, Any] | None = None
        self._beat_buf = shared_buffer(8)
        work.beat = np.frombuffer(self._beat_buf, dtype=np.int64, count=1)
        self._heartbeat = Heartbeat(work.beat, SERVICE_STALL_S)
        self._wanted = False
        self.lost: str | None = None

    # ------------------------------------------------------------ the supervisor's
    @property
    def pid(self) -> int | None:
        return self.child.pid if self.child is not None else None

    @property
    def wanted(self) -> bool:
        return self._wanted

    def health(self, now_s: float) -> str | None:
        """None while the service's process runs and beats (a thread: always)."""
        if not self._wanted or self.child is None:
            return None
        return self._heartbeat.health(self.child, now_s)

    def abandon(self, reason: str) -> None:
        child, self.child = self.child, None
        if child is not None:
            child.stop(0.0)  # kills what is left, reaps it
        self.lost = reason

    def restart(self) -> None:
        self._fork(paused=False)
        self.lost = None

    # ------------------------------------------------------------ life
    def start(self, paused: bool) -> None:
        if not self.process:
            self.work.start(paused)
            return
        self._fork(paused)
        self._wanted = True

    def _fork(self, paused: bool) -> None:
        work = self.work
        keep = [
            fd
            for fd in (work.metrics.fileno() if work.metrics else None, work.control.fileno() if work.control else None)
            if fd is not None
        ]
        child = Child("service")

        def answer(what: str, *args: Any) -> Any:
            if what == "go":
                return work.go()
            if what == "counts":
                return work.counts()
            if what == "finish":
                return work.finish()
            raise ValueError(f"unknown call {what!r}")

        def serve(ch: Child) -> None:
            work.start(paused)
            try:
                ch.serve_calls(answer)
            finally:
                work.finish()

        child.start(serve, self.avoid_cpus, keep_fds=keep)
        self.child = child
        self._heartbeat.reset(time.monotonic())

    def go(self) -> None:
        if self.child is None:
            if not self.process:
                self.work.go()
            return
        with contextlib.suppress(ChildGone):
            self.child.call("go", timeout_s=STOP_TIMEOUT_S)

    def counts(self) -> dict[str, Any]:
        if self.final is not None:
            return self.final
        if self.child is None:
            return self.work.counts() if not self.process else {"error": f"the service process was lost: {self.lost}"}
        try:
            return dict(self.child.call("counts", timeout_s=5.0))
        except ChildGone as e:
            return {"error": str(e)}

    def finish(self) -> dict[str, Any]:
        if self.final is not None:
            return self.final
        self._wanted = False
        if self.process and self.child is None:  # lost, not yet back: a new one writes what waits in the ring
            try:
                self._fork(paused=False)
            except Exception as e:
                self.final = {"error": f"the service process was lost ({self.lost}) and could not be started: {e}"}
                return self.final
        child = self.child
        if child is None:
            self.final = self.work.finish()
            return self.final
        try:
            self.final = dict(child.call("finish", timeout_s=STOP_TIMEOUT_S))
            child.call("exit", timeout_s=5.0)
        except ChildGone as e:
            self.final = {"error": f"the service process did not finish: {e}"}
            log.warning("%s", self.final["error"], extra={"event": "service_stuck"})
        child.stop(5.0)
        self.child = None
        return self.final


class Served(Protocol):
    """What the service reads of the App it serves (compd.daemon.app.App, which imports this module)."""

    @property
    def cfg(self) -> Config: ...
    @property
    def loop(self) -> Loop: ...
    @property
    def frame(self) -> Frame: ...
    @property
    def model(self) -> Model: ...


class Service:
    """The daemon's side of the service for one App: binds the sockets, builds the
    publisher the loop feeds, starts and stops the service (see the module)."""

    def __init__(self, app: Served, observe: bool = False) -> None:
        self.app = app
        self.loop = app.loop
        top = app.cfg.top
        self.observe = observe
        self.period_s = top.status.period_s
        # the plant's (config telemetry, opcua): files read and checked now, so check-config finds what is wrong
        self.telemetry_spec: TelemetrySpec | None = None
        self.opcua_spec: OpcUaSpec | None = None
        if top.telemetry is not None or top.opcua is not None:
            self.period_s = min(self.period_s, *(sec.period_s for sec in (top.telemetry, top.opcua) if sec is not None))
            if top.telemetry is not None:
                self.telemetry_spec = plant_spec.telemetry_spec(
                    app.cfg, list(app.frame.names), list(app.model.outputs), self.period_s
                )
            if top.opcua is not None:
                self.opcua_spec = plant_spec.opcua_spec(app.cfg)
        self.path = status_path(app.cfg)
        self.metrics = MetricsServer(top.metrics.bind, top.metrics.port) if top.metrics.enabled else None
        self.metrics_url: str | None = None
        self._metrics_cfg = (top.metrics.bind, top.metrics.port) if top.metrics.enabled else None
        self._metrics_adopted = False
        self.realtime = top.loop.realtime
        spath = socket_path(app.cfg)
        self.control = ControlServer(spath, socket_key(app.cfg)) if spath is not None else None
        self._control_adopted = False
        self.notifier: Notifier | None = None
        self.watchdog: WatchdogObserver | None = None
        self.state = "starting"
        self._t0 = time.monotonic()
        self.realtime_result: list[tuple[bool, str]] = []
        # made before any fork: shared with a service process
        self.outbox = MessageRing(OUTBOX_BYTES)
        self.inbox = MessageRing(INBOX_BYTES)
        self.status_line = SharedBlob(512)  # the service's STATUS= line, sent by the cycle
        self.publisher = Publisher(
            self.loop,
            self.outbox,
            self.inbox,
            status_period_s=self.period_s,
            observe=observe,
        )
        self.log_spec: LogSpec | None = None
        self.state_spec: StateSpec | None = None
        self._host: _ServiceHost | None = None
        self._previous: Service | None = None

    # ------------------------------------------------------------------ life
    def adopt(self, previous: Service) -> None:
        """Config reload: keep the bound metrics endpoint and probe socket when unchanged."""
        self._previous = previous
        if self._metrics_cfg is not None and self._metrics_cfg == previous._metrics_cfg and previous.metrics_url:
            self.metrics = previous.metrics
            self.metrics_url = previous.metrics_url
            self._metrics_adopted = True
        pc = previous.control
        if self.control is not None and pc is not None and pc.path == self.control.path and pc.fileno() is not None:
            self.control = pc  # the same socket goes on; the new service serves it
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
        self.metrics_url = self.metrics.bind_socket()
        log.info("metrics on %s", self.metrics_url, extra={"event": "metrics", "url": self.metrics_url})

    def close_metrics(self) -> None:
        """Undo `open_metrics` (a reload that failed later): a kept endpoint stays."""
        if self.metrics is not None and not self._metrics_adopted:
            self.metrics.stop()

    def check_status_free(self) -> None:
        """BadInput when another compd that is alive writes this status file (the module's
        `check_status_free`)."""
        check_status_free(self.app.cfg)

    @property
    def in_process(self) -> bool:
        """Whether the service runs in a process of its own."""
        return self._host is not None and self._host.process

    @property
    def pid(self) -> int | None:
        """The service's process id while it runs in a process of its own, else None."""
        child = self._host.child if self._host is not None else None
        return child.pid if child is not None else None

    def start(self) -> None:
        """Start the service (paused on a reload, until the old one has stopped), hook the
        publisher and the watchdog into the loop; then real-time options."""
        app = self.app
        loop = self.loop
        log.info(
            "compd starting: %s, model %s, sink %s%s",
            app.cfg.file,
            loop.model.kind,
            loop.sink.cfg.kind,
            " (observe mode: output held disabled)" if self.observe else "",
            extra={
                "event": "start",
                "config": app.cfg.file,
                "period_s": loop.period_s,
                "observe": self.observe,
                "pid": os.getpid(),
            },
        )
        if self.metrics is not None and self.metrics_url is None:
            self.open_metrics()
        if self.control is None and (
            loop.adapter is not None or (self.telemetry_spec is not None and self.telemetry_spec.remote is not None)
        ):
            log.warning(
                "no probe socket: `compd probe` cannot reach this daemon (set adapt.socket_path or status.path)",
                extra={"event": "probe_socket", "path": None},
            )
        spec = ServiceSpec(
            config=app.cfg.file,
            observe=self.observe,
            status_path=self.path,
            log=self.log_spec,
            state=self.state_spec,
            adapt_axes=list(loop.adapter.axes) if loop.adapter is not None else None,
            telemetry=self.telemetry_spec,
            opcua=self.opcua_spec,
            reload=self._previous is not None,
            block=self.publisher.block,
            status_period_s=self.period_s,
            t0_s=self._t0,
            description=Description(describe_static(loop, self.observe), loop.model.get_status()),
            extra={"config": app.cfg.file, "status_period_s": self.period_s, "metrics_url": self.metrics_url},
        )
        work = ServiceWork(spec, self.outbox, self.inbox, self.metrics, self.control, self.status_line)
        host = _ServiceHost(work, process=loop.io_process and loop.clock.fork_safe, avoid_cpus=loop.cycle_cpus)
        host.start(paused=self._previous is not None)
        self._host = host
        if host.child is not None:
            self.publisher.supervised.append(host)
        self.notifier = Notifier.from_env()
        if self.notifier is not None:
            wd = watchdog_interval_s()
            status = "observe mode: output held disabled" if self.observe else "compensating"
            sup = self.publisher.supervisor
            self.watchdog = WatchdogObserver(
                self.notifier, wd, status, status_line=self.status_line, healthy=lambda: not sup.escalated
            )
            loop.observers.append(self.watchdog)
        # the probes a source reads (its worker puts them in a ring of its own), and compd probe's
        self.publisher.watch_probes(loop.sources)
        loop.publisher = self.publisher
        self.state = "running"
        self.publisher.publish_status("running")
        self.realtime_result = apply_realtime(self.realtime) if not loop.clock.simulated else []
        for ok, what in self.realtime_result:
            log.log(logging.INFO if ok else logging.WARNING, what, extra={"event": "realtime", "ok": ok})
        if self.realtime.lock_memory and not loop.clock.simulated:
            unshared = unshare_pages()  # the children forked above share our pages until written
            log.info(
                "%d kB of memory copied from the pages shared with the daemon's child processes",
                unshared,
                extra={"event": "realtime", "unshared_kb": unshared},
            )

    def reloading(self) -> None:
        """The loop has returned for a reload: the record says `reloading` while the new pipeline
        is built, so that the status tells the pause from a dead cycle (compd.service.status)."""
        self.state = "reloading"
        self.publisher.publish_status("reloading")
        if self.watchdog is not None:  # the interval starts anew: the new pipeline's first cycle pings again
            self.watchdog.ping()

    def resume(self) -> None:
        """The loop runs on after a reload that was refused or failed: the record says running again."""
        if self.state == "reloading":
            self.state = "running"
            self.publisher.publish_status("running")

    def stopping(self) -> None:
        """The loop has returned: tell systemd we are shutting down; the record says `stopping`
        while the safe output goes out (the loop is not meant to run: never `stale`)."""
        self.state = "stopping"
        self.publisher.publish_status("stopping")
        if self.notifier is not None:
            self.notifier.send(STOPPING=1, STATUS="stopping: emitting the safe output")

    def stop(self, handing_over_to: Service | None = None) -> None:
        """After the safe output: the last events and snapshot, the service's last rows and
        state written, the sockets closed; log the summary line.

        Handing over to a reloaded pipeline's Service: no last snapshot (the status file
        is the new pipeline's, never a "stopped" between the two), the sockets it kept
        stay bound, and the new service starts once this one has stopped."""
        self.loop.publisher = None
        self.publisher.flush_events()
        if handing_over_to is None:
            self.state = "stopped"
            self.publisher.publish_status("stopped")
        try:
            if self._host is not None:
                self._host.finish()
        finally:
            if self.control is not None and (handing_over_to is None or handing_over_to.control is not self.control):
                self.control.close()
            if self.metrics is not None and (handing_over_to is None or handing_over_to.metrics is not self.metrics):
                self.metrics.stop()
            if self.notifier is not None:
                self.notifier.close()
        if handing_over_to is not None:
            if handing_over_to._host is not None:
                handing_over_to._host.go()
            return
        st = self.loop.stats
        log.info(
            "compd stopped after %d cycles, %d missed",
            st.cycles,
            st.misses,
            extra={"event": "stop", "cycles": st.cycles, "misses": st.misses},
        )

    def counts(self) -> dict[str, Any]:
        """The service's counts: rows of the data log written and dropped (there, or for want
        of room on the way), status and state writes and errors (the final ones once it stopped)."""
        counts = dict(self._host.counts()) if self._host is not None else {}
        if counts.get("log") is not None:
            counts["log"] = {
                **counts["log"],
                "rows_dropped": counts["log"]["rows_dropped"] + self.publisher.rows_dropped,
            }
        return counts
