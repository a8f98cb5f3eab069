"""The cycle's status as one fixed-layout record in shared memory, written every cycle under a seqlock; the service composes status.json from it.

The cycle's thread ends every cycle with `StatusBlock.write`: a few numbers per axis, per
signal and for the loop copied into arrays made before any fork, between two bumps of a
sequence number (odd while writing). No dict, no pickle, nothing that waits. The loop's
histograms and stage times live in shared memory of their own (compd.cycle.loop.TimingStats)
and are read beside the record.

The service (compd/daemon/host.py, a process of its own or a thread) takes a consistent
copy with `StatusBlock.read` whenever it wants one and `compose`s the status snapshot
(the dict written to status.json, exported as metrics, Sparkplug and OPC UA) from it
and a `Description`: what does not change every cycle (the model, the devices' own
accounts, the adapter, fault counts, the processes), which the cycle hands over
through the service's ring when it changes or once a status period.

Every number of the record is declared once below (`AXIS`, `SIGNAL`, `LOOP`): its key
in the status, unit and meaning; docs/status-fields.md is generated from these
(`python -m compd.cycle.statusblock`).

Relies on stores reaching the other CPU in program order (x86-64), like the mailboxes
of compd.io.mailbox; `compd.cycle.pipeline.check` refuses `loop.io: process` elsewhere.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from compd import version
from compd.core.frame import QUALITY_NAMES
from compd.cycle.inhibit import HOLD_NAMES
from compd.cycle.limiter import STATE_NAMES
from compd.io.histogram import bin_percentiles, over_range, range_limit_us
from compd.io.mailbox import READ_TRIES, shared_buffer
from compd.io.worker import LINK_STATES
from compd.sinks.observe import ObserveSink

# the status file's schema: its version (`schema`), where the packaged unit writes it, and when a record is stale
SCHEMA = 1
DEFAULT_PATH = "/run/compd/status.json"

STALE = "stale"  # the status's state when the cycle's record stopped moving (the record itself never says it)
# The cycle writes its record after every cycle. Unwritten for STALE_PERIODS loop periods, and at
# least STALE_MIN_S, it is stale: a running cycle on a busy 2-core host never pauses that long (160 ms
# at the most, measured at a load of 13: docs/reliability.md), a stopped one is seen within it.
STALE_PERIODS = 5.0
STALE_MIN_S = 1.0
# A reload stops the loop while it builds and opens the new pipeline (state `reloading`): its record
# is stale only past this, far above the longest reload measured (docs/reliability.md).
RELOAD_STALE_S = 60.0
# A turn of the service's loop this much later than its poll: the time between is not counted in the
# record's age (the service did not watch; on a host that busy the cycle may not have run either).
UNSEEN_S = 0.1

# the daemon's state, as its record names it (`reloading`: the loop paused while a reload builds the
# new pipeline); the status says `stale` instead when the record stopped moving (compd.service.status)
STATES = ("starting", "running", "stopping", "stopped", "reloading")


@dataclass(frozen=True)
class Field:
    """One number of the record: its key in the status, unit, meaning and how it is shown.

    `kind`: `number` (NaN → null), `count` (an integer), `flag` (true/false, NaN → null:
    not known), `name` (an index into `names`), `hex` (a byte, NaN → null)."""

    key: str
    unit: str
    meaning: str
    kind: str = "number"
    names: tuple[Any, ...] = ()  # a name per index (None: shown as null)


def _names(table: dict[int, Any]) -> tuple[Any, ...]:
    return tuple(table[i] for i in range(max(table) + 1))


AXIS: tuple[Field, ...] = (
    Field("prediction_um", "µm", "the model's prediction for the axis (null: no good input vector)"),
    Field("target_um", "µm", "what the guard steers to: the prediction (with the probes' offset), clamped"),
    Field("correction_um", "µm", "the correction the cycle commanded, after clamp and slew"),
    Field("commanded_um", "µm", "what the sink commands the device for the axis (the word decoded, the PMC's"
          " target, the NC's ramp target); null for an axis not in the word or a sink that cannot say"),
    Field("applied_um", "µm", "what the device acknowledged or reads back as applied; null when not known"
          " (no read-back, or the sink's link not up)"),
    Field("guard_enable", "", "the guard's enable bit for the axis", "flag"),
    Field("enable", "", "the machine has the axis enabled: the guard's bit in a word that reaches it; false in"
          " observe mode (the word at the machine is 0); null (not confirmed) while the sink's link is not up",
          "flag"),
    Field("state", "", "the guard's state of the axis", "name", _names(STATE_NAMES)),
    Field("inhibit", "", "why the machine holds the axis off (compd.cycle.inhibit)", "name", _names(HOLD_NAMES)),
    Field("saturated", "", "the correction is held at a limit: the guard's clamp (max_abs_um; the model asks for"
          " more) or the codec's range (the word byte's 63 LSB)", "flag"),
    Field("byte", "", "the axis's byte of the computed word (null: the axis is not in the word)", "hex"),
    Field("shadow_um", "µm", "the shadow model's prediction for the axis (the correction it would command is its"
          " negative; it drives nothing); null without a shadow on the axis, or without a good input vector"),
)
PART: tuple[Field, ...] = (
    Field("prediction_um", "µm", "what the contribution adds to its axis's prediction: its model's, after its own"
          " clamp, slew and fault policy (null: under `disable` with an input bad)"),
    Field("raw_um", "µm", "the contribution's model's own prediction (null: an input bad and the model cannot"
          " predict from the others)"),
    Field("state", "", "the contribution's state on the axis (its own fault policy)", "name", _names(STATE_NAMES)),
    Field("clamped", "", "the contribution's prediction is held at its own clamp", "flag"),
)
SIGNAL: tuple[Field, ...] = (
    Field("value", "signal unit", "the newest value the cycle read (°C for a PT100, rpm, µm, …)"),
    Field("quality", "", "the value's quality", "name", _names(QUALITY_NAMES)),
    Field("stamp_s", "s", "loop time at which the value was sampled at its source (`age_s` = loop time − this)"),
)
LOOP: tuple[Field, ...] = (
    Field("state", "", f"the daemon's state; the status says `{STALE}` instead when the cycle has not written this"
          " record for `stale_after_s` (a cycle stopped or hung: nothing it shows is live)", "name", STATES),
    Field("loop_time_s", "s", "loop time of the last cycle"),
    Field("t_start_s", "s", "loop time of the first cycle"),
    Field("cycles", "", "cycles run", "count"),
    Field("misses", "", "late cycles (more than half a period late, or done past the next deadline)", "count"),
    Field("skipped", "", "deadlines skipped when far behind", "count"),
    Field("late_max_s", "s", "the latest a cycle started"),
    Field("compute_max_ns", "ns", "the longest a cycle's work took", "count"),
    Field("between_max_s", "s", "the longest the work between two cycles took"),
    Field("between_overruns", "", "times the work between cycles ended past the next deadline", "count"),
    Field("gc_runs", "", "young-generation collections between cycles", "count"),
    Field("word", "", "the word the loop computed", "count"),
    Field("link", "", "whether what the sink writes reaches the machine", "name", LINK_STATES),
    Field("sink_writes", "", "writes the sink made", "count"),
    Field("saturations", "", "words with a clamped axis byte", "count"),
    Field("degraded", "", "the model runs on a reduced set of inputs", "flag"),
    Field("rows_dropped", "", "data-log rows the service's ring had no room for", "count"),
    Field("messages_dropped", "", "messages to the service its ring had no room for", "count"),
    Field("write_max_ns", "ns", "the longest this record's write took", "count"),
)

# What the service adds beside the record (the top level of the status): how old the record is.
SERVICE: tuple[Field, ...] = (
    Field("record_age_s", "s", "how long (monotonic time, as the service sees it every 20 ms) since the cycle last"
          f" wrote this record; a time the service itself did not run (a turn over {UNSEEN_S:g} s late) is not counted"),
    Field("stale_after_s", "s", f"the age past which the status says `{STALE}`: {STALE_PERIODS:g} loop periods and at"
          f" least {STALE_MIN_S:g} s while running, {RELOAD_STALE_S:g} s while reloading; null while stopping or"
          " stopped (the loop is not meant to run)"),
)


# a signal's unit, by the end of its name (compd's names carry their units; STYLE); T_… is °C
_SUFFIX_UNITS = (("_um", "µm"), ("_mm", "mm"), ("_rpm", "rpm"), ("_c", "°C"), ("_k", "K"), ("_s", "s"),
                 ("_a", "A"), ("_v", "V"), ("_pct", "%"), ("_bar", "bar"), ("_hz", "Hz"))


def signal_unit(name: str) -> str | None:
    """The unit a signal's name says (`err_z_um` → µm, `T_xi` → °C), or None."""
    low = name.lower()
    for suffix, unit in _SUFFIX_UNITS:
        if low.endswith(suffix):
            return unit
    return "°C" if name.startswith("T_") else None


