"""MQTT Sparkplug B telemetry: birth and death certificates, a sample per period, events, store and forward, commands.

One `Telemetry` is one Sparkplug edge node (this compd) with one device (the machine
it compensates). It runs on a thread of its own ("compd-telemetry") in the service
process (compd/daemon/host.py), never on the cycle: the service hands it each status
snapshot (`sample`) and each event (`event`) and returns at once.

Every sample and event goes first into the store-and-forward buffer (an SQLite file,
compd/plant/buffer.py) and is deleted from it only when the broker has acknowledged it
(QoS 1). So while the broker is unreachable samples pile up on disk, bounded by
`telemetry.buffer.max_mb` (full: the oldest are dropped, counted in `Telemetry/dropped`
and the status file), and when it returns they are sent in the order they were taken,
marked historical, before the live ones. A sample that the broker received but whose
acknowledgement was lost with the connection is sent again: each carries its number
(`Sample`, never reused, kept across restarts), so a consumer drops the repeat.

When the buffer's file cannot be written (its disk full, an I/O error) or opened (a service
that starts on a full disk), the telemetry goes on live: samples and events wait in memory
instead (compd/plant/buffer.py's MemoryBuffer, bounded) and go out as they come, `compd
status` says `buffer: memory` with the reason, one line says so (`telemetry_unbuffered`).
The file is tried again with back-off; once it takes records, what memory held is moved into
it and one line says so (`telemetry_buffered`). Nothing the file held is deleted for room.

Sparkplug B as compd speaks it (docs/plant.md):

* with `primary_host_id`, nothing but the connection until that host's STATE says it is
  online (Sparkplug 3.0: a host that is not there would miss the data, so it waits on
  disk), and again when it goes offline;
* on every connection, a new `bdSeq`; the last will is the NDEATH with it; then NBIRTH
  (node metrics) and DBIRTH (every metric the machine's DDATA ever carries, the events'
  too, and the `Model/apply` command, with their types, units, current values and time
  stamps), `seq` 0, 1, … 255, 0 … over every message of the session;
* aliases: the births give every metric its name and an alias (`AliasTable`: unique across
  the node and its device, kept for the life of the process, so a rebirth keeps them; not
  `Node Control/Rebirth`, which goes by name); NDATA and DDATA carry the alias and no name;
* a DDATA per sample, by exception: `Sample` and the metrics that changed since the last
  one sent (a Double by more than its unit's deadband, DEADBAND_BY_UNIT; anything else by
  any change), and every metric at the first sample after each birth and at least every
  `full_refresh_s` of sample time (0: always); a DDATA with the three `Event/*` metrics per
  event (an event is news even when it repeats the last); an NDATA with the node's own
  metrics that changed (and `Model/result` with every answer). The buffer keeps every
  sample whole and by name: a record is encoded (aliases, exceptions) when it is sent, so a
  sample replayed after a rebirth, a reconnection or a restart speaks the aliases of the
  births just sent, and the exceptions run over the records in the order they go out;
* NCMD `Node Control/Rebirth` → births again; NCMD `Node Control/Model` or DCMD
  `Model/apply` (a model file's text) → `commands` (compd/plant/remote_model.py), whose
  answer goes out as NDATA `Model/result`; NCMD `Node Control/Shadow` or DCMD
  `Model/shadow` likewise, the text meant for the shadow model (declared in the births
  of a node that takes remote models);
* data is published with QoS 1, not the QoS 0 the specification asks for, so that the
  broker acknowledges each sample and the buffer knows what it may forget.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import random
import sqlite3
import ssl
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from compd.core.errors import BadInput
from compd.cycle.statusblock import FIELDS, PER_SIGNAL, Field, instances, shown, signal_unit
from compd.plant import sandbox
from compd.plant.buffer import MEMORY_MAX_BYTES, Counters, MemoryBuffer, StoreAndForward
from compd.plant.sparkplug import (
    NAMESPACE,
    AliasTable,
    DataType,
    MetricDef,
    SparkplugError,
    decode,
    encode,
    topic,
)
from compd.plant.spec import BrokerSpec, TelemetrySpec
from compd.service.threads import ServiceThread

log = logging.getLogger("compd.telemetry")

WINDOW = 32  # samples in flight (sent, not yet acknowledged) at a time

CONNECT_TIMEOUT_S = 5.0
RECONNECT_MIN_S = 0.5
DRAIN_S = 3.0  # at stop, how long the samples still buffered may take to go out
MAX_INBOX = 10_000  # samples and events waiting for the thread (it writes them to disk in ms)
MAX_COMMAND_BYTES = 16 << 20  # an NCMD/DCMD longer than this is not even decoded

NODE_REBIRTH = "Node Control/Rebirth"
NODE_MODEL = "Node Control/Model"
DEVICE_MODEL = "Model/apply"
NODE_SHADOW = "Node Control/Shadow"
DEVICE_SHADOW = "Model/shadow"
# the commands that carry a model file's text, and what it replaces (RemoteModels.handle's target)
MODEL_COMMANDS = {NODE_MODEL: "model", DEVICE_MODEL: "model", NODE_SHADOW: "shadow", DEVICE_SHADOW: "shadow"}

# Report by exception: a Double metric goes out again when it has moved more than this from the
# value last sent (so what a host holds is never further than this from the truth, and is exact
# again at every full refresh); half the finest step the quantity comes in, so a real step is
# always sent and only float noise below it waits. Other units, a metric without one, and every
# other datatype (integers, booleans, strings, quality, state): any change.
DEADBAND_BY_UNIT: dict[str, float] = {
    "µm": 0.01,  # 1/100 of the word's 1 µm LSB, the finest correction a machine is given
    "mm": 0.001,  # a position: 1 µm
    "°C": 0.005,  # half the 0.01 °C step of a PT100 transmitter
    "K": 0.005,
    "rpm": 0.5,  # spindle speeds come in whole rpm
    "µs": 0.5,  # half the loop histogram's 1 µs bin
    "A": 0.005,  # half a drive's 0.01 A step
}
_MISSING = object()
_T = TypeVar("_T")


def moved(definition: MetricDef, value: Any, last: Any = _MISSING) -> bool:
    """Whether `value` is news against `last`, the value last sent (none sent yet: news).

    A Double or Float beyond its unit's deadband (DEADBAND_BY_UNIT); a null to a number or back,
    and any change of any other metric, always."""
    if last is _MISSING:
        return True
    if (
        definition.datatype in (DataType.Double, DataType.Float)
        and isinstance(value, int | float)
        and isinstance(last, int | float)
        and not isinstance(value, bool)
        and not isinstance(last, bool)
    ):
        return abs(value - last) > DEADBAND_BY_UNIT.get(definition.unit or "", 0.0)
    return bool(value != last)


def _num(value: Any) -> float | None:
    """A finite float, or None (Sparkplug's is_null) for NaN, None or anything not a number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _count(value: Any) -> int | None:
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) and value >= 0 else None


