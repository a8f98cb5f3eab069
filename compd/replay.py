"""`compd replay`: a log's signals through model, guard and codec into the configured sink's virtual device.

The loop runs on simulated time, one cycle per log row (the clock jumps from row to
row, so a day of 1 Hz log is 86 400 cycles, not 43 million); the guard's slew limit,
the sink's update rate and the PMC's scans all follow that simulated time. After
each cycle the device is given time to act (the PMC two scans, the NC its IPO
cycles), and what it then reports as applied is what the report counts: residual =
logged error + applied correction. A config replays through its own sink's device of
the software PLC (FANUC PMC, Siemens NC data, PCI-1756 card), with that device's
resolution and limits; a bare model file through the FANUC PMC, and the report says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from compd.adapt import Probe
from compd.clock import SimClock
from compd.config import AdaptConfig, CodecConfig, Document, GuardConfig, InhibitConfig
from compd.errors import BadInput
from compd.log import Log, read_log
from compd.models.base import Model
from compd.pipeline import build_model, build_pipeline
from compd.scoring import score_applied
from compd.sinks.base import Sink
from compd.sources.replay import ReplayConfig, ReplaySource

if TYPE_CHECKING:
    from compd.sinks.fanuc_pmc import FanucPmcSink


@dataclass
class ReplayResult:
    """The report (docs/formats.md) plus the traces behind it (for plots and tests)."""

    report: dict[str, Any]
    t_s: np.ndarray
    axes: list[str]
    error_um: np.ndarray  # rows × axes, NaN where the log has no err_<axis>_um
    applied_um: np.ndarray  # rows × axes, what the PLC applied after each row
    word: np.ndarray  # rows
    extra: dict[str, Any] = field(default_factory=dict)


def probe_columns(log: Log, axes: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Per axis with a `probe_<axis>_um` column: (the probes, NaN between them; their positions or None)."""
    out = {}
    for axis in axes:
        col = f"probe_{axis}_um"
        if col in log.columns:
            pos = f"probe_pos_{axis}_mm"
            out[axis] = (log.col(col), log.col(pos) if pos in log.columns else None)
    return out


