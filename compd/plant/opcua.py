"""A read-only OPC UA server (asyncua) that shows compd's live status to the plant, secured with Basic256Sha256.

The service process (compd/daemon/host.py) starts an `OpcUaServer` on its first status
snapshot (compd/service/status.py) and hands it each later one; the server runs on a thread of
its own ("compd-opcua") with its own asyncio loop, never on the cycle.

The address space (docs/plant.md, "OPC UA"): under Objects, a folder `compd` in the
namespace `opcua.namespace_uri`. Every node id is a string that is also the node's
browse path: `ns=<idx>;s=compd.Axes.z.CorrectionUm` is the variable `CorrectionUm` in
the folder `z` in the folder `Axes` in `compd`.

The status record's fields are made from its schema (compd/cycle/statusblock.py FIELDS,
`record_variables`): each field OPC UA shows is a variable named by rule (`correction_um` →
CorrectionUm) in its scope's folder, its data type from its kind, a number in its unit; beside
them what the status adds:

* `compd.State` (String), `compd.Observe` (Boolean): the daemon's state, observe mode;
* `compd.Axes.<axis>.` CorrectionUm, TargetUm, PredictionUm, CommandedUm, AppliedUm (Double,
  µm), Enable (Boolean: on at the machine, so false in observe mode; Bad, not confirmed,
  while the sink's link is not up), State and Inhibit (String), Saturated (Boolean), Word
  (UInt16: the 16-bit word that carries the axis), ModelKind (String), FitDate (String: the
  model's `fit.fitted_at`, or empty);
* `compd.Signals.<signal>.` Value (Double, its StatusCode from the signal's quality,
  see `QUALITY_STATUS`), Quality (String);
* `compd.Loop.` PeriodMs (Double, ms), Cycles, Misses, Skipped and Saturations (UInt64), Link
  (String), LatenessP99Us, LatenessMaxUs, ComputeP99Us (Double, µs; a p99 over the histogram's
  range is its limit, 20000 µs, with Uncertain_EngineeringUnitsExceeded: `OVER_RANGE_STATUS`).

A number in a unit is an AnalogItemType with the properties EURange (the guard's clamp of the axis,
a signal's configured limits or its unit's documented range, the timing histograms' range) and
EngineeringUnits (EUInformation, UNECE code; a signal's unit is the one its name says); the rest
are BaseDataVariableType. Every node has a Description (a status record field's `meaning` from
compd/cycle/statusblock.py, else `DESCRIPTIONS`) and every variable a MinimumSamplingInterval of
`opcua.period_s`. The axes and signals are those of the first snapshot: a reload builds a new server.
A value compd does not have (None, NaN) is written with a Bad StatusCode, never as a
number; a snapshot of another shape writes what it can and counts an error.

Every variable is CurrentRead only and no client is ever an admin, so a write is
refused (Bad_UserAccessDenied). Security: endpoints for the `opcua.security` policies
only; a client whose channel is not secured is refused at login unless "None" is
offered; with `trusted_clients`, only the certificates in that folder (exact match)
may open a session; user names and passwords from the password files (compared in
constant time), the UserName token policy of every endpoint Basic256Sha256 (the password
always encrypted with the server's key; one that is not is refused); anonymous clients only
with `anonymous: true`. asyncua's own log lines reach compd's log as `opcua_stack` events,
rate-limited (`route_asyncua_logs`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hmac
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cryptography import x509
from cryptography.hazmat.primitives import serialization

from compd import version
from compd.core.config import MAX_CORRECTION_UM, SIGNAL_ABS_MAX, GuardConfig
from compd.core.errors import BadInput
from compd.cycle.loop import HIST_US
from compd.cycle.statusblock import (
    FIELDS,
    LP,
    PER_SIGNAL,
    SG,
    STALE,
    SV,
    Field,
    instances,
    shown,
    signal_unit,
)
from compd.models.base import TEMP_MAX_C, TEMP_MIN_C
from compd.plant.material import Material, read_material
from compd.service.threads import ServiceThread

if TYPE_CHECKING:
    from compd.core.config import OpcUaConfig

log = logging.getLogger("compd.opcua")

START_TIMEOUT_S = 60.0  # init (≈ 1.5 s: asyncua builds the standard address space; 28 s on a loaded box) + bind
STOP_TIMEOUT_S = 10.0


# ------------------------------------------------------------------ the address space

UNITS_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"  # Part 8 §5.6.3: UNECE Recommendation 20


@dataclass(frozen=True)
class Unit:
    """An engineering unit as OPC UA names it: a UNECE Recommendation 20 common code and its symbol."""

    symbol: str  # the EUInformation's DisplayName: the code's symbol in Recommendation 20
    unece: str
    description: str

    @property
    def unit_id(self) -> int:
        """Part 8 §5.6.3: the code's characters, each a byte, most significant first ("4H" → 0x3448)."""
        return int.from_bytes(self.unece.encode("ascii"), "big")

    def eu_information(self) -> Any:
        from asyncua import ua

        return ua.EUInformation(
            NamespaceUri=UNITS_NAMESPACE,
            UnitId=self.unit_id,
            DisplayName=ua.LocalizedText(self.symbol),
            Description=ua.LocalizedText(self.description),
        )


MICROMETRE = Unit("µm", "4H", "micrometre (micron)")
MILLISECOND = Unit("ms", "C26", "millisecond")
MICROSECOND = Unit("µs", "B98", "microsecond")
# a signal's unit as its name says it (compd/cycle/statusblock.py `signal_unit`) → its UNECE unit
SIGNAL_UNITS: dict[str, Unit] = {
    "°C": Unit("°C", "CEL", "degree Celsius"),
    "K": Unit("K", "KEL", "kelvin"),
    "µm": MICROMETRE,
    "mm": Unit("mm", "MMT", "millimetre"),
    "rpm": Unit("r/min", "RPM", "revolutions per minute"),
    "s": Unit("s", "SEC", "second [unit of time]"),
    "A": Unit("A", "AMP", "ampere"),
    "V": Unit("V", "VLT", "volt"),
    "%": Unit("%", "P1", "percent"),
    "bar": Unit("bar", "BAR", "bar [unit of pressure]"),
    "Hz": Unit("Hz", "HTZ", "hertz"),
}