# a status field's kind → its Sparkplug datatype (a count shown as a 16-bit word: UInt16)
KIND_DATATYPES = {
    "number": DataType.Double,
    "count": DataType.UInt64,
    "flag": DataType.Boolean,
    "name": DataType.String,
    "hex": DataType.String,
}


def _datatype(f: Field) -> DataType:
    return DataType.UInt16 if f.kind == "count" and f.hex_digits == 4 else KIND_DATATYPES[f.kind]


def _field_value(f: Field, value: Any) -> Any:
    """A field's value as status.json shows it, as its metric's (`_datatype`): a number not finite, or
    anything not of the kind, is null; a name that is null (no hold) the empty string."""
    if f.kind == "number":
        return _num(value)
    if f.kind == "count":
        if isinstance(value, str) and f.hex_digits:
            try:
                return int(value, 16) & 0xFFFF
            except ValueError:
                return None
        return _count(value)
    if f.kind == "flag":
        return None if value is None else bool(value)
    return "" if value is None else str(value)


def record_metrics(snap: dict[str, Any]) -> list[tuple[MetricDef, Any]]:
    """A metric per instance of each field of the status record (compd/cycle/statusblock.py FIELDS)
    that Sparkplug shows: named by its rule (`Field.sparkplug_name`: `Axis/z/correction_um`), its
    datatype from its kind, its unit as status.json shows it (a signal's: the one its name says).
    A loop field whose section the snapshot lacks (a log replayed into telemetry has no loop timing)
    is left out."""
    out: list[tuple[MetricDef, Any]] = []
    for f in FIELDS:
        if not f.on("sparkplug"):
            continue
        assert f.scope is not None
        if f.scope.name in ("loop", "service") and (f.at or (f.key,))[0] not in snap:
            continue
        for at, where in instances(f.scope, snap):
            if not shown(f, snap, at):
                continue
            unit = (signal_unit(at["signal"]) if f.unit == PER_SIGNAL else f.shown_unit) or None
            out.append(
                (MetricDef(f.sparkplug_name(**at), _datatype(f), unit), _field_value(f, f.exported(snap, where)))
            )
    return out


def device_metrics(snap: dict[str, Any]) -> list[tuple[MetricDef, Any]]:
    """The machine's metrics and their values in one status snapshot (compd/service/status.py):
    the status record's fields (`record_metrics`) and what the status adds beside them.

    A section missing from the snapshot (a log replayed into telemetry has no loop
    timing) leaves its metrics out; a value that is not a finite number is null."""
    D = DataType
    out: list[tuple[MetricDef, Any]] = [
        (MetricDef("Observe", D.Boolean), bool(snap.get("observe", False))),
        *record_metrics(snap),
    ]
    shadow = snap.get("shadow")
    if isinstance(shadow, dict):  # the shadow model and its score on the probes, per axis
        out.append((MetricDef("Shadow/kind", D.String), str((shadow.get("model") or {}).get("kind") or "")))
        out.append((MetricDef("Shadow/file", D.String), str((shadow.get("model") or {}).get("file") or "")))
        for axis, sc in sorted((shadow.get("axes") or {}).items()):
            p = f"Shadow/{axis}/"
            out += [
                (MetricDef(p + "probes", D.UInt64), _count(sc.get("probes"))),
                (MetricDef(p + "active_rms_um", D.Double, "µm"), _num(sc.get("active_rms_um"))),
                (MetricDef(p + "shadow_rms_um", D.Double, "µm"), _num(sc.get("shadow_rms_um"))),
            ]
    lp = snap.get("loop")
    if isinstance(lp, dict):  # the loop's timing from its histograms (not fields of the record)
        late, comp = lp.get("lateness_us") or {}, lp.get("cycle_compute_us") or {}
        # a p99 over the histogram's range is its limit (20000 µs) and flagged: not a measurement
        over = lp.get("over_range") if isinstance(lp.get("over_range"), dict) else {}
        out += [
            (MetricDef("Loop/period_ms", D.Double, "ms"), _num(lp.get("period_ms"))),
            (MetricDef("Loop/lateness_p99_us", D.Double, "µs"), _num(late.get("p99"))),
            (MetricDef("Loop/lateness_p99_over_range", D.Boolean), "p99" in (over.get("lateness_us") or ())),
            (MetricDef("Loop/compute_p99_us", D.Double, "µs"), _num(comp.get("p99"))),
            (MetricDef("Loop/compute_p99_over_range", D.Boolean), "p99" in (over.get("cycle_compute_us") or ())),
        ]
    model = snap.get("model")
    if isinstance(model, dict):
        fit = model.get("fit") or {}
        out += [
            (MetricDef("Model/kind", D.String), str(model.get("kind", ""))),
            (MetricDef("Model/fitted_at", D.String), str(fit.get("fitted_at") or "")),
            (MetricDef("Model/file", D.String), str(model.get("file") or "")),
        ]
    return out


