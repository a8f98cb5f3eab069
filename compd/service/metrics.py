"""Prometheus metrics on an opt-in HTTP endpoint (127.0.0.1 by default), via prometheus-client.

Nothing here runs in the cycle, nor in the cycle's process: the daemon binds the
endpoint, and the service (compd/daemon/host.py, a process of its own on the wall clock)
serves it and hands `MetricsServer.update_buckets` the latest snapshot (compd/service/status.py)
about once a second; a scrape renders the metric families from that snapshot. Metric names end
in their base unit (Prometheus: `_seconds`, `_meters`, `_celsius`, `_hertz`, …; a correction of
12 µm is 1.2e-05 meters), one family per unit; `promtool check metrics` passes on a scrape
(tests/service/test_promtool.py). Beside them: `compd_build_info`, the standard `process_*` metrics of
the process that serves the scrape (the service's), and `compd_process_*` for each of compd's
processes by name.
"""

from __future__ import annotations

import math
import platform
import re
import threading
from typing import Any

from compd import version
from compd.core.errors import BadInput
from compd.cycle.statusblock import (
    AXIS,
    BASE_UNITS,
    FIELDS,
    LOOP,
    LP,
    PART,
    PER_SIGNAL,
    SERVICE,
    SG,
    SIGNAL,
    SIGNAL_SERVICE,
    STALE,
    Field,
    instances,
    shown,
    signal_unit,
)
from compd.service.status import lateness_buckets
from compd.service.threads import ServiceThread

# cycle lateness histogram bounds, µs (a 2 ms cycle: "late" starts around 1000)
LATENESS_BOUNDS_US = (10.0, 25.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0, 10000.0)
UM = 1e-6  # µm → m

# a signal's unit (compd.cycle.statusblock.signal_unit) → its family: name, factor to the base unit, what it is
SIGNAL_FAMILIES: dict[str | None, tuple[str, float, str]] = {
    "°C": ("compd_signal_celsius", 1.0, "a temperature, °C"),
    "K": ("compd_signal_kelvin", 1.0, "a temperature difference, K"),
    "µm": ("compd_signal_meters", UM, "a length or error (µm in the signal's name, here in meters)"),
    "mm": ("compd_signal_meters", 1e-3, "a length or error (µm in the signal's name, here in meters)"),
    "rpm": ("compd_signal_hertz", 1.0 / 60.0, "a speed (rpm in the signal's name, here in revolutions per second)"),
    "Hz": ("compd_signal_hertz", 1.0, "a speed (rpm in the signal's name, here in revolutions per second)"),
    "s": ("compd_signal_seconds", 1.0, "a time"),
    "A": ("compd_signal_amperes", 1.0, "a current"),
    "V": ("compd_signal_volts", 1.0, "a voltage"),
    "%": ("compd_signal_ratio", 0.01, "a share (% in the signal's name, here 0 … 1)"),
    "bar": ("compd_signal_pascals", 1e5, "a pressure (bar in the signal's name, here in pascals)"),
    None: ("compd_signal_value", 1.0, "a signal whose name says no unit, as read"),
}
# the processes of compd whose CPU time and memory are exported (`compd_process_*`), by name
PROCESS_METRICS = (
    ("cpu_seconds", "counter", "CPU time (user and system) of compd's process"),
    ("resident_memory_bytes", "gauge", "Resident memory of compd's process"),
    ("start_time_seconds", "gauge", "Start time of compd's process since the Unix epoch"),
)