# a signal's quality (compd/core/frame.py) → the StatusCode of its Value; any other → BadSensorFailure
QUALITY_STATUS = {
    "good": "Good",
    "stale": "UncertainLastUsableValue",
    "comms_lost": "BadNoCommunication",
    "no_data": "BadWaitingForInitialData",
    "out_of_range": "BadOutOfRange",
}
OTHER_QUALITY_STATUS = "BadSensorFailure"  # burnout, implausible, frozen, and any quality not above
NO_VALUE_STATUS = "BadNoData"  # compd has no value (None, NaN) or the snapshot lacks it
# a percentile whose quantile fell in the histogram's overflow bin: the value is the range limit
OVER_RANGE_STATUS = "UncertainEngineeringUnitsExceeded"
# a snapshot whose cycle is stale (compd.service.status): every Good value of the record is its last one
STALE_STATUS = "UncertainLastUsableValue"

Reader = Callable[[dict[str, Any]], tuple[Any, str]]  # snapshot → (raw value, StatusCode name)


@dataclass(frozen=True)
class EuRange:
    """An analog variable's EURange (Part 8 §5.3.2: the values likely in normal operation, for
    scaling a bar graph; a value may lie outside) and where it comes from."""

    low: float
    high: float
    source: str  # the Description of the EURange property: which config key or which documented range


# the signals' EURange without configured limits (guard.signals.<name>.min/max), by the unit their
# name says (docs/plant.md, "Units and ranges"); the numbers are a machine tool's, not compd's limits
SIGNAL_RANGES: dict[str | None, tuple[float, float, str]] = {
    "°C": (TEMP_MIN_C, TEMP_MAX_C, "a temperature on a machine tool (the guard's default limits)"),
    "K": (TEMP_MIN_C - TEMP_MAX_C, TEMP_MAX_C - TEMP_MIN_C, "a difference of two such temperatures"),
    "µm": (-MAX_CORRECTION_UM, MAX_CORRECTION_UM, "a thermal error: at most the largest clamp compd accepts"),
    "mm": (-10_000.0, 10_000.0, "an axis position: 10 m of travel either way"),
    "rpm": (-100_000.0, 100_000.0, "a spindle speed, either direction"),
    "Hz": (-2_000.0, 2_000.0, "a rotational speed (120 000 r/min), either direction"),
    "s": (0.0, 86_400.0, "a duration up to a day"),
    "A": (-1_000.0, 1_000.0, "a motor current"),
    "V": (-1_000.0, 1_000.0, "a voltage"),
    "%": (0.0, 100.0, "a share"),
    "bar": (0.0, 1_000.0, "a pressure (hydraulics reach 700 bar)"),
    None: (-SIGNAL_ABS_MAX, SIGNAL_ABS_MAX, "a signal whose name says no unit: the largest limit compd accepts"),
}
PERIOD_RANGE_MS = (0.0, 60_000.0)  # loop.period_s is at most 60 s

# the Descriptions of the nodes that are not a field of the cycle's status record; a field's Description
# is its `meaning` in compd/cycle/statusblock.py (AXIS, SIGNAL, LOOP), as docs/status-fields.md shows it
DESCRIPTIONS = {
    "compd": "the live status of compd, the thermal-error compensation daemon of this machine (read-only)",
    "compd.Observe": "observe mode: the full loop runs, the output is held disabled (the word at the machine is 0)",
    "compd.Axes": "a folder per axis the model corrects",
    "compd.Signals": "a folder per signal the sources read",
    "compd.Loop": "the fixed-period cycle: its period, counts and timing",
    "ModelKind": "the kind of the thermal-error model (feed_axis, lvr, xi_spindle, ar1, mlr)",
    "FitDate": "when the model was fitted (the model file's fit.fitted_at, ISO 8601); empty if unknown",
    "compd.Loop.PeriodMs": "the cycle's period (loop.period_s)",
    "compd.Loop.LatenessP99Us": "the cycle's wake-up lateness, 99th percentile since start; above the"
    " histogram's range it is the range limit with Uncertain_EngineeringUnitsExceeded",
    "compd.Loop.ComputeP99Us": "the cycle's compute time, 99th percentile since start; above the histogram's"
    " range it is the range limit with Uncertain_EngineeringUnitsExceeded",
}


@dataclass(frozen=True)
class Variable:
    """One variable: its node id (= browse path), type, unit, description, range and where its value comes from.

    With an `eu_range` it is an AnalogItemType (EURange, and EngineeringUnits when the unit is
    known); without, a BaseDataVariableType."""

    node_id: str
    data_type: str  # a ua.VariantType name: Double, UInt16, UInt64, Boolean, String
    unit: Unit | None
    read: Reader
    description: str = ""
    eu_range: EuRange | None = None

    @property
    def analog(self) -> bool:
        return self.eu_range is not None


def _good(get: Callable[[dict[str, Any]], Any]) -> Reader:
    return lambda snap: (get(snap), "Good")


def _fit_date(snap: dict[str, Any]) -> Any:
    return (snap["model"].get("fit") or {}).get("fitted_at") or ""


def _percentile(group: str, key: str) -> Reader:
    """A loop percentile (`group`: lateness_us, cycle_compute_us); one over the histogram's range
    (the loop's `over_range`) is its range limit with Uncertain_EngineeringUnitsExceeded."""

    def read(snap: dict[str, Any]) -> tuple[Any, str]:
        lp = snap["loop"]
        over = lp.get("over_range")
        flagged = isinstance(over, dict) and key in (over.get(group) or ())
        return lp[group][key], OVER_RANGE_STATUS if flagged else "Good"

    return read


