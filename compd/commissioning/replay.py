"""`compd replay`: a log's signals through model, guard and codec into the configured sink's virtual device.

The loop runs on simulated time, one cycle per log row (the clock jumps from row to
row, so a day of 1 Hz log is 86 400 cycles, not 43 million), and each row stands for the
time since the row before: the guard's slew, the codec's walk, the sink's update rate
and the device's scans, steps and ramps all follow that simulated time, not the number
of rows (a row after dt does what the daemon's cycles would have done in dt: the word
walks what the slew licensed, the PMC takes as many steps as `min_update_s` allows, each
two scans after the one before, the NC ramps toward K0 over dt; compd.io.device_time).
After each row the device has acted (the PMC two scans past its last write, the NC its
IPO cycles up to the row), and what it then reports as applied is what the report
counts: residual = logged error + applied correction. A config replays through its own
sink's device of the software PLC (FANUC PMC, Siemens NC data, PCI-1756 card), with that
device's resolution and limits; a bare model file through the FANUC PMC, and the report
says so.

The rows run stage by stage rather than cycle by cycle, with the cycle-by-cycle result
(`replay_log(..., per_row=True)` runs the loop itself, and the tests hold the two
equal): the guard's input checks are vectorised and run for real only on rows whose
inputs could fail them (and the first); the model is evaluated over the log at once
(`Model.predict`) up to the first such row and stepped row by row after it; the guard
(`Guard.update_rows`), the codec (`Encoder.update_rows`) and the sink
(`Sink.write_rows`) step row by row on plain floats, calling their cycle's methods on
the rows where more than the plain path happens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from compd.commissioning.plots import probe_matrix, trend_from_replay, write_trend
from compd.config import load_config, resolve_model
from compd.core.clock import SimClock
from compd.core.config import (
    MODEL_MAX_BYTES,
    MODEL_MAX_VALUES,
    AdaptConfig,
    CodecConfig,
    Document,
    GuardConfig,
    InhibitConfig,
    load_yaml,
)
from compd.core.errors import BadInput
from compd.core.probe import Probe
from compd.core.scoring import score_applied
from compd.cycle.pipeline import build_model, build_pipeline
from compd.io.modbus_client import ModbusClient
from compd.log import Log, read_log
from compd.models.base import Model, step_rows
from compd.sinks.base import Sink
from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink
from compd.sources.replay import ReplayConfig, ReplaySource

if TYPE_CHECKING:
    from compd.cycle.loop import Loop

# the model classes whose `predict` over a log equals stepping `evaluate` row by row
# from its first row (tests/commissioning/test_replay.py checks each on a day of its machine); others
# (a kind from another package) are stepped. A model with linear terms is stepped too:
# the Siemens sink sends the terms of the row it writes, and feed_axis's `predict` gives
# the error at each row's position, not at P0.
REACH_S = 10.0  # a device over the network reads back what it holds within this, or nothing is replayed
BATCH_MODELS = frozenset(
    {
        "compd.models.ar1.AR1",
        "compd.models.xi_spindle.XiSpindle",
        "compd.models.lvr.LVR",
        "compd.models.mlr.MLR",
        "compd.models.feed_axis.FeedAxis",
    }
)


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


@dataclass
class _Rows:
    """What each row of a replay leaves (rows × the model's outputs unless said otherwise)."""

    pred: np.ndarray  # the model's prediction
    corr: np.ndarray  # the guard's correction
    enable: np.ndarray  # the guard's enable flags
    state: np.ndarray  # the guard's axis states
    words: np.ndarray  # rows: the word
    applied: np.ndarray  # what the device applied (0 off the word)
    commanded: np.ndarray  # what the device was commanded (NaN off the word)
    parts: np.ndarray  # rows × (contribution, axis) pairs: each contribution's share (a sum of contributions)

    @classmethod
    def empty(cls, n: int, n_out: int, n_parts: int = 0) -> _Rows:
        return cls(
            np.zeros((n, n_out)),
            np.zeros((n, n_out)),
            np.zeros((n, n_out), dtype=bool),
            np.zeros((n, n_out), dtype=np.uint8),
            np.zeros(n, dtype=np.int64),
            np.zeros((n, n_out)),
            np.full((n, n_out), np.nan),
            np.full((n, n_parts), np.nan),
        )


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
    per_row: bool = False,
) -> ReplayResult:
    """Run every row of `log` through model → guard → codec → sink (the PLC).

    A log with `probe_<axis>_um` columns hands each probe to the adapter at its row, as a
    running daemon's probe source would (`adapt_cfg`, or the defaults when the config has
    none); the report then also gives each axis `without_adaptation`: the same replay with
    the probes ignored (the model alone). With `inhibit_cfg` the log's inhibit and
    referenced columns hold the axes off as they held the machine's. `per_row`: run the
    loop cycle by cycle (the reference the staged run equals)."""
    if len(log) == 0:
        raise BadInput("the log has no rows", file=log.file)
    probes = probe_columns(log, list(model.outputs)) if use_probes else {}
    if probes and adapt_cfg is None:
        adapt_cfg = AdaptConfig()
    plain = None
    if probes:  # the model alone, on a fresh sink of the same kind: the report's without_adaptation
        fresh = type(sink)(sink.cfg, sink.base_dir)
        plain = replay_log(
            log,
            copy_model(model),
            fresh,
            guard_cfg,
            codec_cfg,
            None,
            use_probes=False,
            inhibit_cfg=inhibit_cfg,
            per_row=per_row,
        )
    source = ReplaySource(ReplayConfig(kind="replay", name="log", path=log.file), log=log)
    clock = SimClock(float(log.t_s[0]))
    try:
        loop = build_pipeline(
            sources=[source],
            model=model,
            sink=sink,
            clock=clock,
            period_s=1.0,
            guard_cfg=guard_cfg,
            codec_cfg=codec_cfg,
            adapt_cfg=adapt_cfg if probes else None,
            inhibit_cfg=inhibit_cfg,
        ).loop
    except BadInput as e:
        raise BadInput(e.message, file=log.file, path=e.keys) from None
    # a row stands for the daemon's many cycles in the time since the row before: the word
    # may walk what the slew licensed in that time, not one LSB per row
    loop.encoder.set_slew([float(loop.guard.slew_um_per_s[a]) for a in loop.word_axes], math.inf)
    n, n_out = len(log), len(model.outputs)
    parts = list(model.part_names)
    rows = _Rows.empty(n, n_out, len(parts))
    t = log.t_s
    loop.open()
    try:
        # what the device holds before the first row (a PMC over the network may hold a correction)
        if not loop.sink.await_held(REACH_S):
            raise BadInput(f"{loop.sink.device_info()['device']} does not answer: nothing replayed", file=log.file)
        loop.sync_output(float(t[0]))
        if per_row:
            _run_cycles(loop, clock, probes, log, rows)
        else:
            _run_stages(loop, source, log, probes, rows)
        sink_status = sink.get_status()
    finally:
        loop.close()
    words = rows.words
    codes_sent = int(np.count_nonzero(np.diff(words, prepend=0)))
    err = np.full((n, n_out), np.nan)
    axes_rep: dict[str, Any] = {}
    for a, axis in enumerate(model.outputs):
        col = f"err_{axis}_um"
        if col in log.columns:
            err[:, a] = log.col(col)
            axes_rep[axis] = score_applied(err[:, a], rows.applied[:, a])
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
    for k, (name, axis) in enumerate(parts):
        report.setdefault("contributions", {}).setdefault(axis, {})[name] = _contribution_report(
            rows.parts[:, k], err[:, model.outputs.index(axis)], loop.guard.faults, f"{axis}/{name}"
        )
    extra = {
        "pred_um": rows.pred,
        "corr_um": rows.corr,
        "guard_state": rows.state,
        "lsb_um": loop.encoder.lsb_um,
        "commanded_um": rows.commanded,
        "enable": rows.enable,
        "word_axes": [model.outputs[a] for a in loop.word_axes],
        "signals": {name: log.col(name) for name in model.inputs if name in log.columns},
        "log": log.file,
        "parts": [(name, axis, rows.parts[:, k]) for k, (name, axis) in enumerate(parts)],
    }
    if probes:
        extra["probe_um"] = probe_matrix(log, list(model.outputs))
    return ReplayResult(report, np.asarray(t, float), list(model.outputs), err, rows.applied, words, extra)