class SnapshotCollector:
    """A prometheus-client collector that renders the last snapshot it was given."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._snap: dict[str, Any] | None = None
        self._buckets: list[tuple[float, int]] = []
        self._count = 0
        self._sum_s = 0.0

    def update(self, snap: dict[str, Any], buckets: list[tuple[float, int]], count: int, sum_s: float) -> None:
        with self._lock:
            self._snap, self._buckets, self._count, self._sum_s = snap, buckets, count, sum_s

    def collect(self) -> Any:
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )

        with self._lock:
            snap, buckets, count, sum_s = self._snap, list(self._buckets), self._count, self._sum_s
        if snap is None:
            return
        lp = snap["loop"]
        yield HistogramMetricFamily(
            "compd_cycle_lateness_seconds",
            "Wake-up time minus deadline of each cycle",
            buckets=[(f"{b * 1e-6:g}", n) for b, n in buckets] + [("+Inf", count)],
            sum_value=sum_s,
        )
        mean = GaugeMetricFamily("compd_stage_mean_seconds", "Mean time of a loop stage", labels=["stage"])
        worst = GaugeMetricFamily("compd_stage_max_seconds", "Worst time of a loop stage", labels=["stage"])
        for stage, t in lp["stages"].items():
            mean.add_metric([stage], t["mean_us"] * 1e-6)
            worst.add_metric([stage], t["max_us"] * 1e-6)
        yield mean
        yield worst
        yield from record_families(snap)
        up = GaugeMetricFamily("compd_uptime_seconds", "Loop time since the first cycle")
        up.add_metric([], snap["uptime_s"] or 0.0)
        yield up
        obs = GaugeMetricFamily("compd_observe_mode", "1 when the output is held disabled (observe mode)")
        obs.add_metric([], 1.0 if snap["observe"] else 0.0)
        yield obs
        yield from _shadow_families(snap)
        link_up = GaugeMetricFamily("compd_sink_link_up", "1 when the sink reaches the machine (link up)")
        link_up.add_metric([], 1.0 if LP.link.read(snap) == "up" else 0.0)
        yield link_up
        pup = GaugeMetricFamily(
            "compd_process_up",
            "1 while compd's own process (a device worker, the service) runs; 0 while it is lost and not yet restarted",
            labels=["process"],
        )
        prs = CounterMetricFamily(
            "compd_process_restarts", "Restarts of compd's own process after it died or hung", labels=["process"]
        )
        for p in snap.get("processes") or []:
            pup.add_metric([p["name"]], 1.0 if p["up"] else 0.0)
            prs.add_metric([p["name"]], p["restarts"])
        yield from (pup, prs)
        yield from _process_families(snap)
        info = GaugeMetricFamily(
            "compd_build_info", "1, labelled with compd's version and Python's", labels=["version", "python"]
        )
        info.add_metric([version(), platform.python_version()], 1.0)
        yield info
        good = GaugeMetricFamily("compd_signal_good", "1 when the signal's quality is good", labels=["signal"])
        for at, s in instances(SG.quality.scope, snap):
            good.add_metric([at["signal"]], 1.0 if SG.quality.read(s) == "good" else 0.0)
        yield good
        faults = CounterMetricFamily("compd_faults", "Guard events by kind (event:reason)", labels=["kind"])
        for kind, n in sorted(snap["faults"].items()):
            faults.add_metric([kind], n)
        yield faults
        adapt = snap.get("adapt")
        if adapt:  # the probe-updated estimate (compd.cycle.adapt)
            off = GaugeMetricFamily("compd_adapt_offset_meters", "Probe-estimated offset per axis", labels=["axis"])
            sd = GaugeMetricFamily(
                "compd_adapt_offset_sigma_meters", "Standard deviation of the offset estimate", labels=["axis"]
            )
            acc = CounterMetricFamily(
                "compd_probes_accepted", "Probes accepted by the innovation gate", labels=["axis"]
            )
            rej = CounterMetricFamily(
                "compd_probes_rejected", "Probes rejected by the innovation gate", labels=["axis"]
            )
            slope = GaugeMetricFamily(
                "compd_adapt_slope_ratio", "Probe-estimated slope over the axis position (m per m)", labels=["axis"]
            )
            for axis, e in adapt.items():
                if e.get("slope_um_per_m") is not None:
                    slope.add_metric([axis], _f(e["slope_um_per_m"]) * UM)
                off.add_metric([axis], _f(e.get("offset_um")) * UM)
                sd.add_metric([axis], _f(e.get("offset_sigma_um")) * UM)
                acc.add_metric([axis], e.get("accepted", 0))
                rej.add_metric([axis], e.get("rejected", 0))
            yield from (off, sd, acc, rej, slope)


def _help(f: Field) -> str:
    """A field's meaning as a family's help: JSON's null is NaN here; a name's or a flag's family is 0 or 1."""
    text = re.sub(r"\bnull\b", "NaN", f.meaning)
    if f.kind == "name":
        return f"1 for the current {f.label or f.key}: {text}" + (
            f" ({STALE}: the cycle is stale)" if f.stale and STALE not in text else ""
        )
    if f.kind == "flag":
        return f"1 when {text}"
    return text[:1].upper() + text[1:]