def _meaning(field: Any) -> str:
    """A status record field's meaning as an OPC UA Description: JSON's null is a Bad_NoData value
    here; a name field lists its names."""
    text = re.sub(r"\bnull\b", "Bad_NoData", field.meaning)
    if field.kind == "name":
        text += " (one of " + ", ".join(n for n in field.names if n is not None) + ")"
    return text


def axis_range(guard: GuardConfig, axis: str) -> EuRange:
    """±the guard's clamp of `axis` (as compd.cycle.guard.Guard takes it): what a correction can reach."""
    clamp_um, key = guard.clamp_um(axis)
    return EuRange(-clamp_um, clamp_um, f"± {key}")


def signal_range(guard: GuardConfig, name: str, unit: str | None) -> EuRange:
    """The signal's plausibility limits from the config (guard.signals.<name>), else its unit's range."""
    lim = guard.signals.get(name)
    if lim is not None:
        return EuRange(lim.min, lim.max, f"guard.signals.{name}.min … max")
    low, high, why = SIGNAL_RANGES[unit]
    return EuRange(low, high, f"no configured limits: {why}")


def folders(snap: dict[str, Any]) -> dict[str, str]:
    """Each folder's node id → its Description, for the axes and signals of this (first) snapshot."""
    out = {key: DESCRIPTIONS[key] for key in ("compd", "compd.Axes", "compd.Signals", "compd.Loop")}
    axes = snap.get("axes")
    for axis in axes if isinstance(axes, dict) else ():
        out[f"compd.Axes.{axis}"] = (
            f"the axis {axis}: the model's prediction, the guard's correction, the machine's word"
        )
        parts = axes[axis].get("contributions") if isinstance(axes[axis], dict) else None
        if isinstance(parts, dict):
            out[f"compd.Axes.{axis}.Contributions"] = (
                f"the contributions summed into the axis {axis}'s prediction, each limited on its own"
            )
            for name in parts:
                out[f"compd.Axes.{axis}.Contributions.{name}"] = f"the contribution {name} to the axis {axis}"
    signals = snap.get("signals")
    for name in signals if isinstance(signals, dict) else ():
        unit = signal_unit(name)
        out[f"compd.Signals.{name}"] = f"the signal {name}" + (f" ({unit}, as its name says)" if unit else "")
    return out


# a status field's kind → the data type of its variable (a count shown as a 16-bit word: UInt16)
KIND_DATA_TYPES = {"number": "Double", "count": "UInt64", "flag": "Boolean", "name": "String", "hex": "String"}
UNITS = {**SIGNAL_UNITS, "ms": MILLISECOND, "µs": MICROSECOND}  # a field's unit as status.json shows it


def _locate(f: Field, at: dict[str, str]) -> Callable[[dict[str, Any]], Any]:
    """How to find the instance `at` of the field's scope in a later snapshot (a KeyError or TypeError
    when it is not there: the variable is Bad_NoData, and counted)."""
    assert f.scope is not None
    scope = f.scope.name
    if scope == "axis":
        return lambda s: s["axes"][at["axis"]]
    if scope == "contribution":
        return lambda s: s["axes"][at["axis"]]["contributions"][at["part"]]
    if scope == "signal":
        return lambda s: s["signals"][at["signal"]]
    return lambda s: s


def _reader(f: Field, at: dict[str, str]) -> Reader:
    """A field's value in a snapshot, as its variable's (`KIND_DATA_TYPES`): its key must be there;
    a signal's value takes its StatusCode from its quality (`QUALITY_STATUS`)."""
    locate = _locate(f, at)

    def read(snap: dict[str, Any]) -> tuple[Any, str]:
        where = locate(snap)
        value = f.exported(snap, where)
        if value is None and (f.at or (f.key,))[-1] not in _parent(f, where):
            raise KeyError(f.key)  # not in the snapshot at all: a snapshot of another shape
        if f.kind == "name" and value is None:
            value = ""  # a name that is null (no hold)
        elif f.kind == "count" and f.hex_digits and isinstance(value, str):
            value = int(value, 16)
        code = "Good"
        if f is SG.value:
            code = QUALITY_STATUS.get(SG.quality.read(where), OTHER_QUALITY_STATUS)
        return value, code

    return read


def _parent(f: Field, where: Any) -> Any:
    """The dict that holds the field's value (its `at` but the last key), or an empty one."""
    for key in (f.at or (f.key,))[:-1]:
        where = where.get(key) if isinstance(where, dict) else None
    return where if isinstance(where, dict) else {}


def _field_range(
    f: Field,
    at: dict[str, str],
    unit: str | None,
    guard: GuardConfig,
    clamps: dict[str, dict[str, Any]],
    timing: EuRange,
) -> EuRange | None:
    """The EURange of a field's variable: an axis's µm ± its clamp, a contribution's ± its own (none
    without one), a signal's its limits, the loop's µs the histograms' range, anything else its unit's."""
    scope = f.scope.name if f.scope is not None else ""
    if scope == "axis" and unit == "µm":
        return axis_range(guard, at["axis"])
    if scope == "contribution" and unit == "µm":
        clamp = clamps.get(at["part"], {}).get(at["axis"], {}).get("max_abs_um")
        if isinstance(clamp, int | float) and not isinstance(clamp, bool):
            return EuRange(-float(clamp), float(clamp), f"± the contribution {at['part']}'s clamp (max_abs_um)")
        return None
    if scope == "signal" and f.unit == PER_SIGNAL:
        return signal_range(guard, at["signal"], unit)
    if scope in ("loop", "service") and unit == "µs":
        return timing
    low, high, why = SIGNAL_RANGES.get(unit, SIGNAL_RANGES[None])
    return EuRange(low, high, f"its unit's range: {why}")