def _index(fields: tuple[Field, ...]) -> dict[str, int]:
    return {f.key: i for i, f in enumerate(fields)}


A = _index(AXIS)
P = _index(PART)
S = _index(SIGNAL)
L = _index(LOOP)
_LINK = {name: i for i, name in enumerate(LINK_STATES)}
_HEAD = 2  # int64: sequence number (odd while a write is under way), writes


@dataclass
class Reading:
    """A consistent copy of the record (`StatusBlock.read`): loop fields, per-axis and
    per-signal fields (field-major), and the loop's histograms and stage times."""

    loop: np.ndarray
    axes: np.ndarray
    signals: np.ndarray
    parts: np.ndarray  # PART × the contributions' (name, axis) pairs (none for one model)
    hist: np.ndarray
    compute_hist: np.ndarray
    stages: np.ndarray  # (last, max, sum) × stage, ns

    def get(self, key: str) -> float:
        return float(self.loop[L[key]])


class StatusBlock:
    """The record of one pipeline (see the module); made before the service's fork."""

    def __init__(self, loop: Any) -> None:
        self.loop = loop
        n_axes, n_sig = len(loop.model.outputs), len(loop.frame.names)
        self.n_axes, self.n_signals = n_axes, n_sig
        model = loop.model
        n_parts = len(model.part_names)
        n = len(LOOP) + len(AXIS) * n_axes + len(SIGNAL) * n_sig + len(PART) * n_parts
        self._buf = shared_buffer(8 * (_HEAD + n))
        self._head = memoryview(self._buf).cast("q")[:_HEAD]
        data = np.frombuffer(self._buf, dtype=np.float64, offset=8 * _HEAD)
        self._loop = data[: len(LOOP)]
        self._lv = memoryview(self._buf)[8 * _HEAD: 8 * (_HEAD + len(LOOP))].cast("d")  # scalar stores: no numpy
        rest = data[len(LOOP):]
        self._axes = rest[: len(AXIS) * n_axes].reshape(len(AXIS), n_axes)
        rest = rest[len(AXIS) * n_axes:]
        self._signals = rest[: len(SIGNAL) * n_sig].reshape(len(SIGNAL), n_sig)
        self._parts = rest[len(SIGNAL) * n_sig:].reshape(len(PART), n_parts)
        self._parts[:] = math.nan
        self._axes[:] = math.nan
        self._signals[:] = math.nan
        self._loop[:] = 0.0
        self._slot_cmd = np.full(2, math.nan)
        self._slot_app = np.full(2, math.nan)
        self._slots = [(slot, axis) for slot, axis in enumerate(loop.word_axes)]
        self.state = "starting"
        self.rows_dropped = 0
        self.messages_dropped: Any = None  # a callable: the ring's dropped count

    @property
    def writes(self) -> int:
        return int(self._head[1])

    def write(self) -> None:
        """The cycle's state into the record (the cycle's thread, after every cycle)."""
        t0 = time.perf_counter_ns()
        lp = self.loop
        st = lp.stats
        g = lp.guard
        sink = lp.sink
        head = self._head
        head[0] += 1
        v = self._lv
        v[0] = STATES.index(self.state)
        v[1] = lp.now_s
        v[2] = lp.t_start_s
        v[3] = st.cycles
        v[4] = st.misses
        v[5] = st.skipped
        v[6] = st.late_max_s
        v[7] = st.compute_max_ns
        v[8] = st.between_max_s
        v[9] = st.between_overruns
        v[10] = st.gc_runs
        v[11] = lp.word
        v[12] = _LINK[sink.link_state()]
        v[13] = sink.writes
        v[14] = lp.encoder.saturations
        v[15] = 1.0 if g.degraded else 0.0
        v[16] = self.rows_dropped
        v[17] = self.messages_dropped() if self.messages_dropped is not None else 0
        ax = self._axes
        np.copyto(ax[0], lp.pred_um)
        np.copyto(ax[1], g.target_um)
        np.copyto(ax[2], g.out_um)
        np.copyto(ax[5], g.enable)
        np.copyto(ax[7], g.state)
        np.copyto(ax[8], g.hold)
        np.copyto(ax[9], g.clamped)
        if self._slots:
            cmd, app = self._slot_cmd, self._slot_app
            sink.commanded_um(cmd)
            sink.applied_um(app)
            sat = lp.encoder.saturated
            word = lp.word
            for slot, axis in self._slots:
                ax[3, axis] = cmd[slot]
                ax[4, axis] = app[slot]
                if sat[slot]:
                    ax[9, axis] = 1.0
                ax[10, axis] = (word >> 8) & 0xFF if slot == 0 else word & 0xFF
        if lp.shadow is not None:
            np.copyto(ax[11], lp.shadow.pred_um)
        fr = lp.frame
        sg = self._signals
        np.copyto(sg[0], fr.values)
        np.copyto(sg[1], fr.quality)
        np.copyto(sg[2], fr.stamp_s)
        cs = lp.model
        if cs.part_names:
            pt = self._parts
            np.copyto(pt[0], cs.part_um)
            np.copyto(pt[1], cs.part_raw_um)
            np.copyto(pt[2], cs.part_state)
            np.copyto(pt[3], cs.part_clamped)
        d = time.perf_counter_ns() - t0
        if d > v[18]:
            v[18] = d
        head[1] += 1
        head[0] += 1

    def read(self) -> Reading | None:
        """A consistent copy (None: the writer was always mid-write, or has never written)."""
        head, st = self._head, self.loop.stats
        for _ in range(READ_TRIES):
            seq = head[0]
            if seq & 1:
                continue
            r = Reading(self._loop.copy(), self._axes.copy(), self._signals.copy(), self._parts.copy(),
                        np.frombuffer(st.hist, dtype=np.int64).copy(),
                        np.frombuffer(st.compute_hist, dtype=np.int64).copy(),
                        np.vstack([np.frombuffer(a, dtype=np.int64) for a in
                                   (st.stage_last_ns, st.stage_max_ns, st.stage_sum_ns)]))
            if head[0] == seq:
                return r if seq else None
        return None