EVENT_METRICS = (
    MetricDef("Event/kind", DataType.String),
    MetricDef("Event/subject", DataType.String),
    MetricDef("Event/reason", DataType.String),
)
SAMPLE_METRIC = MetricDef("Sample", DataType.UInt64)
# what a host may write to the device (DCMD): declared in the DBIRTH, so that it has an alias
DEVICE_COMMANDS = (MetricDef(DEVICE_MODEL, DataType.String), MetricDef(DEVICE_SHADOW, DataType.String))
# ... the shadow's only by a node that takes remote models (one that takes none declares
# Model/apply alone, as before shadows; it answers either by name all the same)
SHADOW_COMMANDS = frozenset((NODE_SHADOW, DEVICE_SHADOW))


def declares(command: str, spec: TelemetrySpec) -> bool:
    """Whether the births declare this command metric (see SHADOW_COMMANDS)."""
    return command not in SHADOW_COMMANDS or spec.remote is not None


def log_in(client: Any, broker: BrokerSpec) -> None:
    """Give a paho client the broker's user and password and its TLS (CA, client certificate,
    host name check), as the telemetry section says."""
    if broker.username is not None:
        client.username_pw_set(broker.username, broker.password)
    if broker.ca_file is not None:
        client.tls_set(
            ca_certs=broker.ca_file,
            certfile=broker.cert_file,
            keyfile=broker.key_file,
            cert_reqs=ssl.CERT_REQUIRED,
            tls_version=ssl.PROTOCOL_TLS_CLIENT,
        )
        client.tls_insecure_set(not broker.check_hostname)