def _contribution_report(share: np.ndarray, err: np.ndarray, faults: dict[str, int], subject: str) -> dict[str, Any]:
    """One contribution's part of a replay: its share of the axis's prediction (RMS, largest, last; µm) and,
    where the log has the error, what it alone would leave (RMS of error − share)."""
    fin = share[np.isfinite(share)]
    out: dict[str, Any] = {
        "rms_um": float(np.sqrt(np.mean(fin**2))) if fin.size else None,
        "max_abs_um": float(np.max(np.abs(fin))) if fin.size else None,
        "final_um": float(share[-1]) if np.isfinite(share[-1]) else None,
        "rows_without": int(share.size - fin.size),
    }
    both = np.isfinite(err) & np.isfinite(share)
    if both.any():
        out["alone_residual_rms_um"] = float(np.sqrt(np.mean((err[both] - share[both]) ** 2)))
    return out


def shadow_report(log: Log, shadow: Model, axes: list[str], active_um: np.ndarray) -> dict[str, Any]:
    """The shadow model over the log (it drives nothing: evaluated over the log at once, rows whose
    inputs are not all finite left out) scored against the active model's prediction on the same
    measurements: the log's error `err_<axis>_um` on every row where it and both predictions are
    finite, and its probes `probe_<axis>_um` (RMS of measured − predicted, µm). `_pred`: the
    shadow's prediction per active axis (NaN where it serves none), for the caller."""
    n = len(log)
    X = log.matrix(shadow.inputs) if shadow.inputs else np.zeros((n, 0))
    t = np.asarray(log.t_s, dtype=float)
    pred = np.full((n, len(axes)), np.nan)
    ok = np.isfinite(X).all(axis=1)
    if ok.any():
        own = shadow.predict(X[ok], t[ok])
        for j, axis in enumerate(shadow.outputs):
            pred[ok, axes.index(axis)] = own[:, j]
    per_axis: dict[str, Any] = {}
    for axis in shadow.outputs:
        a = axes.index(axis)
        entry: dict[str, Any] = {}
        for what, col in (("error", f"err_{axis}_um"), ("probes", f"probe_{axis}_um")):
            if col not in log.columns:
                continue
            e = log.col(col)
            use = np.isfinite(e) & np.isfinite(pred[:, a]) & np.isfinite(active_um[:, a])
            k = int(use.sum())
            entry[what] = {
                "rows": k,
                "active_rms_um": float(np.sqrt(np.mean((e[use] - active_um[use, a]) ** 2))) if k else None,
                "shadow_rms_um": float(np.sqrt(np.mean((e[use] - pred[use, a]) ** 2))) if k else None,
            }
        per_axis[axis] = entry
    fit = shadow.fit_info
    return {
        "model": {"kind": shadow.kind, "file": shadow.file, "fitted_at": fit.get("fitted_at")},
        "axes": per_axis,
        "_pred": pred,
    }