@dataclass
class Description:
    """What the status shows besides the record: fixed for a pipeline (`static`), and what
    the cycle hands over when it changes or once a status period (`devices`: sources, sink,
    adapter, faults, processes, threads), the model's state, the latest guard events."""

    static: dict[str, Any]
    model: dict[str, Any]
    devices: dict[str, Any] = field(default_factory=dict)
    events: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=20))

    def add_events(self, events: list[tuple[Any, ...]]) -> None:
        for t, subj, ev, why, *_ in events:
            self.events.append({"t_s": float(t), "subject": subj, "event": ev, "reason": why})


def describe_static(loop: Any, observe: bool) -> dict[str, Any]:
    """The parts of the status fixed for a pipeline (made where the pipeline is)."""
    slot_of = {axis: slot for slot, axis in enumerate(loop.word_axes)}
    return {
        "pid": os.getpid(),
        "version": version(),
        # observe mode: asked for, or the sink is the one that holds the word at 0
        "observe": bool(observe or isinstance(loop.sink, ObserveSink)),
        "period_s": float(loop.period_s),
        "axes": list(loop.model.outputs),
        "signals": list(loop.frame.names),
        "policy": [p.label for p in loop.guard.policy],
        "word_byte": [("high", "low")[slot_of[i]] if i in slot_of else None for i in range(len(loop.model.outputs))],
        # the (contribution, axis) pairs of a sum of contributions, in the record's order
        "parts": [list(p) for p in loop.model.part_names],
    }