def record_variables(snap: dict[str, Any], guard: GuardConfig, timing: EuRange) -> dict[str, list[Variable]]:
    """A variable per instance of each field of the status record (compd/cycle/statusblock.py FIELDS)
    that OPC UA shows, named by its rule (`Field.opcua_name`: compd.Axes.z.CorrectionUm), its data type
    from its kind, a number an AnalogItemType in its unit (a signal's: the one its name says) with an
    EURange; its Description the field's meaning. By where they go: each axis's name, `signals`, `loop`."""
    clamps: dict[str, dict[str, Any]] = {
        c.get("name"): c.get("limits") or {}
        for c in (snap.get("model") or {}).get("contributions") or []
        if isinstance(c, dict)
    }
    out: dict[str, list[Variable]] = {}
    for f in FIELDS:
        if not f.on("opcua"):
            continue
        assert f.scope is not None
        for at, _ in instances(f.scope, snap):
            if not shown(f, snap, at):
                continue
            data_type = "UInt16" if f.kind == "count" and f.hex_digits == 4 else KIND_DATA_TYPES[f.kind]
            text = _meaning(f)
            unit_name = signal_unit(at["signal"]) if f.unit == PER_SIGNAL else f.shown_unit or None
            unit, rng = None, None
            if f.kind == "number":
                unit = UNITS.get(unit_name or "")
                rng = _field_range(f, at, unit_name, guard, clamps, timing)
                if f.unit == PER_SIGNAL:
                    said = f"; in {unit_name}, as its name says" if unit_name else "; its name says no unit"
                    text += said + "; its StatusCode follows Quality"
                elif f.shown and f.shown != f.unit:
                    text += f" (here in {f.shown})"
            group = at.get("axis") or ("signals" if f.scope.name == "signal" else "loop")
            out.setdefault(group, []).append(Variable(f.opcua_name(**at), data_type, unit, _reader(f, at), text, rng))
    return out


def address_space(snap: dict[str, Any], guard: GuardConfig | None = None) -> list[Variable]:
    """The variables for the axes and signals of this (first) snapshot, in browse order; the ranges
    from `guard` (the config's guard section; None: its defaults). The status record's fields are
    `record_variables`; beside them what the status adds (observe mode, the model, the loop's timing
    from its histograms) and each axis's Word."""
    guard = guard if guard is not None else GuardConfig()
    # the loop's timing figures: 0 … the range of its histograms (1 µs bins up to 20 ms); a p99 above it
    # is the range limit with Uncertain_EngineeringUnitsExceeded, the maximum is measured (can lie above)
    timing = EuRange(0.0, float(HIST_US), f"0 … {HIST_US} µs, the range of the loop's timing histograms")
    fields = record_variables(snap, guard, timing)
    loop = fields.get("loop", [])
    out = [v for v in loop if not v.node_id.startswith("compd.Loop.")]  # compd.State
    out.append(Variable("compd.Observe", "Boolean", None, _good(lambda s: s["observe"]), DESCRIPTIONS["compd.Observe"]))
    word_meaning = _meaning(LP.word)
    axes = snap.get("axes")
    for axis in sorted(axes) if isinstance(axes, dict) else []:
        p = f"compd.Axes.{axis}."
        byte = axes[axis].get("word_byte") if isinstance(axes[axis], dict) else None
        word = word_meaning + (
            f"; it carries this axis in its {byte} byte" if byte else "; it does not carry this axis"
        )
        mine = fields.get(axis, [])
        out += [v for v in mine if ".Contributions." not in v.node_id]
        out += [
            Variable(p + "Word", "UInt16", None, _good(lambda s: int(LP.word.read(s), 16)), word),
            Variable(p + "ModelKind", "String", None, _good(lambda s: s["model"]["kind"]), DESCRIPTIONS["ModelKind"]),
            Variable(p + "FitDate", "String", None, _good(_fit_date), DESCRIPTIONS["FitDate"]),
        ]
        out += [v for v in mine if ".Contributions." in v.node_id]
    out += fields.get("signals", [])
    out.append(
        Variable(
            "compd.Loop.PeriodMs",
            "Double",
            MILLISECOND,
            _good(lambda s: s["loop"]["period_ms"]),
            DESCRIPTIONS["compd.Loop.PeriodMs"],
            EuRange(*PERIOD_RANGE_MS, "0 … 60 s, the longest loop.period_s"),
        )
    )
    out += [v for v in loop if v.node_id.startswith("compd.Loop.")]
    out += [
        Variable(
            "compd.Loop.LatenessP99Us",
            "Double",
            MICROSECOND,
            _percentile("lateness_us", "p99"),
            DESCRIPTIONS["compd.Loop.LatenessP99Us"],
            timing,
        ),
        Variable(
            "compd.Loop.ComputeP99Us",
            "Double",
            MICROSECOND,
            _percentile("cycle_compute_us", "p99"),
            DESCRIPTIONS["compd.Loop.ComputeP99Us"],
            timing,
        ),
    ]
    return out


def _coerce(data_type: str, raw: Any) -> Any:
    """`raw` as a value of `data_type`, None for a missing number (None, NaN, ±inf);
    TypeError or ValueError when it is not of that type."""
    if raw is None:
        return None
    if data_type == "Boolean":
        if not isinstance(raw, bool):
            raise TypeError(f"{raw!r} is not a boolean")
        return raw
    if data_type == "String":
        if not isinstance(raw, str):
            raise TypeError(f"{raw!r} is not a string")
        return raw
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise TypeError(f"{raw!r} is not a number")
    if data_type == "Double":
        return float(raw) if math.isfinite(raw) else None
    top = 0xFFFF if data_type == "UInt16" else (1 << 64) - 1
    if not isinstance(raw, int) or not 0 <= raw <= top:
        raise ValueError(f"{raw!r} is not a {data_type}")
    return raw