def _log_probes(loop: Loop, probes: dict[str, tuple[np.ndarray, np.ndarray | None]], i: int, now: float) -> None:
    """Row i's probes into the adapter's inbox, as a probe source hands them over."""
    assert loop.adapter is not None
    for axis, (z, pos) in probes.items():
        if math.isfinite(z[i]):
            loop.adapter.inbox.append(
                Probe(now, axis, float(z[i]), None, None if pos is None else float(pos[i]), "log")
            )


def positions_mm(log: Log, axes: list[str]) -> np.ndarray | None:
    """Where each axis stood at each row (the log's pos_<axis>_mm; NaN for an axis without one),
    rows × axes; None when the log has no position of any of them."""
    cols = [f"pos_{a}_mm" for a in axes]
    if not any(c in log.columns for c in cols):
        return None
    return np.column_stack([log.col(c) if c in log.columns else np.full(len(log), np.nan) for c in cols])


def _run_cycles(
    loop: Loop, clock: SimClock, probes: dict[str, tuple[np.ndarray, np.ndarray | None]], log: Log, rows: _Rows
) -> None:
    """The reference: the loop's own cycle at every row, then the device given its time to act."""
    sink = loop.sink
    commanded = np.zeros(2)
    wa = loop.word_axes
    where = positions_mm(log, list(loop.model.outputs))
    for i, now in enumerate(log.t_s.tolist()):
        clock.set(now)
        if loop.adapter is not None:
            _log_probes(loop, probes, i, now)
        if where is not None:  # the device knows where its axes stand, as on the machine
            sink.set_positions(where[i])
        loop.step(now)
        sink.settle(now)
        rows.applied[i] = loop.applied()
        sink.commanded_um(commanded)
        for slot, axis in enumerate(wa):
            rows.commanded[i, axis] = commanded[slot]
        rows.pred[i] = loop.pred_um
        if rows.parts.shape[1]:
            rows.parts[i] = loop.model.part_um
        rows.corr[i] = loop.guard.out_um
        rows.enable[i] = loop.guard.enable
        rows.state[i] = loop.guard.state
        rows.words[i] = loop.word