class Telemetry:
    """One Sparkplug edge node and its device (see the module). `start`, then `sample` and
    `event` from any thread (they never wait), `stop` at the end."""

    def __init__(
        self,
        spec: TelemetrySpec,
        commands: Callable[[str, str, str], dict[str, Any]] | None = None,
        armed: Callable[[], bool] | None = None,
    ) -> None:
        self.spec = spec
        self.commands = commands  # (model text, request id, "model" or "shadow") → the answer, on this thread
        self.armed = armed or (lambda: False)
        self.buffer: StoreAndForward | MemoryBuffer | None = None  # where records go now: the file, or memory
        self.disk: StoreAndForward | None = None  # the file, while it can be written
        self.memory: MemoryBuffer | None = None  # records taken while it cannot (`_unbuffered`)
        self.buffer_error: str | None = None  # why the file is not used (None: it is)
        self._disk_dropped = 0  # the file's count of dropped records when it was last closed
        self._disk_attempts = 0
        self._disk_next_s = 0.0  # monotonic time the file is tried again
        self._inbox: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread: ServiceThread | None = None
        self._drain_s = DRAIN_S  # at stop, how long what is buffered may take to go out
        self._next_sample_s = -math.inf  # wall time the next sample is due
        self._defs: dict[str, MetricDef] = {}  # the device's metrics as the last DBIRTH announced them
        self.aliases = AliasTable()  # the node's and the device's aliases, kept across rebirths
        self._node_aliases: dict[str, int] = {}  # name → alias of the last NBIRTH
        self._device_aliases: dict[str, int] = {}  # ... and of the last DBIRTH
        self._sent: dict[str, Any] | None = None  # device metric → value last sent (None: next one full)
        self._full_t_ms = 0  # sample time of the last full refresh sent
        self._node_sent: dict[str, Any] = {}  # node metric → value last sent (NBIRTH, NDATA)
        self._answered = False  # a command answered since the last NDATA: Model/result goes again
        self.full_refreshes = 0  # DDATA samples sent with every metric
        self.exceptions = 0  # DDATA samples sent with the metrics that changed
        self._latest: list[tuple[MetricDef, Any]] | None = None  # the newest sample (the births' values)
        self._latest_t_ms = 0
        self._birth_due = False  # a new device metric set: births again
        self._client: Any = None
        self._connected = False  # CONNACK accepted
        self._session = False  # births out: data may flow
        self._host_online = spec.primary_host_id is None  # the primary host's STATE (always, without one)
        self._seq = 0
        self._bdseq = 0
        self.counters: Any = None  # compd.plant.buffer.Counters: Sample and bdSeq, apart from the buffer
        self.failures = 0  # turns of the thread that raised (a full disk …), each followed by a retry
        self.lost_to_disk = 0  # samples and events the buffer could not take (counted in `dropped`)
        self._last_failure: str | None = None
        self._inflight: dict[int, int] = {}  # MQTT mid → buffer record id
        self._cursor = 0  # the newest record id handed to the client in this session
        self._historical_upto = 0  # records up to this id were taken before this session's births
        self._attempts = 0
        self._new_connection = False  # connected, births not yet sent on this connection
        self._sample_names: list[str] = []  # the metrics of the newest sample
        self._last_put_id = 0  # the newest record put in the buffer (births come after the first)
        self._next_try_s = 0.0
        self._down_since: float | None = None
        self._result = ""  # the last command's answer (NDATA Model/result)
        self._node_dirty = False
        self.sent = 0
        self.acked = 0
        self.connects = 0
        self.commands_seen = 0
        self.last_error: str | None = None
        self.inbox_dropped = 0  # samples and events handed over while the thread lagged MAX_INBOX behind
        self.dropped_unknown = 0  # buffered metrics no birth of this session announced (a reload changed the set)

    # ------------------------------------------------------------------ any thread
    def start(self) -> None:
        """Open the buffer (when it cannot be: live, from memory, the file tried again) and start the thread."""
        spec = self.spec
        self.memory = MemoryBuffer(min(spec.buffer_max_bytes, MEMORY_MAX_BYTES))
        self.counters = Counters(spec.buffer_path.with_name(spec.buffer_path.name + ".counters"))
        try:
            self.disk = self.buffer = StoreAndForward(spec.buffer_path, spec.buffer_max_bytes)
        except BadInput as e:  # a full disk (the open writes), a file that cannot be opened: not off for good
            self._unbuffered(e.message)
        self._client = self._make_client()
        self._thread = ServiceThread("compd-telemetry", self._run)
        self._thread.start()

    def sample(self, snap: dict[str, Any], t_unix_s: float | None = None) -> bool:
        """Take a sample from this status snapshot if one is due (one per `period_s` of wall
        time); True if it did. Never waits."""
        now = time.time() if t_unix_s is None else t_unix_s
        if now < self._next_sample_s - self.spec.slack_s or not self._taking():
            return False
        period = self.spec.period_s
        # on the period's grid: a snapshot a little late or early does not shift the next ones
        due = self._next_sample_s
        self._next_sample_s = due + period if abs(now - due) < period else now + period
        self._inbox.put(("sample", int(now * 1000), device_metrics(snap)))
        return True

    def event(self, kind: str, subject: str, reason: str, t_unix_s: float | None = None) -> None:
        """An event (a fault, a sensor lost, a reload, …), sent as it happens."""
        t = time.time() if t_unix_s is None else t_unix_s
        if self._taking():
            self._inbox.put(("event", int(t * 1000), [kind, subject, reason]))

    def _taking(self) -> bool:
        """Whether the thread runs and keeps up: else what is handed over is not kept in memory."""
        if self._thread is None or not self._thread.alive:
            return False
        if self._inbox.qsize() >= MAX_INBOX:
            self.inbox_dropped += 1
            return False
        return True

    def stop(self, drain_s: float = DRAIN_S) -> dict[str, Any]:
        """Send what the buffer holds (at most `drain_s`, if connected), the NDEATH, disconnect,
        close the buffer; the final status. Idempotent."""
        if self._thread is not None:
            self._drain_s = drain_s
            self._stop.set()
            self._thread.join(drain_s + CONNECT_TIMEOUT_S + 5.0)
            self._thread = None
        status = self.get_status()
        if self.disk is not None:
            self.disk.close()
            self.disk = None
        self.buffer = None
        return status

    def _buffer_dropped(self) -> int:
        """Records the buffer dropped (the oldest when full): the file's (its count now, else when
        it was last open) and memory's."""
        disk = self.disk.dropped if self.disk is not None else self._disk_dropped
        return disk + (self.memory.dropped if self.memory is not None else 0)

    def get_status(self) -> dict[str, Any]:
        """The telemetry's state for the status file (from any thread)."""
        current = self.buffer
        try:
            buf = current.get_status() if current is not None else {}
        except sqlite3.Error:  # the file closed by the thread this moment (`_unbuffered`): counted next time
            buf = {}
        return {
            "broker": f"{self.spec.host}:{self.spec.port}",
            "connected": self._session,
            "connects": self.connects,
            "sent": self.sent,
            "acknowledged": self.acked,
            "buffered": buf.get("records", 0),
            "buffered_bytes": buf.get("bytes", 0),
            # where samples wait: `disk` (the buffer's file), `memory` (it cannot be written: buffer_error)
            "buffer": "memory" if current is not None and current is self.memory else "disk",
            "buffer_error": self.buffer_error,
            "dropped": self._buffer_dropped() + self.inbox_dropped + self.lost_to_disk,
            "bdseq": self._bdseq,
            "counters_error": self.counters.error if self.counters is not None else None,
            "failures": self.failures,
            "commands": self.commands_seen,
            "last_error": self.last_error,
        }

    # ------------------------------------------------------------------ the thread
    def _make_client(self) -> Any:
        import paho.mqtt.client as mqtt

        spec = self.spec
        client = mqtt.Client(
            mqtt.CallbackAPIVersion.VERSION2, client_id=spec.client_id, clean_session=True, reconnect_on_failure=False
        )
        client.connect_timeout = CONNECT_TIMEOUT_S
        # paho holds back a QoS 1 message beyond its in-flight limit (20 by default) while a QoS 0
        # one (an NDATA, a rebirth) goes at once: past the window's samples, seq out of order on
        # the wire. Room for the whole window and the NDEATH, so every message leaves in seq order
        client.max_inflight_messages_set(WINDOW + 2)
        log_in(client, spec)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        client.on_message = self._on_message
        client.suppress_exceptions = False
        return client

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._turn()
            except Exception as e:  # a full disk, a bug: said once, the connection dropped, tried again
                self._failed(e)
        try:
            self._finish()
        except Exception as e:
            self.last_error = f"{type(e).__name__}: {e}"
            log.exception("telemetry could not finish: %s", self.last_error, extra={"event": "telemetry_error"})

    def _turn(self) -> None:
        """One turn of the thread: the buffer's file tried again when it is due, take what the
        service handed over, connect or send."""
        if self.disk is None and time.monotonic() >= self._disk_next_s:
            self._buffer_again()
        self._take_inbox()
        if self._client.is_connected() or self._connected:
            if self._session:  # what came in goes out now, not after the wait below
                if self._birth_due:
                    self._births(new_session=False)
                self._send()
            self._client.loop(timeout=self.spec.poll_s)
            if self._session:  # the acknowledgements that came in freed the window
                self._send()
        else:
            if self._latest is not None and time.monotonic() >= self._next_try_s:
                self._connect()
            if not self._client.is_connected():
                self._stop.wait(self.spec.poll_s)

    def _failed(self, e: Exception) -> None:
        """A turn raised (the buffer's disk full, anything unforeseen): log each new reason once,
        drop the connection (births again on the next), wait, go on. The telemetry never stops
        for good while the service runs: it recovers when the disk has room again."""
        reason = f"{type(e).__name__}: {e}"
        self.failures += 1
        if reason != self._last_failure:
            self._last_failure = reason
            log.error(
                "telemetry: %s; retrying", reason, exc_info=e, extra={"event": "telemetry_error", "reason": reason}
            )
        self.last_error = reason
        with contextlib.suppress(Exception):
            self._client.disconnect()
        self._connected = self._session = False
        self._inflight.clear()
        self._new_connection = False
        self._attempts += 1
        wait = min(self.spec.reconnect_max_s, RECONNECT_MIN_S * 2 ** min(self._attempts, 10))
        self._next_try_s = time.monotonic() + wait
        self._stop.wait(wait)

    # ------------------------------------------------------------ the buffer's file, or memory
    def _on_buffer(self, op: Callable[[StoreAndForward | MemoryBuffer], _T]) -> _T:
        """`op(buffer)`; when the buffer's file cannot take it (a full disk, an I/O error), memory
        takes over (`_unbuffered`) and `op` runs there."""
        buf = self.buffer
        assert buf is not None
        try:
            return op(buf)
        except (sqlite3.Error, OSError) as e:
            if buf is not self.disk:
                raise
            self._unbuffered(f"{type(e).__name__}: {e}")
            assert self.buffer is not None
            return op(self.buffer)

    def _unbuffered(self, reason: str) -> None:
        """The buffer's file cannot be written or opened: records wait in memory from now on
        (what the file holds stays there, sent once it is back), and the file is tried again
        later. What was in flight from the file goes again from it then."""
        path = self.spec.buffer_path
        disk, self.disk = self.disk, None
        if disk is not None:
            self._disk_dropped = disk.dropped
            with contextlib.suppress(Exception):
                disk.close()
        assert self.memory is not None
        self.buffer = self.memory
        self.buffer_error = reason
        self._inflight.clear()  # their acknowledgements are the file's: it keeps them, to send again
        self._cursor = self._historical_upto = self._last_put_id = 0
        self._disk_attempts += 1
        self._disk_next_s = time.monotonic() + self._disk_wait_s()
        log.error(
            "telemetry buffer %s cannot be used (%s): publishing live without it, samples kept in memory"
            " (at most %d bytes) until it can; trying it again",
            path,
            reason,
            self.memory.max_bytes,
            extra={"event": "telemetry_unbuffered", "path": str(path), "reason": reason},
        )

    def _disk_wait_s(self) -> float:
        return min(self.spec.reconnect_max_s, RECONNECT_MIN_S * 2 ** min(self._disk_attempts, 10))

    def _buffer_again(self) -> None:
        """Open the buffer's file again and move what memory holds into it (oldest first); on
        success it is the buffer again, else memory stays and the next try comes later."""
        spec = self.spec
        memory = self.memory
        assert memory is not None
        disk = None
        try:
            disk = StoreAndForward(spec.buffer_path, spec.buffer_max_bytes)
            waiting = memory.pending(len(memory))
            for rec in waiting:  # all or none: memory forgets them only once the file has them all
                disk.put(rec.t_ms, rec.kind, rec.body)
        except (BadInput, sqlite3.Error, OSError) as e:
            if disk is not None:  # some may be in the file now and in memory too: sent twice, never lost
                with contextlib.suppress(Exception):
                    disk.close()
            self.buffer_error = e.message if isinstance(e, BadInput) else f"{type(e).__name__}: {e}"  # said: status
            log.debug(
                "telemetry buffer %s still cannot be used: %s",
                spec.buffer_path,
                self.buffer_error,
                extra={"event": "telemetry_unbuffered", "path": str(spec.buffer_path), "reason": self.buffer_error},
            )
            self._disk_attempts += 1
            self._disk_next_s = time.monotonic() + self._disk_wait_s()
            return
        memory.take()
        self.disk = self.buffer = disk
        self.buffer_error = None
        self._disk_attempts = 0
        self._inflight.clear()  # memory's: what they were is in the file now, sent again from it
        self._cursor = 0
        self._historical_upto = self._last_put_id = disk.last_id  # all of it older than this session's births
        log.info(
            "telemetry buffer %s can be used again: %d samples and events moved into it from memory",
            spec.buffer_path,
            len(waiting),
            extra={"event": "telemetry_buffered", "path": str(spec.buffer_path), "moved": len(waiting)},
        )

    def _take_inbox(self) -> None:
        while True:
            try:
                what, t_ms, values = self._inbox.get_nowait()
            except queue.Empty:
                return
            if what == "answer":
                self._answer(values)
                continue
            try:
                self._store(what, t_ms, values)
            except Exception:
                self.lost_to_disk += 1  # could not be written (a full disk): counted as dropped
                raise

    def _store(self, what: str, t_ms: int, values: Any) -> None:
        """A sample or an event into the buffer (the sample numbered)."""
        if what == "sample":
            names = [d.name for d, _ in values]
            if names != self._sample_names:  # a new set of metrics: births again
                self._sample_names = names
                self._birth_due = self._session
            assert self.buffer is not None
            number = self.counters.get("sample", self.buffer.get_meta("sample")) + 1  # never given twice
            self._on_buffer(lambda b: b.set_meta("sample", number))
            self.counters.set("sample", number)
            self._latest = [(SAMPLE_METRIC, number), *values]
            self._latest_t_ms = t_ms
            body = [["Sample", number], *([d.name, v] for d, v in values)]
            self._put(t_ms, "D", body)
        else:
            self._put(t_ms, "D", [[d.name, v] for d, v in zip(EVENT_METRICS, values, strict=True)])

    def _put(self, t_ms: int, kind: str, body: list[Any]) -> None:
        data = json.dumps(body, ensure_ascii=False, allow_nan=False).encode("utf-8")

        def put(b: StoreAndForward | MemoryBuffer) -> tuple[StoreAndForward | MemoryBuffer, int, int]:
            before = b.dropped
            return b, before, b.put(t_ms, kind, data)

        buf, before, self._last_put_id = self._on_buffer(put)
        if buf.dropped != before:
            self._node_dirty = True
            if buf.dropped == 1 or buf.dropped % 1000 == 0:
                log.warning(
                    "telemetry buffer full (%s): the oldest samples dropped, %d so far",
                    buf.path or "memory",
                    buf.dropped,
                    extra={"event": "telemetry_dropped", "dropped": buf.dropped},
                )

    def _connect(self) -> None:
        spec = self.spec
        buf = self.buffer
        assert buf is not None
        bdseq = (
            self.counters.get("bdseq", buf.get_meta("bdseq", -1)) + 1
        ) % 256  # one more per CONNECT (Sparkplug 3.0)
        self._attempts += 1
        # a client of its own for every connection: paho would send again by itself what the last
        # one left unacknowledged, and this thread does that (from the buffer): twice
        self._client._reset_sockets()
        self._client = self._make_client()
        self._client.will_set(topic(spec.group_id, "NDEATH", spec.edge_node_id), _death(bdseq), qos=1, retain=False)
        try:
            self._client.connect(spec.host, spec.port, keepalive=spec.keepalive_s)
        except (OSError, ssl.SSLError, ValueError) as e:
            why = f"cannot connect to {spec.host}:{spec.port}: {getattr(e, 'strerror', None) or e}"
            if sandbox.refused_by_this_host(e):  # EPERM: the unit's IP sandbox (compd.plant.sandbox)
                why += f" ({sandbox.connect_refused_hint(spec.host)})"
            self._connection_failed(why)
            return  # no CONNECT went out: the same bdSeq next time
        self._bdseq = bdseq
        self._on_buffer(lambda b: b.set_meta("bdseq", bdseq))
        self.counters.set("bdseq", bdseq)
        self._connected = True
        self._new_connection = True

    def _connection_failed(self, why: str) -> None:
        self._connected = False
        self._session = False
        self._inflight.clear()
        if self._down_since is None:
            self._down_since = time.monotonic()
        if why != self.last_error:
            log.warning(
                "telemetry: %s; samples are kept %s until it answers",
                why,
                "on disk" if self.buffer is self.disk else "in memory",
                extra={"event": "telemetry_down", "reason": why},
            )
        self.last_error = why
        wait = min(self.spec.reconnect_max_s, RECONNECT_MIN_S * 2 ** min(self._attempts, 10))
        self._next_try_s = time.monotonic() + wait * random.uniform(
            0.5, 1.0
        )  # a plant's nodes do not all return at once

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if reason.is_failure:
            self._connection_failed(f"the broker refused the connection: {reason}")
            client.disconnect()
            return
        spec = self.spec
        subs = [
            (topic(spec.group_id, "NCMD", spec.edge_node_id), 1),
            (topic(spec.group_id, "DCMD", spec.edge_node_id, spec.device_id), 1),
        ]
        if spec.primary_host_id is not None:
            subs.append((f"{NAMESPACE}/STATE/{spec.primary_host_id}", 1))
            self._host_online = False  # until its STATE (retained) says otherwise
        client.subscribe(subs)
        self._attempts = 0
        self.connects += 1
        if self._down_since is not None or self.last_error is not None:
            log.info(
                "telemetry: connected to %s:%d; %d samples to send",
                spec.host,
                spec.port,
                len(self.buffer or ()),
                extra={"event": "telemetry_up"},
            )
        self._down_since = None
        self.last_error = None
        self._new_connection = True
        if self._host_online:
            self._session = True
            self._births(new_session=True)

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if not self._connected:  # after a refused CONNACK (said then), or at stop
            return
        self._connection_failed(f"connection to {self.spec.host}:{self.spec.port} lost: {reason}")

    def _on_publish(self, client: Any, userdata: Any, mid: int, reason: Any, properties: Any) -> None:
        rid = self._inflight.pop(mid, None)
        if rid is None or self.buffer is None:
            return
        self.acked += 1
        try:
            self.buffer.ack([rid])
        except (sqlite3.Error, OSError) as e:  # the file cannot be written: it keeps the record, sent again
            if self.buffer is not self.disk:
                raise
            self._unbuffered(f"{type(e).__name__}: {e}")

    def _births(self, new_session: bool) -> None:
        """NBIRTH and DBIRTH with the newest values; on a new connection, what is buffered up to
        now is historical and goes out first (what was in flight on the lost one again)."""
        spec = self.spec
        buf = self.buffer
        assert buf is not None and self._latest is not None
        self._birth_due = False
        self._seq = 0
        self._last_failure = None  # working again: a failure after this is said again
        # the device's birth declares every metric its DDATA ever carries (Sparkplug 3.0): the
        # sample's, and the events' (null until an event sets them); and what a DCMD may write
        born = [
            *self._latest,
            *((d, None) for d in EVENT_METRICS),
            *((d, "") for d in DEVICE_COMMANDS if declares(d.name, self.spec)),
        ]
        self._defs = {d.name: d for d, _ in born}
        node = self._node_metrics(birth=True)
        # every metric with its name and alias; the aliases stay what they were for a metric born before
        self._node_aliases = self.aliases.declare(None, [d.name for d, _ in node])
        self._device_aliases = self.aliases.declare(spec.device_id, list(self._defs))
        now_ms = int(time.time() * 1000)
        self._publish_raw(
            "NBIRTH",
            None,
            encode(
                node,
                timestamp_ms=now_ms,
                seq=self._next_seq(),
                with_properties=True,
                metric_timestamp_ms=now_ms,
                aliases=self._node_aliases,
            ),
            qos=0,
        )
        self._publish_raw(
            "DBIRTH",
            spec.device_id,
            encode(
                born,
                timestamp_ms=self._latest_t_ms,
                seq=self._next_seq(),
                with_properties=True,
                metric_timestamp_ms=self._latest_t_ms,
                aliases=self._device_aliases,
            ),
            qos=0,
        )
        self._node_sent = {d.name: v for d, v in node}
        self._answered = False
        self._sent = None  # the first sample after a birth goes whole: a host starts from it
        self._node_dirty = False
        self._historical_upto = self._last_put_id  # what waited goes out first, historical
        if new_session:  # what was in flight on a lost connection goes again
            self._new_connection = False
            self._cursor = 0
            self._inflight.clear()

    def _node_metrics(self, birth: bool) -> list[tuple[MetricDef, Any]]:
        D = DataType
        st = self.buffer.get_status() if self.buffer is not None else {}
        out: list[tuple[MetricDef, Any]] = []
        if birth:
            out += [
                (MetricDef("bdSeq", D.UInt64), self._bdseq),
                (MetricDef(NODE_REBIRTH, D.Boolean), False),
                *((MetricDef(n, D.String), "") for n in (NODE_MODEL, NODE_SHADOW) if declares(n, self.spec)),
            ]
            out += [(MetricDef(f"Properties/{k}", D.String), v) for k, v in sorted(self.spec.properties.items())]
        out += [
            (MetricDef("Telemetry/buffered", D.UInt64), int(st.get("records", 0))),
            (MetricDef("Telemetry/dropped", D.UInt64), self._buffer_dropped()),
            (MetricDef("Model/armed", D.Boolean), bool(self.armed())),
            (MetricDef("Model/result", D.String), self._result),
        ]
        return out

    def _next_seq(self) -> int:
        seq = self._seq
        self._seq = (seq + 1) % 256
        return seq

    def _publish_raw(self, kind: str, device: str | None, payload: bytes, qos: int) -> Any:
        spec = self.spec
        info = self._client.publish(topic(spec.group_id, kind, spec.edge_node_id, device), payload, qos=qos)
        self.sent += 1
        return info

    def _send(self) -> None:
        """Hand the client the buffered records after the cursor, WINDOW at a time."""
        buf = self.buffer
        assert buf is not None
        if self._node_dirty:
            self._node_dirty = False
            self._send_node()
        room = WINDOW - len(self._inflight)
        if room <= 0:
            return
        for rec in buf.pending(room, after_id=self._cursor):
            values = []
            rows = json.loads(rec.body)
            for name, value in rows:
                d = SAMPLE_METRIC if name == "Sample" else self._defs.get(name) or _EVENT_DEFS.get(name)
                if d is None or d.name not in self._device_aliases:
                    self.dropped_unknown += 1
                    continue
                values.append((d, value))
            if rows and rows[0][0] == "Sample":  # a sample (an event goes whole: it is news each time)
                values = self._exceptions(values, rec.t_ms)
            payload = encode(
                values,
                timestamp_ms=rec.t_ms,
                seq=self._next_seq(),
                historical=rec.id <= self._historical_upto,
                metric_timestamp_ms=rec.t_ms,
                aliases=self._device_aliases,
                names=False,
            )
            info = self._publish_raw("DDATA", self.spec.device_id, payload, qos=1)
            self._cursor = rec.id
            if info.rc != 0:  # not connected after all: on_disconnect follows
                return
            self._inflight[info.mid] = rec.id

    def _exceptions(self, values: list[tuple[MetricDef, Any]], t_ms: int) -> list[tuple[MetricDef, Any]]:
        """What of a sample goes out (report by exception): every metric when a full refresh is due
        (the first sample after a birth, `full_refresh_s` of sample time after the last refresh or
        more, a sample time before it, or a refresh period of 0), else `Sample` and the metrics that
        `moved` since the value last sent."""
        refresh_ms = self.spec.full_refresh_s * 1000.0
        sent = self._sent
        if sent is None or refresh_ms <= 0 or not 0 <= t_ms - self._full_t_ms < refresh_ms:
            self._sent = {d.name: v for d, v in values}
            self._full_t_ms = t_ms
            self.full_refreshes += 1
            return values
        out = [(d, v) for d, v in values if d.name == "Sample" or moved(d, v, sent.get(d.name, _MISSING))]
        for d, v in out:
            sent[d.name] = v
        self.exceptions += 1
        return out

    def _send_node(self) -> None:
        """An NDATA with the node's metrics that changed since the NBIRTH or the last NDATA (and
        `Model/result` whenever a command was answered since, even with the same text); none when
        nothing did."""
        answered, self._answered = self._answered, False
        sent = self._node_sent
        news = [
            (d, v)
            for d, v in self._node_metrics(birth=False)
            if (answered and d.name == "Model/result") or moved(d, v, sent.get(d.name, _MISSING))
        ]
        if not news:
            return
        for d, v in news:
            sent[d.name] = v
        now_ms = int(time.time() * 1000)
        self._publish_raw(
            "NDATA",
            None,
            encode(
                news,
                timestamp_ms=now_ms,
                seq=self._next_seq(),
                metric_timestamp_ms=now_ms,
                aliases=self._node_aliases,
                names=False,
            ),
            qos=0,
        )

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        """A command (NCMD/DCMD), or the primary host's STATE.

        Nothing in it is trusted before it is decoded and checked.
        """
        if msg.topic.startswith(f"{NAMESPACE}/STATE/"):
            self._host_state(msg.payload)
            return
        self.commands_seen += 1
        if len(msg.payload) > MAX_COMMAND_BYTES:
            self._answer({"result": "refused", "reason": f"command of {len(msg.payload)} bytes is too long"})
            return
        try:
            payload = decode(msg.payload)
        except SparkplugError as e:
            log.warning(
                "telemetry: a command on %s that is not Sparkplug B: %s",
                msg.topic,
                e,
                extra={"event": "telemetry_command_bad", "reason": str(e)},
            )
            self._answer({"result": "refused", "reason": f"not a Sparkplug B payload: {e}"})
            return
        # a command does each thing once, however many metrics ask for it, and what it cannot
        # use is said in one line: a peer cannot make compd log or work without bound. A metric
        # comes by name or (Sparkplug 3.0) by the alias the birth of that node or device gave it
        scope = None if msg.topic.split("/")[2] == "NCMD" else self.spec.device_id
        rebirth = modelled = False
        unknown: list[str] = []
        for m in payload.metrics:
            name = m.name
            if name is None and m.alias is not None:
                name = self.aliases.name(scope, m.alias)
            if name is None:
                unknown.append(f"alias {m.alias}" if m.alias is not None else "a metric with neither name nor alias")
            elif name == NODE_REBIRTH and m.value is True:
                rebirth = True
            elif name in MODEL_COMMANDS:
                if modelled:
                    unknown.append(name)  # one model (or shadow) per command
                    continue
                modelled = True
                request = str(payload.uuid or payload.timestamp_ms or "")
                # the datatype may be left out (Sparkplug 3.0: SHOULD NOT be sent in a CMD)
                if not isinstance(m.value, str) or m.datatype not in (DataType.String, DataType.Text, DataType.Unknown):
                    self._answer({"request": request, "result": "refused", "reason": f"{name} must be a String"})
                elif self.commands is None:
                    self._answer(
                        {
                            "request": request,
                            "result": "refused",
                            "reason": "this compd takes no remote models (telemetry.remote_models.allow)",
                        }
                    )
                else:
                    self._answer({"request": request, **self.commands(m.value, request, MODEL_COMMANDS[name])})
            else:
                unknown.append(name)
        if rebirth:
            log.info("telemetry: rebirth requested", extra={"event": "telemetry_rebirth"})
            self._birth_due = True
        if unknown:
            first = unknown[0][:80]
            log.warning(
                "telemetry: %d command metric(s) ignored (the first: %r)",
                len(unknown),
                first,
                extra={
                    "event": "telemetry_command_bad",
                    "reason": f"{len(unknown)} unknown or repeated metric(s), the first {first!r}",
                },
            )

    def _host_state(self, payload: bytes) -> None:
        """The primary host's STATE (Sparkplug 3.0: JSON {"online": bool, "timestamp": ms})."""
        try:
            state = json.loads(payload[:4096].decode("utf-8")) if payload else {}
        except (UnicodeDecodeError, ValueError):
            state = {}
        online = isinstance(state, dict) and state.get("online") is True
        if online == self._host_online:
            return
        self._host_online = online
        log.info(
            "telemetry: primary host %s %s",
            self.spec.primary_host_id,
            "online" if online else "offline",
            extra={"event": "telemetry_host", "online": online},
        )
        if not online:
            self._session = False  # data waits on disk until the host is back
            return
        self._session = True
        self._births(new_session=self._new_connection)

    def answer(self, result: dict[str, Any]) -> None:
        """Publish a command's late answer (a model applied after the reload it asked for)."""
        self._inbox.put(("answer", 0, result))

    def _answer(self, result: dict[str, Any]) -> None:
        self._result = json.dumps(result, ensure_ascii=False, sort_keys=True)
        self._node_dirty = True
        self._answered = True
        log.info(
            "telemetry: command answered: %s",
            self._result,
            extra={
                "event": "telemetry_command",
                **{k: v for k, v in result.items() if k in ("request", "result", "reason")},
            },
        )

    def _finish(self) -> None:
        """At stop: the inbox into the buffer, what can go out in DRAIN_S, the NDEATH, disconnect."""
        self._take_inbox()
        client = self._client
        if self._session:
            deadline = time.monotonic() + self._drain_s
            while self._session and time.monotonic() < deadline and (self._inflight or len(self.buffer or ())):
                self._send()
                client.loop(timeout=self.spec.poll_s)
            info = self._publish_raw("NDEATH", None, _death(self._bdseq), qos=1)
            deadline = time.monotonic() + 1.0
            while self._session and not info.is_published() and time.monotonic() < deadline:
                client.loop(timeout=self.spec.poll_s)
        self._connected = False
        self._session = False
        if client.is_connected():
            client.disconnect()
            client.loop(timeout=0.1)
        # the connection's socket, and paho's wake-up socket pair (else closed only when the
        # client is garbage-collected)
        client._reset_sockets()


_EVENT_DEFS = {d.name: d for d in EVENT_METRICS}


def _death(bdseq: int) -> bytes:
    """The NDEATH payload: the bdSeq of the connection it ends (the last will, and a clean stop)."""
    return encode([(MetricDef("bdSeq", DataType.UInt64), bdseq)], timestamp_ms=int(time.time() * 1000), seq=None)