def data_values(variables: list[Variable], snap: dict[str, Any]) -> tuple[list[Any], list[str]]:
    """A ua.DataValue per variable from one snapshot, and a line per value the snapshot lacked
    or had of the wrong type (that variable: Bad_NoData). Never raises for the snapshot's shape.

    A snapshot whose cycle is stale: the states (compd.State, each axis's and contribution's State,
    all `stale`) are Good, composed now; every other Good value is the record's last one,
    Uncertain_LastUsableValue with the time the cycle last wrote it as its SourceTimestamp."""
    from asyncua import ua

    now = datetime.now(UTC)
    written = snap.get("written_unix_s")
    source = now
    if isinstance(written, int | float) and not isinstance(written, bool) and math.isfinite(written):
        source = datetime.fromtimestamp(written, UTC)
    stale = LP.state.read(snap) == STALE
    last = source  # when the cycle last wrote its record
    age = SV.record_age_s.read(snap)
    if stale and isinstance(age, int | float) and not isinstance(age, bool) and math.isfinite(age) and age >= 0:
        last = source - timedelta(seconds=age)
    out, problems = [], []
    for var in variables:
        vtype = getattr(ua.VariantType, var.data_type)
        try:
            raw, code = var.read(snap)
            value = _coerce(var.data_type, raw)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as e:
            problems.append(f"{var.node_id}: {type(e).__name__}: {e}")
            value, code = None, NO_VALUE_STATUS
        recorded = stale and not var.node_id.endswith(".State")  # a value of the stale record
        if recorded and code == "Good":
            code = STALE_STATUS
        status = ua.StatusCode(getattr(ua.StatusCodes, code))
        if value is None and not status.is_bad():
            status = ua.StatusCode(getattr(ua.StatusCodes, NO_VALUE_STATUS))
        variant = ua.Variant() if status.is_bad() else ua.Variant(value, vtype)
        out.append(
            ua.DataValue(
                Value=variant, StatusCode=status, SourceTimestamp=last if recorded else source, ServerTimestamp=now
            )
        )
    return out, problems


# ------------------------------------------------------------------ files


# ------------------------------------------------------------------ the server


class _Users:
    """asyncua's user manager: who may open a session. Nobody is ever an admin (who could write)."""

    def __init__(self, passwords: dict[str, bytes], anonymous: bool, plain_ok: bool) -> None:
        self._passwords = passwords
        self._anonymous = anonymous
        self._plain_ok = plain_ok

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> Any:
        from asyncua.crypto.permission_rules import User, UserRole

        # asyncua keeps a channel with SecurityPolicy None open to every client (for
        # GetEndpoints) even when no None endpoint is offered: such a channel has no peer
        # certificate, and its sessions are refused here.
        if not certificate and not self._plain_ok:
            log.info("OPC UA login refused: the channel is not secured")
            return None
        if username is None:
            if self._anonymous:
                return User(role=UserRole.User, name="anonymous")
            log.info("OPC UA login refused: anonymous")
            return None
        expected = self._passwords.get(username)
        ok = hmac.compare_digest((password or "").encode("utf-8"), expected or b"")
        if ok and expected is not None:
            return User(role=UserRole.User, name=username)
        log.info("OPC UA login refused: user %r", username)
        return None


class _TrustedClients:
    """asyncua's certificate validator: a client certificate must be one of those given, valid
    now, and name the client's application URI."""

    def __init__(self, trusted: frozenset[bytes]) -> None:
        from asyncua.crypto.validator import CertificateValidator
        from asyncua.crypto.validator import CertificateValidatorOptions as Opt

        self._trusted = trusted
        self._basic = CertificateValidator(Opt.TIME_RANGE | Opt.URI | Opt.PEER_CLIENT)

    async def __call__(self, cert: x509.Certificate, app_description: Any) -> None:
        from asyncua import ua
        from asyncua.common.utils import ServiceError

        if cert.public_bytes(serialization.Encoding.DER) not in self._trusted:
            log.warning(
                "OPC UA client refused: its certificate (%s) is not in trusted_clients", cert.subject.rfc4514_string()
            )
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        await self._basic.validate(cert, app_description)


def _folder_item(nid: Any, parent: Any, bname: Any, description: str) -> Any:
    """AddNodes: a folder (FolderType), organized by its parent, with its Description."""
    from asyncua import ua

    attrs = ua.ObjectAttributes(
        DisplayName=ua.LocalizedText(bname.Name),
        Description=ua.LocalizedText(description),
        EventNotifier=0,
        WriteMask=0,
        UserWriteMask=0,
    )
    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(ua.ObjectIds.Organizes),
        RequestedNewNodeId=nid,
        BrowseName=bname,
        NodeClass=ua.NodeClass.Object,
        NodeAttributes=attrs,
        TypeDefinition=ua.NodeId(ua.ObjectIds.FolderType),
    )


def _read_only(value: Any, data_type: Any, description: str, bname: Any, sampling_ms: float) -> Any:
    from asyncua import ua

    read = ua.AccessLevel.CurrentRead.mask
    return ua.VariableAttributes(
        DisplayName=ua.LocalizedText(bname.Name),
        Description=ua.LocalizedText(description),
        Value=value,
        DataType=data_type,
        ValueRank=ua.ValueRank.Scalar,
        ArrayDimensions=None,
        AccessLevel=read,
        UserAccessLevel=read,
        MinimumSamplingInterval=sampling_ms,
        Historizing=False,
        WriteMask=0,
        UserWriteMask=0,
    )