def _run_stages(
    loop: Loop, source: ReplaySource, log: Log, probes: dict[str, tuple[np.ndarray, np.ndarray | None]], rows: _Rows
) -> None:
    """The replay stage by stage, each over every row, with `_run_cycles`'s result."""
    t = np.asarray(log.t_s, dtype=float)
    n = len(t)
    ok, degraded, hold, terms = _inputs_and_model(loop, source, log, rows.pred, rows.parts)
    guard = loop.guard
    dt = np.zeros(n)
    if loop.adapter is None:
        guard.update_rows(rows.pred, ok, t, degraded, hold, rows.corr, rows.enable, rows.state, dt)
    else:
        _adapt_and_guard(loop, log, probes, ok, degraded, hold, rows, dt, terms)
    wa = loop.word_axes
    changed = np.zeros(n, dtype=bool)
    c2 = rows.corr[:, wa[1]] if len(wa) == 2 else np.zeros(n)
    en2 = rows.enable[:, wa[1]] if len(wa) == 2 else np.zeros(n, dtype=bool)
    loop.encoder.update_rows(rows.corr[:, wa[0]], c2, rows.enable[:, wa[0]], en2, dt, rows.words, changed)
    loop.word = loop.encoder.word
    applied = np.zeros((n, 2))
    commanded = np.zeros((n, 2))
    loop.sink.write_rows(
        t,
        rows.words,
        changed,
        rows.corr,
        rows.enable,
        applied,
        commanded,
        terms,
        positions_mm(log, list(loop.model.outputs)),
    )
    for slot, axis in enumerate(wa):
        rows.applied[:, axis] = applied[:, slot]
        rows.commanded[:, axis] = commanded[:, slot]