def replay_log(
    log: Log,
    model: Model,
    sink: Sink,
    guard_cfg: GuardConfig | None = None,
    codec_cfg: CodecConfig | None = None,
    adapt_cfg: AdaptConfig | None = None,
    use_probes: bool = True,
    inhibit_cfg: InhibitConfig | None = None,
) -> ReplayResult:
    """Run every row of `log` through model → guard → codec → sink (the PLC).

    A log with `probe_<axis>_um` columns hands each probe to the adapter at its row, as a
    running daemon's probe source would (`adapt_cfg`, or the defaults when the config has
    none); the report then also gives each axis `without_adaptation`: the same replay with
    the probes ignored (the model alone). With `inhibit_cfg` the log's inhibit and
    referenced columns hold the axes off as they held the machine's."""
    if len(log) == 0:
        raise BadInput("the log has no rows", file=log.file)
    probes = probe_columns(log, list(model.outputs)) if use_probes else {}
    if probes and adapt_cfg is None:
        adapt_cfg = AdaptConfig()
    plain = None
    if probes:  # the model alone, on a fresh sink of the same kind: the report's without_adaptation
        fresh = type(sink)(sink.cfg, sink.base_dir)
        plain = replay_log(log, copy_model(model), fresh, guard_cfg, codec_cfg, None, use_probes=False,
                           inhibit_cfg=inhibit_cfg)
    source = ReplaySource(ReplayConfig(kind="replay", name="log", path=log.file), log=log)
    clock = SimClock(float(log.t_s[0]))
    try:
        loop = build_pipeline(
            sources=[source], model=model, sink=sink, clock=clock, period_s=1.0,
            guard_cfg=guard_cfg, codec_cfg=codec_cfg, adapt_cfg=adapt_cfg if probes else None,
            inhibit_cfg=inhibit_cfg,
        ).loop
    except BadInput as e:
        raise BadInput(e.message, file=log.file, path=e.keys) from None
    n, n_out = len(log), len(model.outputs)
    applied = np.zeros((n, n_out))
    pred = np.zeros((n, n_out))
    corr = np.zeros((n, n_out))
    state = np.zeros((n, n_out), dtype=np.uint8)
    words = np.zeros(n, dtype=np.int64)
    t = log.t_s
    codes_sent = 0
    prev_word = 0
    loop.open()
    try:
        inbox = loop.adapter.inbox if loop.adapter is not None else None
        for i in range(n):
            now = float(t[i])
            clock.set(now)
            if inbox is not None:
                for axis, (z, pos) in probes.items():
                    if math.isfinite(z[i]):
                        inbox.append(Probe(now, axis, float(z[i]), None,
                                           None if pos is None else float(pos[i]), "log"))
            loop.step(now)
            sink.settle(now)
            applied[i] = loop.applied()
            pred[i] = loop.pred_um
            corr[i] = loop.guard.out_um
            state[i] = loop.guard.state
            w = loop.word
            words[i] = w
            if w != prev_word:
                codes_sent += 1
                prev_word = w
        sink_status = sink.get_status()
    finally:
        loop.close()
    err = np.full((n, n_out), np.nan)
    axes_rep: dict[str, Any] = {}
    for a, axis in enumerate(model.outputs):
        col = f"err_{axis}_um"
        if col in log.columns:
            err[:, a] = log.col(col)
            axes_rep[axis] = score_applied(err[:, a], applied[:, a])
    faults = dict(loop.guard.faults)
    alarms = sink_status.get("alarm_count")
    if alarms and sum(alarms):
        faults["plc_alarm"] = int(sum(alarms))
    if plain is not None:
        for axis, rep in axes_rep.items():
            base = plain.report["axes"].get(axis)
            if base is not None:
                rep["without_adaptation"] = {k: base[k] for k in ("rms_after_um", "reduction_pct")}
        events = list(loop.adapter.events) if loop.adapter is not None else []
        adaptation = {
            "probes": {a: int(np.isfinite(z).sum()) for a, (z, _) in probes.items()},
            "accepted": sum(e["event"] == "accepted" for e in events),
            "rejected": sum(e["event"] == "rejected" for e in events),
            "faults": sum(e["event"] == "fault" for e in events),
            "estimate": loop.adapter.get_status() if loop.adapter is not None else {},
        }
    report = {
        "rows": n,
        "codes_sent": codes_sent,
        "axes": axes_rep,
        "saturated": int(loop.encoder.saturations),
        "faults": faults,
        "plc": sink.cfg.kind,
        "duration_s": float(t[-1] - t[0]),
        **device_report(sink),
    }
    if probes:
        report["adaptation"] = adaptation
    extra = {
        "pred_um": pred, "corr_um": corr, "guard_state": state, "lsb_um": loop.encoder.lsb_um,
        "word_axes": [model.outputs[a] for a in loop.word_axes],
        "signals": {name: log.col(name) for name in model.inputs if name in log.columns},
        "log": log.file,
    }
    if probes:
        from compd.plots import probe_matrix

        extra["probe_um"] = probe_matrix(log, list(model.outputs))
    return ReplayResult(report, np.asarray(t, float), list(model.outputs), err, applied, words, extra)


def device_report(sink: Sink) -> dict[str, Any]:
    """The report's `device` (what was replayed against) and that device's resolution and limits."""
    info = sink.device_info()
    return {"device": info["device"], "device_limits": {k: v for k, v in info.items() if k != "device"}}


def copy_model(model: Model) -> Model:
    """A fresh model of the same kind and params (no state): for a second replay of the same log."""
    return type(model)(model.params, list(model.inputs), list(model.outputs), dict(model.fit_info))


def _pmc_sink(host: str | None = None) -> FanucPmcSink:
    from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink

    return FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", host=host))