def _variable_item(
    nid: Any, parent: Any, bname: Any, description: str, value: Any, sampling_ms: float, type_definition: int
) -> Any:
    """AddNodes: a read-only scalar variable, a component of its folder, of `type_definition`
    (AnalogItemType or BaseDataVariableType)."""
    from asyncua import ua

    data_type = ua.NodeId(value.VariantType.value)  # a built-in type's NodeId is its VariantType's number
    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasComponent),
        RequestedNewNodeId=nid,
        BrowseName=bname,
        NodeClass=ua.NodeClass.Variable,
        TypeDefinition=ua.NodeId(type_definition),
        NodeAttributes=_read_only(value, data_type, description, bname, sampling_ms),
    )


def _property_item(
    nid: Any, parent: Any, name: str, description: str, value: Any, data_type: int, sampling_ms: float
) -> Any:
    """AddNodes: a read-only property (PropertyType, browse name in namespace 0) of a variable."""
    from asyncua import ua

    bname = ua.QualifiedName(name, 0)
    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasProperty),
        RequestedNewNodeId=nid,
        BrowseName=bname,
        NodeClass=ua.NodeClass.Variable,
        TypeDefinition=ua.NodeId(ua.ObjectIds.PropertyType),
        NodeAttributes=_read_only(value, ua.NodeId(data_type), description, bname, sampling_ms),
    )


def _encrypted_passwords(iserver: Any) -> None:
    """Every endpoint's UserName token policy carries Basic256Sha256, so that a client encrypts the
    password with the server's key whatever its channel (asyncua leaves it None on a SignAndEncrypt
    endpoint: the channel's encryption only); a password that comes unencrypted, or with another
    algorithm or server nonce, is refused (Bad_IdentityTokenInvalid)."""
    from asyncua import ua
    from asyncua.common.utils import ServiceError
    from asyncua.crypto import uacrypto
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256 as Policy

    # asyncua's internal server, pinned to 2.1 in pyproject.toml for these two: a version without them
    # must not run with a UserName policy that says None
    if not (
        callable(getattr(iserver, "add_endpoint", None)) and callable(getattr(iserver, "decrypt_user_token", None))
    ):
        raise RuntimeError(
            "this asyncua has no InternalServer.add_endpoint/decrypt_user_token: compd needs asyncua 2.1"
        )
    add = iserver.add_endpoint

    def add_endpoint(edp: Any) -> None:  # asyncua makes the endpoints in Server.start, before it listens
        for token in edp.UserIdentityTokens:
            if token.TokenType == ua.UserTokenType.UserName:
                token.SecurityPolicyUri = Policy.URI
        add(edp)

    def decrypt_user_token(isession: Any, token: Any) -> tuple[str, str]:
        # Part 4 §7.36.3: Password = Encrypt(length ‖ password ‖ the session's server nonce)
        if token.EncryptionAlgorithm != Policy.AsymmetricEncryptionURI:
            log.info(
                "OPC UA login refused: user %r sent the password %s",
                token.UserName,
                f"encrypted with {token.EncryptionAlgorithm}" if token.EncryptionAlgorithm else "unencrypted",
            )
            raise ServiceError(ua.StatusCodes.BadIdentityTokenInvalid)
        data, block = bytes(token.Password or b""), iserver.private_key.key_size // 8
        raw = b"".join(
            uacrypto.decrypt_rsa_oaep(iserver.private_key, data[i : i + block])  # a block per key size
            for i in range(0, len(data), block)
        )
        nonce = isession.nonce or b""
        length = int.from_bytes(raw[:4], "little")
        if (
            len(raw) != 4 + length
            or length < len(nonce)
            or not hmac.compare_digest(raw[4 + length - len(nonce) :], nonce)
        ):
            log.info("OPC UA login refused: user %r's password token is not of this session", token.UserName)
            raise ServiceError(ua.StatusCodes.BadIdentityTokenInvalid)
        return token.UserName, raw[4 : 4 + length - len(nonce)].decode("utf-8")

    iserver.add_endpoint = add_endpoint
    iserver.decrypt_user_token = decrypt_user_token


# ------------------------------------------------------------------ asyncua's log

STACK_EVENT = "opcua_stack"  # the event of asyncua's log lines in compd's event log
STACK_WINDOW_S = 60.0  # one line per distinct asyncua message a window; the repeats counted into the next
STACK_LINES_PER_WINDOW = 20  # at most this many asyncua lines a window in all; the others counted
STACK_KEYS = 256  # distinct messages remembered