def _inputs_and_model(
    loop: Loop, source: ReplaySource, log: Log, pred: np.ndarray, parts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, list[Any] | None]:
    """The read, check and model stages of every row: the prediction into `pred`; per row the
    guard's `inputs_ok` (the loop's ok, or degraded), the degraded flag, the hold reasons
    (None without an inhibit section) and the model's linear terms (None unless the sink
    sends them and the model has them)."""
    guard, model, frame, inhibit = loop.guard, loop.model, loop.frame, loop.inhibit
    t = np.asarray(log.t_s, dtype=float)
    tl = t.tolist()
    n, n_out = len(t), len(model.outputs)
    X = log.matrix(model.inputs) if model.inputs else np.zeros((n, 0))
    plain = guard.plain_rows(X, t)
    # the model's linear terms of every row: for a sink that sends them, and for the adapter (a
    # probe at position y is compared with the error the model predicts there)
    uses_terms = (loop.sink.sends_linear_terms or loop.adapter is not None) and model.linear_terms() is not None
    # rows [0, e) pass every check: the model is evaluated over them at once where that
    # equals stepping it (its `predict` leads the inputs as `run` does, compd.models.lead)
    batch = (
        bool(plain[0])
        and model.linear_terms() is None
        and (
            type(model).predict is Model.predict
            or f"{type(model).__module__}.{type(model).__qualname__}" in BATCH_MODELS
        )
    )
    e = (n if plain.all() else int(np.argmin(plain))) if batch else 0
    ok_rows = np.zeros(n, dtype=bool)
    deg_rows = np.zeros(n, dtype=bool)
    hold_rows = np.zeros((n, n_out), dtype=np.uint8) if inhibit is not None else None
    terms: list[Any] | None = [None] * n if uses_terms else None
    if e:  # what the loop's model stage leaves after row e − 1
        pred[:e] = model.predict(X[:e], t[:e])
        ok_rows[:e] = True
        loop.stage.started = True
        loop.pred_um[:] = pred[e - 1]
        ups = model.update_period_s
        if ups > 0:
            loop.stage.next_s = float(t[step_rows(t[:e], ups)[-1]]) + ups
    moved = None
    if inhibit is not None:  # its signals' rows: the hold reasons change only where they do
        S = log.matrix(inhibit_signals(inhibit.cfg))
        same = (S[1:] == S[:-1]) | (np.isnan(S[1:]) & np.isnan(S[:-1]))
        moved = np.r_[True, ~same.all(axis=1)].tolist()
    x = loop.x
    ok = False  # the last check passed every input
    framed_before = False  # the frame held the row before (its checks ran)
    for i in range(n):
        now = tl[i]
        if 0 < i < e and moved is None:
            framed_before = False
            continue  # checked, and modelled in the batch
        if i > 0 and plain[i] and ok:
            framed = False
        else:
            if i > 0 and not framed_before:  # the rows before passed without the guard
                guard.passed(X[i - 1], tl[i - 1])
            source.read(frame, now)
            ok = guard.check_inputs(frame, now)
            framed = True
        if i >= e:
            if now >= loop.stage.next_s:
                if framed:
                    np.take(frame.values, guard.input_idx, out=x)
                else:
                    np.copyto(x, X[i])
                loop.model_step(ok, now)
            pred[i] = loop.pred_um
            if parts.shape[1]:  # a sum of contributions (never batched): each one's share
                parts[i] = model.part_um
            ok_rows[i] = ok or loop.degraded
            deg_rows[i] = loop.degraded
            if terms is not None:
                terms[i] = model.linear_terms()
        if moved is not None and hold_rows is not None:
            if moved[i] or framed or framed_before:
                if not framed:
                    source.read(frame, now)
                inhibit.evaluate(frame, now, guard.hold)
            hold_rows[i] = guard.hold
        framed_before = framed
    if not framed_before:  # the guard as the last row left it
        guard.passed(X[n - 1], tl[n - 1])
    return ok_rows, deg_rows, hold_rows, terms