def inhibit_signals(cfg: InhibitConfig) -> list[str]:
    """Every signal the inhibit section names (inhibit and referenced)."""
    names = [cfg.signal] + [n for ax in cfg.axes.values() for n in (ax.signal, ax.referenced)]
    return [n for n in names if n is not None]


def _check_reachable(host: str, port: int, device_id: int, doc: Document) -> None:
    """BadInput naming `sink.host` when nothing answers there (a replay would wait on every row)."""
    from compd.io.modbus_client import ModbusClient

    client = ModbusClient.tcp(host, port, device_id=device_id, timeout_s=1.0)
    try:
        if not client.connect():
            raise doc.error(f"the PMC at {host}:{port} does not answer: start it, or drop host to replay"
                            " against the PMC in process", ("sink", "host"))
    finally:
        client.close()


def replay_config(config_file: str | Path, log_file: str | Path) -> ReplayResult:
    """Replay with a config's model, guard, codec and sink: the sink's own device of the
    software PLC in process (a fanuc_pmc that names a host: that PMC over Modbus TCP); the
    config's sources are replaced by the log."""
    from compd.config import load_config
    from compd.sinks.fanuc_pmc import FanucPmcSink

    cfg = load_config(config_file)
    log = read_log(log_file, allow_nan=True)
    model = build_model(cfg.model)
    sink_cls, sink_cfg, _ = cfg.sink
    if sink_cls is not FanucPmcSink:  # the sink's own device, in process
        sink_cfg = sink_cls.in_process_config(sink_cfg)
    elif sink_cfg.host is not None:  # a PMC over Modbus TCP: it answers, or the replay does not start
        _check_reachable(sink_cfg.host, sink_cfg.port, sink_cfg.device_id, cfg.doc)
    sink = sink_cls(sink_cfg, base_dir=str(Path(cfg.file).parent))
    inhibit = cfg.top.inhibit
    held = inhibit_signals(inhibit) if inhibit is not None else []
    use_inhibit = bool(held) and all(name in log.columns for name in held)
    result = replay_log(log, model, sink, cfg.guard, cfg.codec, cfg.top.adapt,
                        inhibit_cfg=inhibit if use_inhibit else None)
    if held:
        result.report["inhibit"] = "from the log" if use_inhibit else "not in the log: never held off"
    host = sink.cfg.host if isinstance(sink, FanucPmcSink) else None
    result.report["plc"] = f"{host}:{sink.cfg.port}" if host else "in_process"
    return result


def replay_model(model_file: str | Path, log_file: str | Path) -> ReplayResult:
    """Replay with a model file, the default guard and codec and the PMC in process."""
    from compd.config import MODEL_MAX_BYTES, MODEL_MAX_VALUES, load_yaml, resolve_model

    path = Path(model_file)
    doc = load_yaml(path, max_bytes=MODEL_MAX_BYTES, max_values=MODEL_MAX_VALUES)
    if not isinstance(doc.data, dict) or "kind" not in doc.data:
        raise BadInput("a model file is a mapping with kind, inputs, outputs, params", file=str(path))
    spec = resolve_model({"kind": doc.data["kind"], "file": path.name}, doc, (), path.parent)
    model = build_model(spec)
    if len(model.outputs) > 2:
        raise BadInput("the word carries two axes; replay a config that names codec.axes", file=str(path))
    log = read_log(log_file, allow_nan=True)
    result = replay_log(log, model, _pmc_sink())
    result.report["plc"] = "in_process"
    result.report["device"] += " (the default for a bare model file: replay a config for its own sink)"
    return result


def write_plot(result: ReplayResult, path: str | Path) -> None:
    """The replay's trend (compd.plots): inputs, per axis error without and with compensation,
    commanded (the word decoded) and applied correction in µm, enable and fault bands."""
    from compd.plots import trend_from_replay, write_trend

    write_trend(trend_from_replay(result), path)