def _sample(f: Field, value: Any) -> float:
    """A field's value (as status.json shows it) as a sample: in the base unit, a flag 0 or 1, NaN: none."""
    if f.kind == "flag":
        return math.nan if value is None else 1.0 if value else 0.0
    if isinstance(value, str) and (f.hex_digits or f.kind == "hex"):
        return float(int(value, 16))
    return _f(value) * BASE_UNITS.get(f.shown_unit, ("", 1.0))[1]


def record_families(snap: dict[str, Any]) -> list[Any]:
    """A family per field of the status record (compd/cycle/statusblock.py FIELDS) that Prometheus
    shows, named by its rule (`Field.metric_name`), labelled by its scope; a name field is one
    sample per name (1 for the current one), a signal's value is in the family of its unit
    (SIGNAL_FAMILIES). A family of a scope the snapshot has no instance of (no contributions, no
    shadow) is left out, the signals' families never."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    out: list[Any] = []
    for f in FIELDS:
        if not f.on("prometheus"):
            continue
        scope = f.scope
        assert scope is not None
        found = [(at, d) for at, d in instances(scope, snap) if shown(f, snap, at)]
        labels = list(scope.labels)
        if f.unit == PER_SIGNAL:
            fams = {}
            for fam, _, what in SIGNAL_FAMILIES.values():
                fams.setdefault(fam, GaugeMetricFamily(fam, f"Last value of a signal: {what}", labels=labels))
            for at, d in found:
                fam, factor, _ = SIGNAL_FAMILIES[signal_unit(at["signal"])]
                fams[fam].add_metric([at["signal"]], _f(f.read(d)) * factor)
            out += fams.values()
            continue
        if not found:
            continue
        cls = CounterMetricFamily if f.metric_kind() == "counter" else GaugeMetricFamily
        if f.kind == "name":
            fam = cls(f.metric_name(), _help(f), labels=[*labels, f.label or f.key])
        else:
            fam = cls(f.metric_name(), _help(f), labels=labels)
        for at, d in found:
            names = [at[k] for k in ("axis", "part", "signal") if k in at]
            value = f.exported(snap, d)
            if f.kind == "name":
                for name in (*(n for n in f.names if n is not None), *((STALE,) if f.stale else ())):
                    fam.add_metric([*names, name], 1.0 if value == name else 0.0)
            else:
                fam.add_metric(names, _sample(f, value))
        out.append(fam)
    return out


def _shadow_families(snap: dict[str, Any]) -> list[Any]:
    """A shadow model: the probes it was scored on, and what each model left (its prediction is a
    field of the record: `record_families`)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    shadow = snap.get("shadow")
    if not shadow:
        return []
    probes = CounterMetricFamily(
        "compd_shadow_probes", "Probes the active and the shadow model were scored on", labels=["axis"]
    )
    rms = GaugeMetricFamily(
        "compd_shadow_probe_rms_meters",
        "RMS over the probes of the measured error minus the model's prediction, for the active and the shadow model",
        labels=["axis", "model"],
    )
    for axis, sc in (shadow.get("axes") or {}).items():
        probes.add_metric([axis], sc.get("probes", 0))
        rms.add_metric([axis, "active"], _f(sc.get("active_rms_um")) * UM)
        rms.add_metric([axis, "shadow"], _f(sc.get("shadow_rms_um")) * UM)
    return [probes, rms]