def _adapt_and_guard(
    loop: Loop,
    log: Log,
    probes: dict[str, tuple[np.ndarray, np.ndarray | None]],
    ok: np.ndarray,
    degraded: np.ndarray,
    hold: np.ndarray | None,
    rows: _Rows,
    dt: np.ndarray,
    terms: list[Any] | None,
) -> None:
    """With probes: the adapter and the guard, row by row as the loop runs them."""
    adapter, guard = loop.adapter, loop.guard
    assert adapter is not None
    values = log.matrix(loop.frame.names) if any(adapter.position_signal) else None
    pa = loop.pred_adapted_um
    for i, now in enumerate(log.t_s.tolist()):
        _log_probes(loop, probes, i, now)
        if values is not None:
            adapter.read_positions(values[i])
        # a probe from the log is the whole error (not residual): the adapter needs no applied correction
        adapter.apply(rows.pred[i], now, pa, None, terms[i] if terms is not None else None)
        if hold is not None:
            guard.hold[:] = hold[i]
        guard.update(pa, bool(ok[i]), now, degraded=bool(degraded[i]))
        adapter.record(rows.pred[i], guard.out_um)
        rows.corr[i] = guard.out_um
        rows.enable[i] = guard.enable
        rows.state[i] = guard.state
        dt[i] = guard.dt_s


def device_report(sink: Sink) -> dict[str, Any]:
    """The report's `device` (what was replayed against) and that device's resolution and limits."""
    info = sink.device_info()
    return {"device": info["device"], "device_limits": {k: v for k, v in info.items() if k != "device"}}


def copy_model(model: Model) -> Model:
    """A fresh model of the same kind and params (no state): for a second replay of the same log."""
    return type(model)(model.params, list(model.inputs), list(model.outputs), dict(model.fit_info))


def _pmc_sink(host: str | None = None) -> FanucPmcSink:
    return FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", host=host))


def inhibit_signals(cfg: InhibitConfig) -> list[str]:
    """Every signal the inhibit section names (inhibit and referenced)."""
    names = [cfg.signal] + [n for ax in cfg.axes.values() for n in (ax.signal, ax.referenced)]
    return [n for n in names if n is not None]


def _check_reachable(host: str, port: int, device_id: int, doc: Document) -> None:
    """BadInput naming `sink.host` when nothing answers there (a replay would wait on every row)."""
    client = ModbusClient.tcp(host, port, device_id=device_id, timeout_s=1.0)
    try:
        if not client.connect():
            raise doc.error(
                f"the PMC at {host}:{port} does not answer: start it, or drop host to replay"
                " against the PMC in process",
                ("sink", "host"),
            )
    finally:
        client.close()


def replay_config(config_file: str | Path, log_file: str | Path) -> ReplayResult:
    """Replay with a config's model, guard, codec and sink: the sink's own device of the
    software PLC in process (a fanuc_pmc that names a host: that PMC over Modbus TCP); the
    config's sources are replaced by the log."""
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
    result = replay_log(
        log, model, sink, cfg.guard, cfg.codec, cfg.top.adapt, inhibit_cfg=inhibit if use_inhibit else None
    )
    if cfg.shadow is not None:
        shadow = build_model(cfg.shadow)
        result.report["shadow"] = shadow_report(log, shadow, list(model.outputs), result.extra["pred_um"])
        result.extra["shadow_um"] = result.report["shadow"].pop("_pred")
    if held:
        result.report["inhibit"] = "from the log" if use_inhibit else "not in the log: never held off"
    host = sink.cfg.host if isinstance(sink, FanucPmcSink) else None
    result.report["plc"] = f"{host}:{sink.cfg.port}" if host else "in_process"
    return result


def replay_model(model_file: str | Path, log_file: str | Path) -> ReplayResult:
    """Replay with a model file, the default guard and codec and the PMC in process."""
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
    """The replay's trend (compd.commissioning.plots): inputs, per axis error without and with compensation,
    commanded (the word decoded) and applied correction in µm, enable and fault bands."""
    write_trend(trend_from_replay(result), path)
