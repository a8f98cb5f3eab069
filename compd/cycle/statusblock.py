"""The cycle's status as one fixed-layout record in shared memory, written every cycle under a seqlock.

The service composes status.json from it.

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
of compd.io.mailbox; `compd.plant.spec.check_config` refuses `loop.io: process` elsewhere.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from collections import deque, namedtuple
from dataclasses import dataclass, field, replace
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


# the channels a field reaches besides status.json (compd.service.metrics, compd.plant.telemetry, compd.plant.opcua)
CHANNELS = ("prometheus", "sparkplug", "opcua")
KINDS = ("number", "count", "flag", "name", "hex")
PER_SIGNAL = "signal unit"  # a signal's value: the unit its name says (`signal_unit`)
# a field's unit → Prometheus's base unit (what the metric's name ends in) and the factor to it
BASE_UNITS: dict[str, tuple[str, float]] = {
    "µm": ("meters", 1e-6),
    "mm": ("meters", 1e-3),
    "s": ("seconds", 1.0),
    "ms": ("seconds", 1e-3),
    "µs": ("seconds", 1e-6),
    "ns": ("seconds", 1e-9),
    "°C": ("celsius", 1.0),
    "K": ("kelvin", 1.0),
}


@dataclass(frozen=True)
class Scope:
    """Where a group of fields stands in status.json and how each channel names its members:
    Prometheus's labels and the start of a family's name, Sparkplug's folder, OPC UA's folder
    (`{axis}`, `{part}`, `{signal}`: the instance's names; `{name}`: the field's own)."""

    name: str  # axis, contribution, signal, loop, service
    where: str  # in status.json (docs/status-fields.md)
    labels: tuple[str, ...]
    metric: str  # a number's family: compd_<this><stem>_<base unit>
    metric_other: str  # anything else's: compd_<this><key>
    sparkplug: str
    opcua: str


AXIS_SCOPE = Scope("axis", "`axes.<axis>`", ("axis",), "", "axis_", "Axis/{axis}/{name}", "compd.Axes.{axis}.{name}")
PART_SCOPE = Scope(
    "contribution",
    "`axes.<axis>.contributions.<name>`",
    ("axis", "contribution"),
    "contribution_",
    "contribution_",
    "Axis/{axis}/Contribution/{part}/{name}",
    "compd.Axes.{axis}.Contributions.{part}.{name}",
)
SIGNAL_SCOPE = Scope(
    "signal",
    "`signals.<name>`",
    ("signal",),
    "signal_",
    "signal_",
    "Signal/{signal}/{name}",
    "compd.Signals.{signal}.{name}",
)
LOOP_SCOPE = Scope(
    "loop", "the top level, `loop`, `sink` and `publisher`", (), "", "", "Loop/{name}", "compd.Loop.{name}"
)
SERVICE_SCOPE = Scope("service", "the top level", (), "", "", "{name}", "compd.{name}")


@dataclass(frozen=True)
class Field:
    """One number of the record: its key in the status, unit, meaning and how it is shown.

    `kind`: `number` (NaN → null), `count` (an integer), `flag` (true/false, NaN → null:
    not known), `name` (an index into `names`), `hex` (a byte, NaN → null).

    What every exporter shows of it is derived from these by rule (`metric_name`, `sparkplug_name`,
    `opcua_name`): a field declared once reaches Prometheus, Sparkplug and OPC UA with its unit and
    meaning. Where a channel's name is not the rule's (a name clients already know), `metric`,
    `sparkplug` or `opcua` says it; where a channel leaves the field out, `omit` says which and why.
    The group it is declared in (`_scoped`) sets `scope`."""

    key: str
    unit: str
    meaning: str
    kind: str = "number"
    names: tuple[Any, ...] = ()  # a name per index (None: shown as null)
    scope: Scope | None = None
    omit: tuple[tuple[str, str], ...] = ()  # (channel, why it leaves the field out)
    metric: str = ""  # the Prometheus family, when not the rule's
    label: str = ""  # a name's label on Prometheus (its key when empty)
    sparkplug: str = ""  # the Sparkplug metric (its scope's `{…}` filled), when not the rule's
    opcua: str = ""  # the OPC UA node (its scope's `{…}` filled), when not the rule's
    at: tuple[str, ...] = ()  # a loop or service field: where status.json shows it (empty: its key at the top)
    shown: str = ""  # ... in this unit (empty: `unit`)
    hex_digits: int = 0  # a count shown in status.json as 0x and this many hex digits (the word)
    metric_type: str = ""  # gauge or counter (empty: a count is a counter, anything else a gauge)
    stale: bool = False  # a state: the status says `stale` instead when the cycle's record is stale
    shadow_only: bool = False  # only on an axis that a shadow model predicts
    off_in_observe: bool = False  # false in observe mode, whatever the status says (the word at the machine is 0)

    def __post_init__(self) -> None:
        where = f"status field {self.key!r}"
        if not self.key.isidentifier():
            raise ValueError(f"{where}: a key is an identifier")
        if self.kind not in KINDS:
            raise ValueError(f"{where}: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        if self.kind == "name" and not self.names:
            raise ValueError(f"{where}: a name field needs its names")
        for unit in (self.unit, self.shown):
            if unit and unit != PER_SIGNAL and unit not in BASE_UNITS:
                raise ValueError(f"{where}: unit {unit!r} has no base unit (BASE_UNITS)")
        for channel, why in self.omit:
            if channel not in CHANNELS or not why:
                raise ValueError(f"{where}: omit {channel!r} needs one of {', '.join(CHANNELS)} and the reason")
        if self.metric_type not in ("", "gauge", "counter"):
            raise ValueError(f"{where}: metric_type {self.metric_type!r} is gauge or counter")

    def on(self, channel: str) -> bool:
        """Whether `channel` shows the field (CHANNELS; a misspelt one: ValueError)."""
        if channel not in CHANNELS:
            raise ValueError(f"no channel {channel!r}")
        return all(c != channel for c, _ in self.omit)

    @property
    def stem(self) -> str:
        """The key without its unit (`correction_um` → `correction`)."""
        for suffix in ("_um", "_mm", "_ns", "_us", "_ms", "_s"):
            if self.unit and self.key.endswith(suffix):
                return self.key[: -len(suffix)]
        return self.key

    @property
    def shown_unit(self) -> str:
        """The unit of the value as status.json shows it (a loop field's `at`)."""
        return self.shown or self.unit

    def metric_name(self) -> str:
        """Its Prometheus family: a number's name ends in its base unit (`correction_um` →
        `compd_correction_meters`), anything else is `compd_<scope>_<key>` (`compd_axis_state`)."""
        assert self.scope is not None
        if self.metric:
            return self.metric
        if self.kind == "number" and self.unit in BASE_UNITS:
            return f"compd_{self.scope.metric}{self.stem}_{BASE_UNITS[self.unit][0]}"
        return f"compd_{self.scope.metric_other}{self.key}"

    def metric_kind(self) -> str:
        return self.metric_type or ("counter" if self.kind == "count" else "gauge")

    def sparkplug_name(self, **at: str) -> str:
        """Its Sparkplug metric for one instance (`axis=`, `part=`, `signal=`): `Axis/z/correction_um`."""
        assert self.scope is not None
        return (self.sparkplug or self.scope.sparkplug).format(name=self.key, **at)

    def opcua_name(self, **at: str) -> str:
        """Its OPC UA node id (= browse path) for one instance: `compd.Axes.z.CorrectionUm`."""
        assert self.scope is not None
        return (self.opcua or self.scope.opcua).format(name=browse_name(self.key), **at)

    def read(self, where: Any) -> Any:
        """Its value as status.json shows it, from the dict of its scope (an axis's, a contribution's,
        a signal's; the whole status for the loop and the service); None when it is not there."""
        for key in self.at or (self.key,):
            if not isinstance(where, dict):
                return None
            where = where.get(key)
        return where

    def exported(self, status: dict[str, Any], where: Any) -> Any:
        """What every channel shows of it: `read`, but false in observe mode for a field `off_in_observe`
        (a status from before that rule, or of another shape, never makes an exporter say enabled)."""
        if self.off_in_observe and status.get("observe") is True:
            return False
        return self.read(where)


def browse_name(key: str) -> str:
    """A key as OPC UA's browse names go: `correction_um` → `CorrectionUm`."""
    return "".join(part[:1].upper() + part[1:] for part in key.split("_"))


def _scoped(scope: Scope, *fields: Field) -> tuple[Field, ...]:
    return tuple(replace(f, scope=scope) for f in fields)


def _names(table: dict[int, Any]) -> tuple[Any, ...]:
    return tuple(table[i] for i in range(max(table) + 1))


def _nowhere(why: str) -> tuple[tuple[str, str], ...]:
    return tuple((channel, why) for channel in CHANNELS)


AXIS: tuple[Field, ...] = _scoped(
    AXIS_SCOPE,
    Field("prediction_um", "µm", "the model's prediction for the axis (null: no good input vector)"),
    Field("target_um", "µm", "what the guard steers to: the prediction (with the probes' offset), clamped"),
    Field("correction_um", "µm", "the correction the cycle commanded, after clamp and slew"),
    Field(
        "commanded_um",
        "µm",
        "what the sink commands the device for the axis (the word decoded, the PMC's"
        " target, the NC's ramp target); null for an axis not in the word or a sink that cannot say",
    ),
    Field(
        "applied_um",
        "µm",
        "what the device acknowledged or reads back as applied; null when not known"
        " (no read-back, or the sink's link not up)",
    ),
    Field(
        "guard_enable",
        "",
        "the guard's enable bit for the axis",
        "flag",
        omit=_nowhere("the guard's own bit: `enable`, what the machine has, is shown instead"),
    ),
    Field(
        "enable",
        "",
        "the machine has the axis enabled: the guard's bit in a word that reaches it; false in"
        " observe mode (the word at the machine is 0); null (not confirmed) while the sink's link is not up",
        "flag",
        metric="compd_axis_enabled",
        off_in_observe=True,
    ),
    Field("state", "", "the guard's state of the axis", "name", _names(STATE_NAMES), stale=True),
    Field(
        "inhibit",
        "",
        "why the machine holds the axis off (compd.cycle.inhibit)",
        "name",
        _names(HOLD_NAMES),
        metric="compd_axis_held",
        label="reason",
    ),
    Field(
        "saturated",
        "",
        "the correction is held at a limit: the guard's clamp (max_abs_um; the model asks for"
        " more) or the codec's range (the word byte's 63 LSB)",
        "flag",
    ),
    Field(
        "byte",
        "",
        "the axis's byte of the computed word (null: the axis is not in the word)",
        "hex",
        omit=_nowhere("a byte of the loop's `word`, which is shown whole"),
    ),
    Field(
        "shadow_um",
        "µm",
        "the shadow model's prediction for the axis (the correction it would command is its"
        " negative; it drives nothing); null without a shadow on the axis, or without a good input vector",
        metric="compd_shadow_prediction_meters",
        shadow_only=True,
    ),
)
PART: tuple[Field, ...] = _scoped(
    PART_SCOPE,
    Field(
        "prediction_um",
        "µm",
        "what the contribution adds to its axis's prediction: its model's, after its own"
        " clamp, slew and fault policy (null: under `disable` with an input bad)",
        metric="compd_contribution_meters",
    ),
    Field(
        "raw_um",
        "µm",
        "the contribution's model's own prediction (null: an input bad and the model cannot predict from the others)",
    ),
    Field(
        "state",
        "",
        "the contribution's state on the axis (its own fault policy)",
        "name",
        _names(STATE_NAMES),
        stale=True,
    ),
    Field("clamped", "", "the contribution's prediction is held at its own clamp", "flag"),
)
SIGNAL: tuple[Field, ...] = _scoped(
    SIGNAL_SCOPE,
    Field("value", PER_SIGNAL, "the newest value the cycle read (°C for a PT100, rpm, µm, …)"),
    Field("quality", "", "the value's quality", "name", _names(QUALITY_NAMES)),
    Field(
        "stamp_s",
        "s",
        "loop time at which the value was sampled at its source (`age_s` = loop time − this)",
        omit=_nowhere("a time on the loop's clock, which no client shares: its age `age_s` is shown instead"),
    ),
)
LOOP: tuple[Field, ...] = _scoped(
    LOOP_SCOPE,
    Field(
        "state",
        "",
        f"the daemon's state; the status says `{STALE}` instead when the cycle has not written this"
        " record for `stale_after_s` (a cycle stopped or hung: nothing it shows is live)",
        "name",
        STATES,
        stale=True,
        sparkplug="State",
        opcua="compd.State",
    ),
    Field(
        "loop_time_s",
        "s",
        "loop time of the last cycle",
        omit=_nowhere("a time on the loop's clock, which no client shares (compd_uptime_seconds is the loop's age)"),
    ),
    Field(
        "t_start_s",
        "s",
        "loop time of the first cycle",
        omit=_nowhere("a time on the loop's clock, which no client shares (compd_uptime_seconds is the loop's age)"),
    ),
    Field("cycles", "", "cycles run", "count", at=("loop", "cycles")),
    Field(
        "misses",
        "",
        "late cycles (more than half a period late, or done past the next deadline)",
        "count",
        at=("loop", "misses"),
        metric="compd_cycle_misses",
    ),
    Field(
        "skipped",
        "",
        "deadlines skipped when far behind",
        "count",
        at=("loop", "skipped"),
        metric="compd_cycles_skipped",
    ),
    Field(
        "late_max_s",
        "s",
        "the latest a cycle started (its wake-up lateness)",
        at=("loop", "lateness_us", "max"),
        shown="µs",
        omit=(("prometheus", "the lateness histogram, compd_cycle_lateness_seconds, is exported instead"),),
        sparkplug="Loop/lateness_max_us",
        opcua="compd.Loop.LatenessMaxUs",
    ),
    Field(
        "compute_max_ns",
        "ns",
        "the longest a cycle's work took",
        "count",
        at=("loop", "cycle_compute_us", "max"),
        shown="µs",
        metric="compd_cycle_compute_max_seconds",
        metric_type="gauge",
        omit=(
            ("sparkplug", "the compute time's 99th percentile, Loop/compute_p99_us, is published instead"),
            ("opcua", "the compute time's 99th percentile, compd.Loop.ComputeP99Us, is shown instead"),
        ),
    ),
    Field(
        "between_max_s",
        "s",
        "the longest the work between two cycles took",
        omit=_nowhere("the service's bookkeeping (status.json's `publisher`), for tuning, not for the plant"),
    ),
    Field(
        "between_overruns",
        "",
        "times the work between cycles ended past the next deadline",
        "count",
        omit=_nowhere("the service's bookkeeping (status.json's `publisher`), for tuning, not for the plant"),
    ),
    Field(
        "gc_runs",
        "",
        "young-generation collections between cycles",
        "count",
        omit=_nowhere("Python's collector between cycles, for tuning (compd bench), not for the plant"),
    ),
    Field(
        "word",
        "",
        "the word the loop computed",
        "count",
        hex_digits=4,
        metric_type="gauge",
        sparkplug="Word",
        omit=(("opcua", "shown per axis instead (compd.Axes.<axis>.Word), with the byte that carries the axis"),),
    ),
    Field(
        "link",
        "",
        "whether what the sink writes reaches the machine",
        "name",
        LINK_STATES,
        at=("sink", "link"),
        metric="compd_sink_link",
        label="state",
    ),
    Field(
        "sink_writes",
        "",
        "writes the sink made",
        "count",
        omit=_nowhere("the sink's own count, in status.json for its diagnosis, not for the plant"),
    ),
    Field("saturations", "", "words with a clamped axis byte", "count"),
    Field(
        "degraded",
        "",
        "the model runs on a reduced set of inputs",
        "flag",
        omit=_nowhere("shown per axis in status.json; the plant sees it in the signals' qualities"),
    ),
    Field(
        "rows_dropped",
        "",
        "data-log rows the service's ring had no room for",
        "count",
        omit=_nowhere("the service's bookkeeping (status.json's `publisher`), for tuning, not for the plant"),
    ),
    Field(
        "messages_dropped",
        "",
        "messages to the service its ring had no room for",
        "count",
        omit=_nowhere("the service's bookkeeping (status.json's `publisher`), for tuning, not for the plant"),
    ),
    Field(
        "write_max_ns",
        "ns",
        "the longest this record's write took",
        "count",
        omit=_nowhere("the service's bookkeeping (status.json's `publisher`), for tuning, not for the plant"),
    ),
)

# What the service adds beside the record (the top level of the status): how old the record is.
SERVICE: tuple[Field, ...] = _scoped(
    SERVICE_SCOPE,
    Field(
        "record_age_s",
        "s",
        "how long (monotonic time, as the service sees it every 20 ms) since the cycle last"
        f" wrote this record; a time the service itself did not run (a turn over {UNSEEN_S:g} s late) is not counted",
        metric="compd_cycle_record_age_seconds",
        omit=(
            ("sparkplug", "a host judges a sample by its time stamp, and a stale cycle by State"),
            ("opcua", "a stale record's values are Uncertain_LastUsableValue, stamped when it was written"),
        ),
    ),
    Field(
        "stale_after_s",
        "s",
        f"the age past which the status says `{STALE}`: {STALE_PERIODS:g} loop periods and at"
        f" least {STALE_MIN_S:g} s while running, {RELOAD_STALE_S:g} s while reloading; null while stopping or"
        " stopped (the loop is not meant to run)",
        omit=_nowhere("a limit, not a measurement: the state says `stale` once the age passes it"),
    ),
)
# ... and per signal: how old its value is
SIGNAL_SERVICE: tuple[Field, ...] = _scoped(
    SIGNAL_SCOPE,
    Field(
        "age_s",
        "s",
        "how old the value is: loop time of the last cycle − `stamp_s`",
        omit=(
            (
                "sparkplug",
                "it grows every sample (by exception it would go out every time); each sample has its time stamp",
            ),
            ("opcua", "it grows every sample; each value has its SourceTimestamp"),
        ),
    ),
)
# every field, in the order the exporters show them
FIELDS: tuple[Field, ...] = (*AXIS, *PART, *SIGNAL, *SIGNAL_SERVICE, *LOOP, *SERVICE)


def instances(scope: Scope, status: dict[str, Any]) -> list[tuple[dict[str, str], dict[str, Any]]]:
    """Each instance of `scope` in a status snapshot, in name order: its names (`axis`, `part`,
    `signal`: what `Field.sparkplug_name` and `Field.opcua_name` take) and its dict, what
    `Field.read` reads. A section missing or not of status.json's shape has none."""
    if scope.name in ("loop", "service"):
        return [({}, status)]
    if scope.name == "signal":
        signals = status.get("signals")
        named = sorted((n, s) for n, s in signals.items() if isinstance(s, dict)) if isinstance(signals, dict) else []
        return [({"signal": n}, s) for n, s in named]
    axes = status.get("axes")
    axes = sorted((n, a) for n, a in axes.items() if isinstance(a, dict)) if isinstance(axes, dict) else []
    if scope.name == "axis":
        return [({"axis": n}, a) for n, a in axes]
    out = []
    for axis, a in axes:
        parts = a.get("contributions")
        for part, c in sorted(parts.items()) if isinstance(parts, dict) else ():
            if isinstance(c, dict):
                out.append(({"axis": axis, "part": part}, c))
    return out


def shown(f: Field, status: dict[str, Any], at: dict[str, str]) -> bool:
    """Whether the instance `at` of the status has the field at all (a shadow's only on an axis it predicts)."""
    if not f.shadow_only:
        return True
    shadow = status.get("shadow")
    axes = shadow.get("axes") if isinstance(shadow, dict) else None
    return isinstance(axes, dict) and at.get("axis") in axes


# a signal's unit, by the end of its name (compd's names carry their units; STYLE); T_… is °C
_SUFFIX_UNITS = (
    ("_um", "µm"),
    ("_mm", "mm"),
    ("_rpm", "rpm"),
    ("_c", "°C"),
    ("_k", "K"),
    ("_s", "s"),
    ("_a", "A"),
    ("_v", "V"),
    ("_pct", "%"),
    ("_bar", "bar"),
    ("_hz", "Hz"),
)


def signal_unit(name: str) -> str | None:
    """The unit a signal's name says (`err_z_um` → µm, `T_xi` → °C), or None."""
    low = name.lower()
    for suffix, unit in _SUFFIX_UNITS:
        if low.endswith(suffix):
            return unit
    return "°C" if name.startswith("T_") else None


def _by_key(name: str, fields: tuple[Field, ...], values: Any) -> Any:
    """A named tuple of `values`, one per field, named by the fields' keys: a key that is not a
    field's is an AttributeError where it is first used (a module's top level: at import), never a
    wrong row or a silent None; two fields with one key fail here, at import."""
    return namedtuple(name, [f.key for f in fields])(*values)


# each group's fields by key (`AX.correction_um` is the Field): how the exporters name what they read
AX = _by_key("AxisFields", AXIS, AXIS)
PT = _by_key("PartFields", PART, PART)
SG = _by_key("SignalFields", SIGNAL, SIGNAL)
SGS = _by_key("SignalServiceFields", SIGNAL_SERVICE, SIGNAL_SERVICE)
LP = _by_key("LoopFields", LOOP, LOOP)
SV = _by_key("ServiceFields", SERVICE, SERVICE)
# each field's row in the record (`AI.correction_um` is 2): how the cycle writes it, an int per name
AI = _by_key("AxisRows", AXIS, range(len(AXIS)))
PI = _by_key("PartRows", PART, range(len(PART)))
SI = _by_key("SignalRows", SIGNAL, range(len(SIGNAL)))
LI = _by_key("LoopRows", LOOP, range(len(LOOP)))
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
    stage_names: tuple[str, ...]  # the loop's stages, in the order of `stages`' columns

    def get(self, row: int) -> float:
        """A loop field by its row (`LI.cycles`)."""
        return float(self.loop[row])


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
        self._lv = memoryview(self._buf)[8 * _HEAD : 8 * (_HEAD + len(LOOP))].cast("d")  # scalar stores: no numpy
        rest = data[len(LOOP) :]
        self._axes = rest[: len(AXIS) * n_axes].reshape(len(AXIS), n_axes)
        rest = rest[len(AXIS) * n_axes :]
        self._signals = rest[: len(SIGNAL) * n_sig].reshape(len(SIGNAL), n_sig)
        self._parts = rest[len(SIGNAL) * n_sig :].reshape(len(PART), n_parts)
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
        v[LI.state] = STATES.index(self.state)
        v[LI.loop_time_s] = lp.now_s
        v[LI.t_start_s] = lp.t_start_s
        v[LI.cycles] = st.cycles
        v[LI.misses] = st.misses
        v[LI.skipped] = st.skipped
        v[LI.late_max_s] = st.late_max_s
        v[LI.compute_max_ns] = st.compute_max_ns
        v[LI.between_max_s] = st.between_max_s
        v[LI.between_overruns] = st.between_overruns
        v[LI.gc_runs] = st.gc_runs
        v[LI.word] = lp.word
        v[LI.link] = _LINK[sink.link_state()]
        v[LI.sink_writes] = sink.writes
        v[LI.saturations] = lp.encoder.saturations
        v[LI.degraded] = 1.0 if g.degraded else 0.0
        v[LI.rows_dropped] = self.rows_dropped
        v[LI.messages_dropped] = self.messages_dropped() if self.messages_dropped is not None else 0
        ax = self._axes
        np.copyto(ax[AI.prediction_um], lp.pred_um)
        np.copyto(ax[AI.target_um], g.target_um)
        np.copyto(ax[AI.correction_um], g.out_um)
        np.copyto(ax[AI.guard_enable], g.enable)
        np.copyto(ax[AI.state], g.state)
        np.copyto(ax[AI.inhibit], g.hold)
        np.copyto(ax[AI.saturated], g.clamped)
        if self._slots:
            cmd, app = self._slot_cmd, self._slot_app
            sink.commanded_um(cmd)
            sink.applied_um(app)
            sat = lp.encoder.saturated
            word = lp.word
            commanded, applied, saturated, byte = AI.commanded_um, AI.applied_um, AI.saturated, AI.byte
            for slot, axis in self._slots:
                ax[commanded, axis] = cmd[slot]
                ax[applied, axis] = app[slot]
                if sat[slot]:
                    ax[saturated, axis] = 1.0
                ax[byte, axis] = (word >> 8) & 0xFF if slot == 0 else word & 0xFF
        if lp.shadow is not None:
            np.copyto(ax[AI.shadow_um], lp.shadow.pred_um)
        fr = lp.frame
        sg = self._signals
        np.copyto(sg[SI.value], fr.values)
        np.copyto(sg[SI.quality], fr.quality)
        np.copyto(sg[SI.stamp_s], fr.stamp_s)
        cs = lp.model
        if cs.part_names:
            pt = self._parts
            np.copyto(pt[PI.prediction_um], cs.part_um)
            np.copyto(pt[PI.raw_um], cs.part_raw_um)
            np.copyto(pt[PI.state], cs.part_state)
            np.copyto(pt[PI.clamped], cs.part_clamped)
        d = time.perf_counter_ns() - t0
        if d > v[LI.write_max_ns]:
            v[LI.write_max_ns] = d
        head[1] += 1
        head[0] += 1

    def read(self) -> Reading | None:
        """A consistent copy (None: the writer was always mid-write, or has never written)."""
        head, st = self._head, self.loop.stats
        for _ in range(READ_TRIES):
            seq = head[0]
            if seq & 1:
                continue
            r = Reading(
                self._loop.copy(),
                self._axes.copy(),
                self._signals.copy(),
                self._parts.copy(),
                np.frombuffer(st.hist, dtype=np.int64).copy(),
                np.frombuffer(st.compute_hist, dtype=np.int64).copy(),
                np.vstack(
                    [np.frombuffer(a, dtype=np.int64) for a in (st.stage_last_ns, st.stage_max_ns, st.stage_sum_ns)]
                ),
                st.stage_names,
            )
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
    late = {"p50": p50, "p99": p99, "p999": p999, "max": round(r.get(LI.late_max_s) * 1e6, 1)}
    compute = {"p50": c50, "p99": c99, "max": round(r.get(LI.compute_max_ns) / 1000, 1)}
    limit = range_limit_us(r.hist)
    n = max(int(r.get(LI.cycles)), 1)
    stages = {
        name: {
            "last_us": int(r.stages[0, i]) / 1000,
            "mean_us": int(r.stages[2, i]) / n / 1000,
            "max_us": int(r.stages[1, i]) / 1000,
        }
        for i, name in enumerate(r.stage_names)
    }
    return {
        "period_ms": period_s * 1000.0,
        "cycles": int(r.get(LI.cycles)),
        "misses": int(r.get(LI.misses)),
        "skipped": int(r.get(LI.skipped)),
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
    link = _value(LP.link, r.get(LI.link))
    reaches = link == "up"
    word = int(r.get(LI.word))
    axes: dict[str, Any] = {}
    for i, name in enumerate(st["axes"]):
        a = {f.key: _value(f, float(r.axes[j, i])) for j, f in enumerate(AXIS)}
        a["policy"] = st["policy"][i]
        a["degraded"] = bool(r.get(LI.degraded))
        a["word_byte"] = st["word_byte"][i]
        if observe:
            a[AX.enable.key] = False  # the word at the machine is 0: every enable bit off
        elif not reaches:
            a[AX.enable.key] = None  # not confirmed at the machine
            a[AX.applied_um.key] = None
        else:
            a[AX.enable.key] = bool(a[AX.guard_enable.key])
        axes[name] = a
    for k, (part, axis) in enumerate(st.get("parts") or []):
        c = {f.key: _value(f, float(r.parts[j, k])) for j, f in enumerate(PART)}
        axes[axis].setdefault("contributions", {})[part] = c
    now = r.get(LI.loop_time_s)
    signals = {}
    for i, name in enumerate(st["signals"]):
        s = {f.key: _value(f, float(r.signals[j, i])) for j, f in enumerate(SIGNAL)}
        stamp = float(r.signals[SI.stamp_s, i])
        s[SGS.age_s.key] = None if not math.isfinite(now - stamp) else float(now - stamp)
        signals[name] = s
    sink = dict(dev.get("sink") or {})
    sink["link"] = link
    sink["writes"] = int(r.get(LI.sink_writes))
    if observe:
        sink["observe"] = True
        sink["word"] = "0x0000"
    cycles = int(r.get(LI.cycles))
    snap: dict[str, Any] = {
        "schema": SCHEMA,
        "version": st["version"],
        "pid": st["pid"],
        "state": _value(LP.state, r.get(LI.state)),
        "observe": observe,
        "written_unix_s": time.time(),
        "uptime_s": now - r.get(LI.t_start_s) if cycles else 0.0,
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
        "saturations": int(r.get(LI.saturations)),
        "events": list(desc.events),
        "threads": dev.get("threads") or [],
        "publisher": {
            "messages_dropped": int(r.get(LI.messages_dropped)),
            "rows_dropped": int(r.get(LI.rows_dropped)),
            "status_write_max_us": round(r.get(LI.write_max_ns) / 1000, 1),
            "between_max_us": round(r.get(LI.between_max_s) * 1e6, 1),
            "between_overruns": int(r.get(LI.between_overruns)),
            **(dev.get("publisher") or {}),
        },
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


_PLACEHOLDERS = {"axis": "<axis>", "part": "<name>", "signal": "<name>"}


def channel_names(f: Field) -> dict[str, str]:
    """Each channel's name of the field (its instances' names as placeholders), or why it leaves it out."""
    why = dict(f.omit)
    assert f.scope is not None
    at = {k: v for k, v in _PLACEHOLDERS.items() if k in f.scope.sparkplug or k in f.scope.opcua}
    labels = (*f.scope.labels, *((f.label or f.key,) if f.kind == "name" else ()))
    names = {
        "prometheus": f"`{f.metric_name()}`" + (f" {{{', '.join(labels)}}}" if labels else ""),
        "sparkplug": f"`{f.sparkplug_name(**at)}`",
        "opcua": f"`{f.opcua_name(**at)}`",
    }
    if f.unit == PER_SIGNAL:
        names["prometheus"] = "`compd_signal_<unit>` {signal} (docs/metrics.md)"
    return {c: f"— {why[c]}" if c in why else names[c] for c in CHANNELS}


def fields_markdown() -> str:
    """docs/status-fields.md: every number of the record, by group, and what each channel calls it."""
    out = [
        "# Status fields",
        "",
        "Generated from compd/cycle/statusblock.py (`python -m compd.cycle.statusblock`): every number the cycle",
        "writes into its status record each cycle, and those the service adds beside it, under the key",
        'it has in status.json (docs/formats.md, "Status file"), with its unit and meaning; then the name',
        "each channel gives it (docs/metrics.md, docs/plant.md), derived from the key by rule, or why the",
        "channel leaves it out. A Prometheus family is in the base unit (µm as meters, µs and ns as seconds).",
        "",
    ]
    for title, fields in (
        ("Per axis", AXIS),
        ("Per contribution (a sum of contributions only)", PART),
        ("Per signal", SIGNAL),
        ("The service's, per signal", SIGNAL_SERVICE),
        ("The loop", LOOP),
        ("The service's, beside the record", SERVICE),
    ):
        assert fields[0].scope is not None
        out += [f"## {title} ({fields[0].scope.where})", "", "| key | unit | kind | meaning |", "|---|---|---|---|"]
        for f in fields:
            kind = (
                f"one of {', '.join('null' if n is None else f'`{n}`' for n in f.names)}"
                if f.kind == "name"
                else f.kind
            )
            where = f" (status.json: `{'.'.join(f.at)}`{f', in {f.shown}' if f.shown else ''})" if f.at else ""
            out.append(f"| `{f.key}` | {f.unit or '—'} | {kind} | {f.meaning}{where} |")
        out += ["", "| key | Prometheus | Sparkplug B | OPC UA |", "|---|---|---|---|"]
        for f in fields:
            names = channel_names(f)
            out.append(f"| `{f.key}` | {names['prometheus']} | {names['sparkplug']} | {names['opcua']} |")
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(fields_markdown())