def _process_families(snap: dict[str, Any]) -> list[Any]:
    """`compd_process_*{process}` for the cycle's process, the service's and each one the
    supervisor watches, read from /proc by prometheus-client's process collector (a process
    that is gone has no sample)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
    from prometheus_client.process_collector import ProcessCollector

    out = {
        key: (CounterMetricFamily if kind == "counter" else GaugeMetricFamily)(
            f"compd_process_{key}", doc, labels=["process"]
        )
        for key, kind, doc in PROCESS_METRICS
    }
    procs = [("cycle", snap.get("pid")), ("service", snap.get("service_pid"))]
    procs += [(p["name"], p["pid"]) for p in snap.get("processes") or [] if p.get("up") and p["name"] != "service"]
    for name, pid in procs:
        if not isinstance(pid, int) or pid <= 0:
            continue
        for fam in ProcessCollector(pid=lambda pid=pid: pid, registry=None).collect():
            key = fam.name.removeprefix("process_")
            if key in out and fam.samples:
                out[key].add_metric([name], fam.samples[0].value)
    return list(out.values())


def _f(value: Any) -> float:
    return float("nan") if value is None else float(value)


def _example(f: Field) -> Any:
    """A value of the field as status.json shows it (the catalogue's snapshot)."""
    if f.kind == "count":
        return f"0x{0:0{f.hex_digits}X}" if f.hex_digits else 1
    if f.kind == "flag":
        return True
    if f.kind == "name":
        return next(n for n in f.names if n is not None)
    return "0x00" if f.kind == "hex" else 0.0


def _put(where: dict[str, Any], f: Field) -> None:
    *path, last = f.at or (f.key,)
    for key in path:
        where = where.setdefault(key, {})
    where[last] = _example(f)


def example_snapshot() -> dict[str, Any]:
    """A snapshot that takes every branch of `SnapshotCollector.collect` (one axis with a contribution
    and a shadow, a signal of each unit's family, one fault kind, an adaptation estimate with a slope),
    every field of the status record in it (compd/cycle/statusblock.py FIELDS): what the catalogue is
    generated from."""
    snap: dict[str, Any] = {
        "loop": {"stages": {"model": {"mean_us": 1.0, "max_us": 1.0}}},
        "uptime_s": 1.0,
        "observe": False,
        "shadow": {"model": {"kind": "mlr"}, "axes": {"z": {"probes": 1, "active_rms_um": 1.0, "shadow_rms_um": 0.5}}},
        "processes": [{"name": "modbus-link-fanuc_pmc", "pid": 1, "up": True, "restarts": 0, "lost": None}],
        "faults": {"bad:stale": 1},
        "adapt": {"z": {"offset_um": 0.0, "offset_sigma_um": 1.0, "accepted": 0, "rejected": 0, "slope_um_per_m": 0.0}},
    }
    for f in (*LOOP, *SERVICE):
        _put(snap, f)
    axis = {f.key: _example(f) for f in AXIS}
    axis["contributions"] = {"spindle": {f.key: _example(f) for f in PART}}
    snap["axes"] = {"z": axis}
    snap["signals"] = {
        name: {f.key: _example(f) for f in (*SIGNAL, *SIGNAL_SERVICE)}  # one of each unit's family
        for name in (
            "T_xi",
            "T_rise_k",
            "err_z_um",
            "speed_rpm",
            "cycle_s",
            "current_a",
            "supply_v",
            "coolant_pct",
            "coolant_bar",
            "spindle_load",
        )
    }
    return snap


EXAMPLE_SNAPSHOT: dict[str, Any] = example_snapshot()

# a metric's unit from its name (Prometheus: the base unit ends the name); others by name
_UNIT_SUFFIXES = (
    ("_meters", "m"),
    ("_seconds", "s"),
    ("_celsius", "°C"),
    ("_kelvin", "K"),
    ("_hertz", "Hz"),
    ("_amperes", "A"),
    ("_volts", "V"),
    ("_pascals", "Pa"),
    ("_bytes", "bytes"),
    ("_ratio", "ratio"),
)
_UNITS = {
    "compd_word": "16-bit word (0 … 65535)",
    "compd_signal_value": "the signal's own (its name says none)",
    "compd_build_info": "1",
}
# the names before the base units (this release): old → new (no alias under an old name: promtool refuses them)
RENAMED = (
    ("compd_correction_micrometres", "compd_correction_meters"),
    ("compd_prediction_micrometres", "compd_prediction_meters"),
    ("compd_adapt_offset_micrometres", "compd_adapt_offset_meters"),
    ("compd_adapt_offset_sigma_micrometres", "compd_adapt_offset_sigma_meters"),
    ("compd_adapt_slope_micrometres_per_metre", "compd_adapt_slope_ratio"),
    (
        "compd_signal_value (every signal)",
        "compd_signal_celsius, _kelvin, _meters, _hertz, _seconds, _amperes, _volts,"
        " _ratio, _pascals by the unit the signal's name says; compd_signal_value for the others",
    ),
)


def families() -> list[Any]:
    """Every metric family compd exports (prometheus-client objects, from `EXAMPLE_SNAPSHOT`)."""
    c = SnapshotCollector()
    c.update(EXAMPLE_SNAPSHOT, [(b, 0) for b in LATENESS_BOUNDS_US], 0, 0.0)
    return list(c.collect())


def unit_of(family: Any) -> str:
    """The unit of a metric family, from its name (or a count, or 0/1)."""
    for suffix, unit in _UNIT_SUFFIXES:
        if family.name.endswith(suffix):
            return unit
    if family.name in _UNITS:
        return _UNITS[family.name]
    if family.type == "counter":
        return "count"
    if family.documentation.startswith("1 "):
        return "0 or 1"
    raise ValueError(f"metric {family.name}: no unit (name it with one, or add it to _UNITS)")


def sample_names(family: Any) -> list[str]:
    """The names a scrape shows for `family` (a counter's `_total`, a histogram's `_bucket`, …)."""
    return sorted({s.name for s in family.samples} | ({f"{family.name}_total"} if family.type == "counter" else set()))


def metrics_markdown() -> str:
    """docs/metrics.md: every metric compd exports, with its unit, labels and meaning."""
    lines = [
        "# Metrics",
        "",
        "<!-- generated by `compd docs --metrics --out docs/metrics.md` from compd/service/metrics.py: do not edit -->",
        "",
        "With `metrics: {enabled: true}` compd serves these on `http://127.0.0.1:9105/metrics`",
        "(Prometheus text format; `metrics.bind` and `metrics.port` change where). The service (a process",
        "of its own beside the cycle) updates them about once a second. The Grafana dashboard",
        "`contrib/grafana/compd.json` has a panel for each: import it (Dashboards, New, Import) and pick",
        "the Prometheus data source that scrapes compd; its `instance` variable selects the daemons.",
        "",
        "| metric (as scraped) | type | unit | labels | meaning |",
        "|---|---|---|---|---|",
    ]
    for fam in families():
        labels = sorted({k for smp in fam.samples for k in smp.labels if k != "le"})
        names = "<br>".join(f"`{n}`" for n in sample_names(fam))
        label_text = ", ".join(f"`{k}`" for k in labels) or "—"
        lines.append(f"| {names} | {fam.type} | {unit_of(fam)} | {label_text} | {fam.documentation} |")
    lines += [
        "",
        "The adaptation metrics (`compd_adapt_*`, `compd_probes_*`) are there only with an `adapt`",
        "section; `compd_adapt_slope_ratio` only for an axis that estimates a slope. A signal is in",
        "the family of the unit its name says (`T_…` and `…_c`: °C, `…_um`: µm as meters, `…_rpm`:",
        "revolutions per second, …; compd/cycle/statusblock.py `signal_unit`). The endpoint also",
        "serves prometheus-client's standard `process_*` metrics of the service's process.",
        "",
        "## Renamed to base units",
        "",
        "Metric names end in their base unit, as `promtool check metrics` asks; the old names are",
        "not served any more (promtool refuses them). Old → new:",
        "",
        "| old | new |",
        "|---|---|",
        *(f"| `{old}` | `{new}` |" if "(" not in old else f"| {old} | {new} |" for old, new in RENAMED),
        "",
    ]
    return "\n".join(lines)


def _make_server(bind: str, port: int, registry: Any, idle_timeout_s: float, max_connections: int) -> Any:
    """prometheus-client's WSGI app on the standard library's threading WSGI server, with
    what its own `start_http_server` lacks: a connection that sends nothing for
    `idle_timeout_s` is closed (its thread ends), and at most `max_connections` are
    served at once (more are closed at once), so idle or stuck clients can neither
    block a scrape nor pile up threads."""
    import socket
    from wsgiref.simple_server import WSGIRequestHandler, make_server

    from prometheus_client.exposition import ThreadingWSGIServer, make_wsgi_app

    slots = threading.BoundedSemaphore(max_connections)

    class Handler(WSGIRequestHandler):
        timeout = idle_timeout_s  # StreamRequestHandler: a socket timeout on every read

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
            pass  # no line per scrape

        def handle(self) -> None:
            try:
                super().handle()
            except (TimeoutError, OSError):
                self.close_connection = True

    class Server(ThreadingWSGIServer):
        address_family = socket.AF_INET6 if ":" in bind else socket.AF_INET
        request_queue_size = 128  # the listen backlog (socketserver's default is 5)

        def process_request(self, request: Any, client_address: Any) -> None:
            if not slots.acquire(blocking=False):
                self.shutdown_request(request)
                return
            try:
                super().process_request(request, client_address)
            except BaseException:
                slots.release()
                raise

        def process_request_thread(self, request: Any, client_address: Any) -> None:
            try:
                super().process_request_thread(request, client_address)
            finally:
                slots.release()

    return make_server(bind, port, make_wsgi_app(registry), Server, handler_class=Handler)


class MetricsServer:
    """The HTTP endpoint: `start` binds (BadInput if it cannot), `stop` shuts it down.

    Connections are served concurrently, one thread each; an idle one is closed after
    `idle_timeout_s`, and beyond `max_connections` new ones are closed at once.
    """

    def __init__(
        self,
        bind: str = "127.0.0.1",
        port: int = 9105,
        *,
        idle_timeout_s: float = 10.0,
        max_connections: int = 256,
    ) -> None:
        self.bind = bind
        self.port = port
        self.idle_timeout_s = idle_timeout_s
        self.max_connections = max_connections
        self.collector = SnapshotCollector()
        self._httpd: Any = None
        self._thread: ServiceThread | None = None

    def start(self) -> str:
        """Bind and serve /metrics here; returns its URL."""
        url = self.bind_socket()
        self.serve()
        return url

    def bind_socket(self) -> str:
        """Bind the endpoint (BadInput if it cannot) without serving it yet; returns its URL.
        The daemon binds, the service process serves (`serve`) the socket it inherits."""
        try:
            from prometheus_client import CollectorRegistry
        except ImportError:
            raise BadInput(
                "metrics.enabled needs prometheus-client: pip install 'compd[metrics]'", path="metrics.enabled"
            ) from None
        from prometheus_client.process_collector import ProcessCollector

        registry = CollectorRegistry(auto_describe=False)
        registry.register(self.collector)
        ProcessCollector(registry=registry)  # process_* of the process that serves the scrape: the service
        try:
            self._httpd = _make_server(self.bind, self.port, registry, self.idle_timeout_s, self.max_connections)
        except OSError as e:
            raise BadInput(
                f"cannot serve metrics on {self.bind}:{self.port}: {e.strerror or e}", path="metrics"
            ) from None
        self.port = self._httpd.server_address[1]
        host = f"[{self.bind}]" if ":" in self.bind else self.bind
        return f"http://{host}:{self.port}/metrics"

    def fileno(self) -> int | None:
        """The listening socket (a service process keeps it open), or None when not bound."""
        return self._httpd.fileno() if self._httpd is not None else None

    def serve(self) -> None:
        """Serve the bound socket from a thread of this process (once)."""
        if self._httpd is None or self._thread is not None:
            return
        self._thread = ServiceThread("compd-metrics", self._httpd.serve_forever, 0.1)  # poll_interval 0.1 s
        self._thread.start()

    def stop_serving(self) -> None:
        """End this process's serving thread; the socket stays bound (another takes over)."""
        if self._thread is not None:
            if self._httpd is not None:
                self._httpd.shutdown()
            self._thread.join(5.0)
            self._thread = None

    def update(self, snap: dict[str, Any], stats: Any) -> None:
        self.update_buckets(snap, lateness_buckets(stats, LATENESS_BOUNDS_US))

    def update_buckets(self, snap: dict[str, Any], buckets: tuple[list[tuple[float, int]], int, float]) -> None:
        """The newest snapshot and the loop's lateness buckets (compd.service.status.lateness_buckets)."""
        self.collector.update(snap, *buckets)

    def stop(self) -> None:
        """Stop serving and release the socket."""
        self.stop_serving()
        if self._httpd is not None:
            self._httpd.server_close()
            self._httpd = None