class _StackEvents(logging.Handler):
    """asyncua's log records as compd events (`event=opcua_stack`), never raw lines: its logger, level
    and message as fields; its INFO and DEBUG (a line per request) at debug, its WARNING and ERROR at
    warning (a refused client, a bad request: the server goes on); each distinct message (its format)
    at most once per STACK_WINDOW_S, STACK_LINES_PER_WINDOW lines per window in all, what was held
    back counted in the next line (`repeated`, `dropped`)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self._clock = clock
        self._seen: dict[tuple[str, int, str], tuple[float, int]] = {}  # key → (time of its line, repeats since)
        self._window = (-math.inf, 0)  # start of the budget's window, lines in it
        self._dropped = 0
        self.out = logging.getLogger("compd.opcua.stack")

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = logging.DEBUG if record.levelno < logging.WARNING else logging.WARNING
            if not self.out.isEnabledFor(level):
                return
            now = self._clock()
            key = (record.name, record.levelno, str(record.msg))
            last, repeats = self._seen.get(key, (-math.inf, 0))
            if now - last < STACK_WINDOW_S:
                self._seen[key] = (last, repeats + 1)
                return
            start, lines = self._window
            if now - start >= STACK_WINDOW_S:
                start, lines = now, 0
            if lines >= STACK_LINES_PER_WINDOW:
                self._dropped += 1
                return
            self._window = (start, lines + 1)
            self._seen.pop(key, None)
            self._seen[key] = (now, 0)
            while len(self._seen) > STACK_KEYS:
                del self._seen[next(iter(self._seen))]
            extra: dict[str, Any] = {
                "event": STACK_EVENT,
                "stack_logger": record.name,
                "stack_level": record.levelname.lower(),
            }
            if repeats:
                extra["repeated"] = repeats
            if self._dropped:
                extra["dropped"], self._dropped = self._dropped, 0
            if record.exc_info and record.exc_info[1] is not None:
                extra["error"] = f"{type(record.exc_info[1]).__name__}: {record.exc_info[1]}"
            self.out.log(level, "asyncua: %s", record.getMessage(), extra=extra)
        except Exception:  # a log line must never break the server
            self.handleError(record)


_STACK_HANDLER = _StackEvents()


def route_asyncua_logs() -> None:
    """asyncua's loggers into compd's event log through `_StackEvents` (idempotent): no raw line and
    no Python last-resort line; asyncua logs INFO (every request) only while compd logs debug."""
    stack = logging.getLogger("asyncua")
    stack.propagate = False
    if _STACK_HANDLER not in stack.handlers:
        stack.addHandler(_STACK_HANDLER)
    stack.setLevel(logging.INFO if _STACK_HANDLER.out.isEnabledFor(logging.DEBUG) else logging.WARNING)


class OpcUaServer:
    """The OPC UA server of one config: `start` on the first snapshot, `update` with each later one, `stop`."""

    def __init__(self, cfg: OpcUaConfig, base_dir: Path, guard: GuardConfig | None = None) -> None:
        """`guard`: the config's guard section, whose clamps and signal limits are the EURanges
        (None: the guard's defaults)."""
        self.cfg = cfg
        self.base_dir = Path(base_dir)
        self.guard = guard
        self._lock = threading.Lock()
        self._thread: ServiceThread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None  # the server thread's, while it runs
        self._wake: asyncio.Event | None = None
        self._pending: list[Any] | None = None  # the newest values not yet written
        self._stopping = False
        self._variables: list[Variable] = []
        self._folders: dict[str, str] = {}
        self._endpoint: str | None = None
        self._updates = 0
        self._errors = 0
        self._last_error: str | None = None

    # ------------------------------------------------------------ the caller's side
    def start(self, snap: dict[str, Any]) -> str:
        """Build the address space from this first status snapshot, start serving on a thread of
        its own (its own asyncio loop), return the endpoint URL (opc.tcp://HOST:PORT/compd/, the
        real port when `port` is 0). BadInput (one line naming the file) for a certificate, key or
        password file that is missing or unreadable, or a port that is taken. Returns once the
        server accepts connections."""
        if self._thread is not None:
            raise RuntimeError("OpcUaServer.start called twice")
        route_asyncua_logs()
        material = read_material(self.cfg, self.base_dir)
        if "None" in self.cfg.security:
            log.warning("OPC UA security 'None' is offered: that traffic is not encrypted")
        self._variables = address_space(snap, self.guard)
        self._folders = folders(snap)
        values, problems = data_values(self._variables, snap)
        self._count(problems)
        ready: concurrent.futures.Future[str] = concurrent.futures.Future()
        self._thread = ServiceThread("compd-opcua", self._run, material, values, ready)
        self._thread.start()
        try:
            self._endpoint = ready.result(timeout=START_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            self.stop()
            raise BadInput(f"the OPC UA server did not start within {START_TIMEOUT_S:g} s") from None
        except BaseException:
            self.stop()
            raise
        return self._endpoint

    def update(self, snap: dict[str, Any]) -> None:
        """Write this snapshot's values. Thread-safe and quick: the values are computed here and
        handed to the server's loop, which writes the newest it has (never waits for a client).
        Axes and signals not in the first snapshot are ignored (a reload builds a new server)."""
        values, problems = data_values(self._variables, snap)
        self._count(problems)
        with self._lock:
            if self._loop is None or self._stopping:
                return
            wake = self._pending is None  # else a wake-up is already on its way
            self._pending = values
            if wake:
                self._loop.call_soon_threadsafe(self._wake.set)  # type: ignore[union-attr]

    def stop(self) -> None:
        """Stop serving, join the thread, close the sockets. Idempotent."""
        with self._lock:
            self._stopping = True
            if self._loop is not None:
                self._loop.call_soon_threadsafe(self._wake.set)  # type: ignore[union-attr]
        thread = self._thread
        if thread is not None and not thread.is_current():
            thread.join(STOP_TIMEOUT_S)

    def get_status(self) -> dict[str, Any]:
        """The endpoint, the snapshots written, the snapshots that had a problem and the last one."""
        with self._lock:
            return {
                "endpoint": self._endpoint,
                "updates": self._updates,
                "errors": self._errors,
                "last_error": self._last_error,
            }

    def _count(self, problems: list[str]) -> None:
        if not problems:
            return
        # a value of the wrong type first: it says more about the snapshot than a key it lacks
        first = sorted(problems, key=lambda p: ": KeyError: " in p)[:3]
        line = f"{len(problems)} value(s) missing or of the wrong type: " + "; ".join(first)
        with self._lock:
            self._errors += 1
            new = line != self._last_error
            self._last_error = line
        if new:  # once per kind of problem, not once a second
            log.warning("OPC UA: %s", line)

    # ------------------------------------------------------------ the server thread
    def _run(self, material: Material, values: list[Any], ready: concurrent.futures.Future[str]) -> None:
        try:
            asyncio.run(self._serve(material, values, ready))
        except Exception as e:
            if not ready.done():
                ready.set_exception(e)
            else:
                log.exception("the OPC UA server failed")
        finally:
            with self._lock:
                self._loop = None

    async def _serve(self, material: Material, values: list[Any], ready: concurrent.futures.Future[str]) -> None:
        from asyncua import Server, ua

        cfg = self.cfg
        server = Server(user_manager=_Users(material.passwords, cfg.anonymous, "None" in cfg.security))
        await server.init()
        host = f"[{cfg.bind}]" if ":" in cfg.bind else cfg.bind
        server.set_endpoint(f"opc.tcp://{host}:{cfg.port}/compd/")
        server.set_server_name("compd")
        server.product_uri = "urn:compd"
        await server.set_application_uri(material.application_uri)
        await server.set_build_info("urn:compd", "compd", "compd", version(), version(), datetime.now(UTC))
        server.set_security_policy([getattr(ua.SecurityPolicyType, _POLICIES[p]) for p in cfg.security])
        server.set_identity_tokens(
            ([ua.UserNameIdentityToken] if material.passwords else [])
            + ([ua.AnonymousIdentityToken] if cfg.anonymous else [])
        )
        _encrypted_passwords(server.iserver)
        await server.load_certificate(material.certificate.public_bytes(serialization.Encoding.DER), format="der")
        await server.load_private_key(
            material.private_key.private_bytes(
                serialization.Encoding.DER, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            ),
            format="der",
        )
        if material.trusted is not None:
            server.set_certificate_validator(_TrustedClients(material.trusted))
        node_ids = await self._build(server, await server.register_namespace(cfg.namespace_uri))
        await self._write(server, node_ids, values)
        try:
            await server.start()
        except OSError as e:
            raise BadInput(f"opcua: cannot listen on {cfg.bind}:{cfg.port}: {e.strerror or e}") from None
        try:
            url = f"opc.tcp://{host}:{server.bserver.port}/compd/"  # type: ignore[union-attr]
            server.set_endpoint(url)
            for edp in server.iserver.endpoints:  # they were made before the port was known
                edp.EndpointUrl = url
                edp.Server.DiscoveryUrls = [url]
            self._wake = asyncio.Event()
            with self._lock:
                self._loop = asyncio.get_running_loop()
                if self._stopping:  # stop() came while starting (start timed out)
                    self._wake.set()
            ready.set_result(url)
            await self._pump(server, node_ids)
        finally:
            await server.stop()

    async def _pump(self, server: Any, node_ids: list[Any]) -> None:
        """Write the newest values handed over by `update` until `stop`."""
        assert self._wake is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            with self._lock:
                values, self._pending = self._pending, None
                if self._stopping:
                    return
            if values is None:
                continue
            try:
                await self._write(server, node_ids, values)
            except Exception as e:  # asyncua's: keep serving, count it
                log.exception("OPC UA: writing the values failed")
                self._count([f"write: {type(e).__name__}: {e}"])
                continue
            with self._lock:
                self._updates += 1

    async def _build(self, server: Any, idx: int) -> list[Any]:
        """The folders, variables and their properties under Objects/compd (one AddNodes call); the
        variables' NodeIds, in order."""
        from asyncua import ua

        sampling_ms = self.cfg.period_s * 1000.0  # the service writes a snapshot once a period_s (host.py)
        items: list[Any] = []
        made: set[str] = set()
        node_ids = []
        for var in self._variables:
            *path, name = var.node_id.split(".")
            for depth in range(1, len(path) + 1):
                key = ".".join(path[:depth])
                if key not in made:
                    made.add(key)
                    parent = ua.NodeId(".".join(path[: depth - 1]), idx) if depth > 1 else server.nodes.objects.nodeid
                    items.append(
                        _folder_item(
                            ua.NodeId(key, idx),
                            parent,
                            ua.QualifiedName(path[depth - 1], idx),
                            self._folders.get(key, ""),
                        )
                    )
            nid = ua.NodeId(var.node_id, idx)
            items.append(
                _variable_item(
                    nid,
                    ua.NodeId(".".join(path), idx),
                    ua.QualifiedName(name, idx),
                    var.description,
                    ua.Variant(_ZERO[var.data_type], getattr(ua.VariantType, var.data_type)),
                    sampling_ms,
                    ua.ObjectIds.AnalogItemType if var.analog else ua.ObjectIds.BaseDataVariableType,
                )
            )
            if var.eu_range is not None:
                r = var.eu_range
                items.append(
                    _property_item(
                        ua.NodeId(var.node_id + ".EURange", idx),
                        nid,
                        "EURange",
                        f"the range of values likely in normal operation (OPC UA Part 8 EURange): {r.source}",
                        ua.Variant(ua.Range(Low=float(r.low), High=float(r.high)), ua.VariantType.ExtensionObject),
                        ua.ObjectIds.Range,
                        sampling_ms,
                    )
                )
            if var.unit is not None:
                items.append(
                    _property_item(
                        ua.NodeId(var.node_id + ".EngineeringUnits", idx),
                        nid,
                        "EngineeringUnits",
                        f"the unit of the value: {var.unit.description} (UNECE Recommendation 20 code"
                        f" {var.unit.unece})",
                        ua.Variant(var.unit.eu_information(), ua.VariantType.ExtensionObject),
                        ua.ObjectIds.EUInformation,
                        sampling_ms,
                    )
                )
            node_ids.append(nid)
        results = await server.iserver.isession.add_nodes(items)
        for item, res in zip(items, results, strict=True):
            if not res.StatusCode.is_good():
                raise RuntimeError(f"OPC UA: adding {item.RequestedNewNodeId} failed: {res.StatusCode.name}")
        return node_ids

    async def _write(self, server: Any, node_ids: list[Any], values: list[Any]) -> None:
        for node_id, dv in zip(node_ids, values, strict=True):
            await server.write_attribute_value(node_id, dv)


_POLICIES = {
    "Basic256Sha256_SignAndEncrypt": "Basic256Sha256_SignAndEncrypt",
    "Basic256Sha256_Sign": "Basic256Sha256_Sign",
    "None": "NoSecurity",
}
_ZERO = {"Double": 0.0, "UInt16": 0, "UInt64": 0, "Boolean": False, "String": ""}  # before the first write