def describe_devices(loop: Any, processes: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The slowly changing parts, from the pipeline's objects (the cycle's thread, between
    cycles; ≈ tens of µs: every device's status)."""
    return {
        "sources": [src.get_status() for src in loop.sources],
        "sink": loop.sink.get_status(),
        "adapt": loop.adapter.get_status() if loop.adapter is not None else None,
        "shadow": loop.shadow.get_status() if loop.shadow is not None else None,
        "faults": dict(loop.guard.faults),
        "processes": processes,
        # the threads of Python in the cycle's process (on the wall clock: the cycle's alone)
        "threads": sorted(t.name for t in threading.enumerate()),
    }


def describe(loop: Any, observe: bool) -> Description:
    """All of it at once, from the pipeline's objects (tests, a status taken in process)."""
    desc = Description(describe_static(loop, observe), loop.model.get_status(), describe_devices(loop))
    desc.add_events(list(loop.guard.events)[-20:])
    return desc


def _value(f: Field, x: float) -> Any:
    if math.isnan(x):
        return None
    if f.kind == "count":
        return int(x)
    if f.kind == "flag":
        return bool(x)
    if f.kind == "name":
        i = int(x)
        return f.names[i] if 0 <= i < len(f.names) else "?"
    if f.kind == "hex":
        return f"0x{int(x):02X}"
    return float(x)


def timing(r: Reading, period_s: float) -> dict[str, Any]:
    """The loop's timing figures (the names of the bench JSON) from a reading; a percentile
    in the histogram's overflow bin is named in `over_range` (its value is the range limit)."""
    p50, p99, p999 = bin_percentiles(r.hist, (0.5, 0.99, 0.999))
    c50, c99 = bin_percentiles(r.compute_hist, (0.5, 0.99))
    late = {"p50": p50, "p99": p99, "p999": p999, "max": round(r.get("late_max_s") * 1e6, 1)}
    compute = {"p50": c50, "p99": c99, "max": round(r.get("compute_max_ns") / 1000, 1)}
    limit = range_limit_us(r.hist)
    n = max(int(r.get("cycles")), 1)
    from compd.cycle.loop import STAGES

    stages = {name: {"last_us": int(r.stages[0, i]) / 1000, "mean_us": int(r.stages[2, i]) / n / 1000,
                     "max_us": int(r.stages[1, i]) / 1000} for i, name in enumerate(STAGES)}
    return {
        "period_ms": period_s * 1000.0,
        "cycles": int(r.get("cycles")),
        "misses": int(r.get("misses")),
        "skipped": int(r.get("skipped")),
        "lateness_us": late,
        "cycle_compute_us": compute,
        "over_range": {"lateness_us": over_range(late, limit), "cycle_compute_us": over_range(compute, limit)},
        "stages": stages,
    }


def compose(r: Reading, desc: Description) -> dict[str, Any]:
    """The status snapshot (status.json's shape, docs/formats.md) from a reading and a
    description: JSON values only (NaN → null)."""
    st = desc.static
    observe = st["observe"]
    dev = desc.devices
    link = _value(LOOP[L["link"]], r.get("link"))
    reaches = link == "up"
    word = int(r.get("word"))
    axes: dict[str, Any] = {}
    for i, name in enumerate(st["axes"]):
        a = {f.key: _value(f, float(r.axes[j, i])) for j, f in enumerate(AXIS)}
        a["policy"] = st["policy"][i]
        a["degraded"] = bool(r.get("degraded"))
        a["word_byte"] = st["word_byte"][i]
        if observe:
            a["enable"] = False  # the word at the machine is 0: every enable bit off
        elif not reaches:
            a["enable"] = None  # not confirmed at the machine
            a["applied_um"] = None
        else:
            a["enable"] = bool(a["guard_enable"])
        axes[name] = a
    for k, (part, axis) in enumerate(st.get("parts") or []):
        c = {f.key: _value(f, float(r.parts[j, k])) for j, f in enumerate(PART)}
        axes[axis].setdefault("contributions", {})[part] = c
    now = r.get("loop_time_s")
    signals = {}
    for i, name in enumerate(st["signals"]):
        s = {f.key: _value(f, float(r.signals[j, i])) for j, f in enumerate(SIGNAL)}
        stamp = float(r.signals[S["stamp_s"], i])
        s["age_s"] = None if not math.isfinite(now - stamp) else float(now - stamp)
        signals[name] = s
    sink = dict(dev.get("sink") or {})
    sink["link"] = link
    sink["writes"] = int(r.get("sink_writes"))
    if observe:
        sink["observe"] = True
        sink["word"] = "0x0000"
    cycles = int(r.get("cycles"))
    snap: dict[str, Any] = {
        "schema": SCHEMA,
        "version": st["version"],
        "pid": st["pid"],
        "state": _value(LOOP[L["state"]], r.get("state")),
        "observe": observe,
        "written_unix_s": time.time(),
        "uptime_s": now - r.get("t_start_s") if cycles else 0.0,
        "loop_time_s": now,
        "word": f"0x{word:04X}",  # the word the loop computed
        # what the sink writes; null: the link is not up, nothing is known at the machine
        "word_at_machine": ("0x0000" if observe else sink.get("word", f"0x{word:04X}")) if reaches else None,
        "axes": axes,
        "signals": signals,
        "loop": timing(r, st["period_s"]),
        "model": desc.model,
        "sink": sink,
        "sources": dev.get("sources") or [],
        "faults": dev.get("faults") or {},
        "saturations": int(r.get("saturations")),
        "events": list(desc.events),
        "threads": dev.get("threads") or [],
        "publisher": {"messages_dropped": int(r.get("messages_dropped")), "rows_dropped": int(r.get("rows_dropped")),
                      "status_write_max_us": round(r.get("write_max_ns") / 1000, 1),
                      "between_max_us": round(r.get("between_max_s") * 1e6, 1),
                      "between_overruns": int(r.get("between_overruns")),
                      **(dev.get("publisher") or {})},
    }
    if dev.get("adapt") is not None:
        snap["adapt"] = dev["adapt"]
    if dev.get("shadow") is not None:
        snap["shadow"] = dev["shadow"]
    if dev.get("processes") is not None:
        snap["processes"] = dev["processes"]
    return _jsonable(snap)


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def fields_markdown() -> str:
    """docs/status-fields.md: every number of the record, by group."""
    out = ["# Status fields", "",
           "Generated from compd/cycle/statusblock.py (`python -m compd.cycle.statusblock`): every number the cycle",
           "writes into its status record each cycle, and those the service adds beside it, under the key",
           "it has in status.json (docs/formats.md, \"Status file\"), with its unit and meaning. The same names",
           "reach the metrics, Sparkplug and OPC UA (docs/plant.md).", ""]
    for title, where, fields in (("Per axis", "`axes.<axis>`", AXIS),
                                 ("Per contribution (a sum of contributions only)",
                                  "`axes.<axis>.contributions.<name>`", PART),
                                 ("Per signal", "`signals.<name>`", SIGNAL),
                                 ("The loop", "the top level, `loop` and `publisher`", LOOP),
                                 ("The service's, beside the record", "the top level", SERVICE)):
        out += [f"## {title} ({where})", "", "| key | unit | kind | meaning |", "|---|---|---|---|"]
        for f in fields:
            kind = f"one of {', '.join('null' if n is None else f'`{n}`' for n in f.names)}" if f.kind == "name" else f.kind
            out.append(f"| `{f.key}` | {f.unit or '—'} | {kind} | {f.meaning} |")
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(fields_markdown())
