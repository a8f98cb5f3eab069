"""The strict config base: YAML read within bounds, the Strict model, and the sections every stage reads.

The top-level sections are pydantic models with unknown keys forbidden. The
`sources`, `model` and `sink` sections are validated in a second pass against the
`Config` (or `Params`) model of the class that their `kind` names, found through the
registries, so each driver owns its options (STYLE: one config section, one module).
"""

from __future__ import annotations

import difflib
import os
import platform
import stat
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from compd.codec import MAX_MAG
from compd.core.errors import ConfigError

PathT = tuple[str | int, ...]


class Strict(BaseModel):
    """Base of every config model: unknown keys are errors, values are immutable, and every
    number is finite (`.inf`/`.nan` would switch a limit off)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


PositiveS = Annotated[float, Field(gt=0)]

# Physical bounds shared by several sections (see docs/configuration.md).
SIGNAL_ABS_MAX = 1e6  # any signal: °C, rpm (≤ 10⁵), mm, A — a limit beyond ±10⁶ is a typo
MAX_CORRECTION_UM = 10_000.0  # 10 mm: thermal errors are tens to hundreds of µm
MIN_SLEW_UM_PER_S = 1e-4  # 0.36 µm/h: slower never follows a thermal drift
MAX_SLEW_UM_PER_S = 1000.0  # 1 mm/s: a faster "slew limit" limits nothing


# --------------------------------------------------------------------------- YAML


@dataclass
class Document:
    """A parsed YAML file and the line (1-based) of every key path in it."""

    data: Any
    file: str
    lines: dict[PathT, int] = field(default_factory=dict)

    def line_of(self, path: PathT) -> int | None:
        """The line of `path`, or of its nearest ancestor that has one."""
        path = tuple(path)
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return self.lines.get(())

    def error(self, message: str, path: PathT) -> ConfigError:
        return ConfigError(message, file=self.file, line=self.line_of(path), path=path)


# Limits of the YAML reader: a config or model file is refused (exit 2, one line) rather
# than read without bound. The example configs are under 2 KB; a fitted lvr model of 19
# sensors is 11 KB and grows with sensors² (its covariance), so 4 MiB holds ~400 sensors.
CONFIG_MAX_BYTES = 1 << 20  # 1 MiB
MODEL_MAX_BYTES = 4 << 20  # 4 MiB
MAX_SECRET_BYTES = 4096  # a password file (telemetry, OPC UA users): a secret, not a document
MAX_DEPTH = 64  # nesting of mappings and lists (the examples nest 5 deep)
MAX_ALIAS_VALUES = 10_000  # values reached through aliases (*name, <<: *name), after expansion
CONFIG_MAX_VALUES = 100_000  # scalars, lists and mappings in a config (the examples: < 200)
MODEL_MAX_VALUES = 1_000_000  # in a model file (the 19-sensor lvr: ~1 000)

_MERGE_TAG = "tag:yaml.org,2002:merge"


class _Limit(Exception):
    """A YAML limit was hit at `line` (1-based, or None)."""

    def __init__(self, message: str, line: int | None) -> None:
        super().__init__(message)
        self.message = message
        self.line = line


def read_bounded(file: str, max_bytes: int) -> str:
    """A regular file's text, refused when it is larger than `max_bytes`.

    Opened non-blocking, so a FIFO without a writer does not hang the open; a
    directory, FIFO, socket or device (/dev/zero) is refused after `fstat`.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(file, flags)
    except OSError as e:
        raise ConfigError(f"cannot read: {e.strerror or e}", file=file) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError("cannot read: is a directory", file=file)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError("cannot read: not a regular file (a device, FIFO or socket)", file=file)
        if st.st_size > max_bytes:
            raise ConfigError(f"file is {st.st_size} bytes, larger than the limit of {max_bytes}", file=file)
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > max_bytes:  # it grew after fstat
            raise ConfigError(f"file is larger than the limit of {max_bytes} bytes", file=file)
    except OSError as e:
        raise ConfigError(f"cannot read: {e.strerror or e}", file=file) from None
    finally:
        os.close(fd)
    try:
        return b"".join(chunks).decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError("not a UTF-8 text file", file=file) from None


_Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when built with it: 6× faster


def _compose(loader: Any, max_values: int) -> yaml.Node | None:
    """The single document's node tree, composed from parser events without recursion.

    PyYAML's own composer recurses once per level (RecursionError at ~300 levels, and
    libyaml's composer segfaults on 200 000 nested `[`); this one stops at MAX_DEPTH.
    """
    loader.get_event()  # stream start
    if loader.check_event(yaml.StreamEndEvent):
        loader.get_event()
        return None
    loader.get_event()  # document start
    anchors: dict[str, yaml.Node] = {}
    stack: list[list[Any]] = []  # [collection node, pending key node or None]
    root: yaml.Node | None = None
    count = 0
    while root is None or stack:
        ev = loader.get_event()
        count += 1
        if count > max_values:
            raise _Limit(f"more than {max_values} values", ev.start_mark.line + 1)
        node: yaml.Node
        if isinstance(ev, yaml.AliasEvent):
            if ev.anchor not in anchors:
                raise yaml.composer.ComposerError(None, None, f"found undefined alias {ev.anchor!r}", ev.start_mark)
            node = anchors[ev.anchor]
        elif isinstance(ev, yaml.ScalarEvent):
            tag = ev.tag
            if tag is None or tag == "!":
                tag = loader.resolve(yaml.ScalarNode, ev.value, ev.implicit)
            node = yaml.ScalarNode(tag, ev.value, ev.start_mark, ev.end_mark, style=ev.style)
        elif isinstance(ev, yaml.SequenceStartEvent | yaml.MappingStartEvent):
            if len(stack) >= MAX_DEPTH:
                raise _Limit(f"nested deeper than {MAX_DEPTH} levels", ev.start_mark.line + 1)
            kind = yaml.SequenceNode if isinstance(ev, yaml.SequenceStartEvent) else yaml.MappingNode
            tag = ev.tag
            if tag is None or tag == "!":
                tag = loader.resolve(kind, None, ev.implicit)
            node = kind(tag, [], ev.start_mark, None, flow_style=ev.flow_style)
        elif isinstance(ev, yaml.SequenceEndEvent | yaml.MappingEndEvent):
            stack.pop()[0].end_mark = ev.end_mark
            continue
        else:  # the parser only emits these in order; anything else is a bug of ours
            raise yaml.composer.ComposerError(None, None, f"unexpected {type(ev).__name__}", ev.start_mark)
        anchor = getattr(ev, "anchor", None)
        if anchor is not None and not isinstance(ev, yaml.AliasEvent):
            anchors[anchor] = node
        if not stack:
            root = node
        elif isinstance(stack[-1][0], yaml.SequenceNode):
            stack[-1][0].value.append(node)
        elif stack[-1][1] is None:
            stack[-1][1] = node
        else:
            stack[-1][0].value.append((stack[-1][1], node))
            stack[-1][1] = None
        if isinstance(node, yaml.SequenceNode | yaml.MappingNode) and not isinstance(ev, yaml.AliasEvent):
            stack.append([node, None])
    loader.get_event()  # document end
    if not loader.check_event(yaml.StreamEndEvent):
        raise _Limit("one YAML document per file; found a second", loader.peek_event().start_mark.line + 1)
    loader.get_event()
    return root


def load_yaml(
    file: str | Path,
    text: str | None = None,
    max_bytes: int = CONFIG_MAX_BYTES,
    max_values: int = CONFIG_MAX_VALUES,
) -> Document:
    """Parse a YAML file keeping each key's line; syntax errors are ConfigError.

    Bounded: at most `max_bytes` (regular files only) holding `max_values` values,
    MAX_DEPTH levels of nesting and MAX_ALIAS_VALUES values reached through aliases,
    so no input hangs or overflows the stack.
    """
    file = str(file)
    if text is None:
        text = read_bounded(file, max_bytes)
    elif len(text) > max_bytes:
        raise ConfigError(f"text is {len(text)} characters, larger than the limit of {max_bytes}", file=file)
    loader = _Loader(text)
    doc = Document(None, file)
    try:
        node = _compose(loader, max_values)
        if node is not None:
            doc.data = _Builder(loader, doc).build(node, ())
    except _Limit as e:
        raise ConfigError(e.message, file=file, line=e.line) from None
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = str(e.problem or e)
        if "nesting" in problem:  # some libyaml builds stop at their own depth before MAX_DEPTH
            problem = f"nested deeper than the YAML parser allows ({problem})"
        raise ConfigError(f"YAML syntax: {problem}", file=file, line=line) from None
    except yaml.YAMLError as e:
        raise ConfigError(f"YAML: {e}", file=file) from None
    finally:
        loader.dispose()
    return doc


class _Builder:
    """Composed nodes → plain data with each key's line, within the limits."""

    def __init__(self, loader: Any, doc: Document) -> None:
        self.loader = loader
        self.doc = doc
        self.seen: set[int] = set()
        self.via_alias = 0

    def build(self, node: yaml.Node, path: PathT) -> Any:
        line = node.start_mark.line + 1
        if len(path) > MAX_DEPTH:  # an alias placed deep, or an alias inside its own anchor
            raise _Limit(f"nested deeper than {MAX_DEPTH} levels (aliases expanded)", line)
        if id(node) in self.seen:
            self.via_alias += 1
            if self.via_alias > MAX_ALIAS_VALUES:
                raise _Limit(f"aliases expand to more than {MAX_ALIAS_VALUES} values", line)
        else:
            self.seen.add(id(node))
        self.doc.lines.setdefault(path, line)
        if isinstance(node, yaml.MappingNode):
            return self._mapping(node, path)
        if isinstance(node, yaml.SequenceNode):
            return [self.build(item, (*path, i)) for i, item in enumerate(node.value)]
        try:
            return self.loader.construct_object(node, deep=True)
        except (ValueError, OverflowError) as e:  # e.g. an integer of more than 4300 digits
            raise _Limit(f"bad value: {e}", line) from None

    def _mapping(self, node: yaml.MappingNode, path: PathT) -> dict[str, Any]:
        merged: dict[str, Any] = {}
        out: dict[str, Any] = {}
        for key_node, value_node in node.value:
            kline = key_node.start_mark.line + 1
            if key_node.tag == _MERGE_TAG:  # `<<: *base` or `<<: [*a, *b]`; explicit keys win
                subs = value_node.value if isinstance(value_node, yaml.SequenceNode) else [value_node]
                for sub in reversed(subs):  # the first mapping listed wins
                    if not isinstance(sub, yaml.MappingNode):
                        raise _Limit("'<<' merges mappings only", kline)
                    merged.update(self.build(sub, path))
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                raise ConfigError("keys must be plain names", file=self.doc.file, line=kline, path=path)
            key = self.build(key_node, path)
            if not isinstance(key, str | int | float | bool) or key is None:
                raise ConfigError("keys must be plain names", file=self.doc.file, line=kline, path=path)
            key = str(key)
            sub_path = (*path, key)
            if key in out:
                raise ConfigError("duplicate key", file=self.doc.file, line=kline, path=sub_path)
            self.doc.lines[sub_path] = kline
            out[key] = self.build(value_node, sub_path)
        return {**merged, **out} if merged else out


# ---------------------------------------------------------------- pydantic errors


def _unwrap(annotation: Any) -> list[Any]:
    """The classes inside Optional/Union/Annotated/list/dict annotations."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _unwrap(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [c for a in typing.get_args(annotation) for c in _unwrap(a)]
    if origin in (list, tuple, dict):
        args = typing.get_args(annotation)
        return _unwrap(args[-1]) if args else []
    return [annotation]


def _model_at(model: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model class that owns the last key of `loc`."""
    current: Any = model
    for part in loc[:-1]:
        if isinstance(part, int) or not (isinstance(current, type) and issubclass(current, BaseModel)):
            continue
        f = current.model_fields.get(part)
        if f is None:
            return None
        candidates = [c for c in _unwrap(f.annotation) if isinstance(c, type) and issubclass(c, BaseModel)]
        if not candidates:
            return None
        current = candidates[0]
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def validate(model: type[Strict], data: Any, doc: Document, base: PathT = (), what: str = "section") -> Any:
    """Validate `data` against `model`; the first error becomes a ConfigError."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise doc.error(f"expected a mapping for this {what}, got {type(data).__name__}", base)
    try:
        return model.model_validate(data)
    except ValidationError as e:
        errors = e.errors()
        err = errors[0]
        if err["type"] == "missing":  # a key misspelt is both unknown and missing: name the misspelling
            err = next(
                (
                    x
                    for x in errors
                    if x["type"] == "extra_forbidden" and tuple(x["loc"])[:-1] == tuple(err["loc"])[:-1]
                ),
                err,
            )
        raw = tuple(err["loc"])
        if err["type"] == "extra_forbidden" and raw:  # the last part is the user's key, whatever it holds
            loc = (*(p for p in raw[:-1] if not (isinstance(p, str) and "[" in p)), raw[-1])
        else:
            loc = tuple(p for p in raw if not (isinstance(p, str) and "[" in p))
        path = (*base, *loc)
        if err["type"] == "extra_forbidden":
            owner = _model_at(model, loc)
            known = sorted(owner.model_fields) if owner else []
            close = difflib.get_close_matches(str(loc[-1]), known, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            msg = f"unknown key{hint} (known: {', '.join(known)})" if known else "unknown key"
        elif err["type"] == "missing":
            msg = "required key is missing"
        else:
            msg = err["msg"]
            if (
                "input" in err and err["type"] not in ("model_type", "dict_type") and not isinstance(err["input"], dict)
            ):  # a whole section is no help in a one-line message
                msg += f" (got {err['input']!r})"
        raise doc.error(msg, path) from None


# -------------------------------------------------------------- top-level schema


class RealtimeConfig(Strict):
    """Real-time options; compd applies what the OS permits and logs the rest."""

    scheduler: Literal["other", "fifo"] = Field(
        "other", description="scheduling policy of the cycle thread (fifo needs realtime.conf)"
    )
    priority: int = Field(50, ge=1, le=99, description="SCHED_FIFO priority of the cycle thread")
    cpu_affinity: list[Annotated[int, Field(ge=0, le=1023)]] | None = Field(
        None, description="CPUs the cycle thread may run on; none = any"
    )
    lock_memory: bool = Field(
        False,
        description="lock memory against paging (mlockall; each page from when it is first touched,"
        " MCL_ONFAULT, where the kernel has it)",
    )


class PlantClockConfig(Strict):
    """Where a simulated plant publishes its clock (its clock device's register map, over Modbus TCP)."""

    host: str = Field("127.0.0.1", description="the plant's Modbus TCP address")
    port: int = Field(ge=1, le=65535, description="the plant's Modbus TCP port")
    device_id: int = Field(1, ge=0, le=247, description="unit id of the plant's register map")
    address: int = Field(0, ge=0, le=65534, description="plant time, ms, uint32 in two registers (high first)")
    poll_period_s: float = Field(0.001, ge=0.0001, le=1, description="wall time between clock reads")
    stall_s: float = Field(0.5, ge=0.01, le=3600, description="wall time without plant progress before a wait gives up")
    lockstep: bool = Field(
        False,
        description="test and acceptance runs: the plant holds its time until compd has finished its"
        " cycle (sink writes acknowledged by the CNC) and asks for the next; sources are read once per"
        " cycle at the plant time, so a run gives the same result on a busy machine (poll_period_s and"
        " stall_s are not used then)",
    )


def stores_in_order() -> bool:
    """Whether this CPU makes stores visible to other CPUs in program order (x86-64), which the
    seqlocks of compd.io.mailbox rely on between processes."""
    return platform.machine().lower() in ("x86_64", "amd64")


class LoopConfig(Strict):
    """The fixed-period cycle."""

    period_s: float = Field(
        0.002,
        ge=0.0005,
        le=60,
        description="cycle period (0.5 ms: below that Python cannot keep a schedule; 60 s: thermal"
        " time constants are tens of minutes, a slower cycle no longer follows them)",
    )
    clock: Literal["wall", "sim", "plant"] = Field(
        "wall",
        description="wall time, simulated time, or a plant's clock (plant_clock): then every"
        " time in the config (period, Δτ, slew, staleness, --duration) is plant time",
    )
    plant_clock: PlantClockConfig | None = Field(None, description="clock: plant — where to read it")
    speedup: float = Field(
        0.0, ge=0, le=1e6, description="sim clock only: simulated seconds per wall second, 0 = flat out"
    )
    spin_margin_s: float = Field(
        0.0002, ge=0, le=0.01, description="sleep until this long before a deadline, then spin"
    )
    duration_s: float | None = Field(
        None, gt=0, le=1e9, description="stop after this long (loop time; 1e9 s is 31 years)"
    )
    gil_switch_interval_s: float = Field(
        0.0001,
        gt=0,
        le=0.005,
        description="wall clock: how soon a thread holding the GIL must hand it to the waking cycle",
    )
    io: Literal["process", "thread"] = Field(
        default_factory=lambda: "process" if stores_in_order() else "thread",
        description="wall clock: where device I/O and the service (status, metrics, logs) run — a process"
        " of its own each (their Python never holds the GIL the cycle needs) or threads of the daemon"
        " (other clocks: always threads). process needs x86-64 (its shared-memory mailboxes rely on its"
        " store order); elsewhere the default is thread",
    )
    realtime: RealtimeConfig = Field(RealtimeConfig(), description="real-time options")

    @model_validator(mode="after")
    def _plant_clock(self) -> LoopConfig:
        if self.clock == "plant" and self.plant_clock is None:
            raise ValueError("clock: plant needs a plant_clock section")
        return self

    @field_validator("io")
    @classmethod
    def _io_on_this_cpu(cls, io: str) -> str:
        if io == "process" and not stores_in_order():
            raise ValueError(
                f"process needs an x86-64 CPU (the mailboxes between processes rely on its store"
                f" order); this one is {platform.machine() or 'unknown'}: set io: thread"
            )
        return io


class SignalLimits(Strict):
    """Plausibility limits of one signal."""

    min: float = Field(
        -40.0,
        ge=-SIGNAL_ABS_MAX,
        le=SIGNAL_ABS_MAX,
        description="lowest plausible value (°C for temperatures; any signal's unit: rpm, mm, A)",
    )
    max: float = Field(150.0, ge=-SIGNAL_ABS_MAX, le=SIGNAL_ABS_MAX, description="highest plausible value; above min")
    max_rate_per_s: float | None = Field(None, gt=0, le=SIGNAL_ABS_MAX, description="largest plausible change per s")
    rate_allowance: float = Field(
        0.3,
        ge=0,
        le=SIGNAL_ABS_MAX,
        description="added to max_rate_per_s × dt: room for noise and quantization",
    )
    stale_after_s: float | None = Field(
        None, gt=0, le=86400, description="older than this is stale; longer than loop.period_s"
    )
    frozen_after_s: float | None = Field(
        None,
        gt=0,
        le=7 * 86400,
        description="a value that has not changed by more than frozen_band for this long, while"
        " another model input changed, is frozen (a stuck transmitter); none = not checked;"
        " longer than loop.period_s",
    )
    frozen_band: float = Field(0.0, ge=0, le=SIGNAL_ABS_MAX, description="a change of at most this much is no change")

    @model_validator(mode="after")
    def _order(self) -> SignalLimits:
        if not self.min < self.max:
            raise ValueError(f"min ({self.min:g}) must be below max ({self.max:g})")
        return self


# what an axis or a contribution does when an input it needs goes bad (compd.cycle.limiter.Policy:
# the enum these names stand for)
FaultPolicy = Literal["hold", "ramp_to_zero", "disable"]


class AxisGuardConfig(Strict):
    """Per-axis overrides of the guard."""

    fault_policy: FaultPolicy | None = Field(None, description="this axis's fault policy; none = guard.fault_policy")
    max_abs_um: float | None = Field(
        None, gt=0, le=MAX_CORRECTION_UM, description="this axis's clamp; none = guard.max_abs_um"
    )
    max_slew_um_per_s: float | None = Field(
        None,
        ge=MIN_SLEW_UM_PER_S,
        le=MAX_SLEW_UM_PER_S,
        description="this axis's slew limit; none = guard.max_slew_um_per_s",
    )


class GuardConfig(Strict):
    """What reaches the machine: plausibility, clamp, slew, fault policy."""

    max_abs_um: float = Field(
        63.0,
        gt=0,
        le=MAX_CORRECTION_UM,
        description="magnitude clamp on the correction (thermal errors are tens to hundreds of µm)",
    )
    max_slew_um_per_s: float = Field(
        5.0,
        ge=MIN_SLEW_UM_PER_S,
        le=MAX_SLEW_UM_PER_S,
        description="largest rate of change (thermal errors drift by µm per minute)",
    )
    fault_policy: FaultPolicy = Field("hold", description="what an axis does when an input it needs goes bad")
    ramp_um_per_s: float = Field(1.0, ge=MIN_SLEW_UM_PER_S, le=MAX_SLEW_UM_PER_S, description="ramp_to_zero rate")
    recovery_s: float = Field(5.0, ge=0, le=3600, description="inputs good this long before recovery")
    stale_after_s: float = Field(
        5.0, gt=0, le=86400, description="default staleness limit of a signal; longer than loop.period_s"
    )
    signals: dict[str, SignalLimits] = Field(default_factory=dict, description="plausibility limits by signal name")
    axes: dict[str, AxisGuardConfig] = Field(default_factory=dict, description="per-axis overrides by axis name")

    def clamp_um(self, axis: str) -> tuple[float, str]:
        """The clamp of `axis` (µm) and the key that sets it: its own override, else guard.max_abs_um."""
        own = self.axes.get(axis)
        if own is not None and own.max_abs_um:
            return float(own.max_abs_um), f"guard.axes.{axis}.max_abs_um"
        return float(self.max_abs_um), "guard.max_abs_um"

    def slew_um_per_s(self, axis: str) -> float:
        """The slew limit of `axis` (µm/s): its own override, else guard.max_slew_um_per_s."""
        own = self.axes.get(axis)
        return float((own.max_slew_um_per_s if own else None) or self.max_slew_um_per_s)


class CodecConfig(Strict):
    """The 16-bit word of paper 002 (docs/formats.md)."""

    lsb_um: float = Field(
        1.0,
        ge=0.01,
        le=100,
        description="µm per magnitude LSB (63 LSB of 0.01 µm to 100 µm: 0.63 µm to 6.3 mm full scale)",
    )
    deadband_um: float = Field(
        1.0,
        ge=0,
        le=100,
        description=(
            "|c| at or below this is sent as disabled; the word moves once the correction is"
            " max(deadband_um, lsb_um) from it, one LSB at a time at the slew limit, and settles"
            " within that of it; below full scale (63 × lsb_um)"
        ),
    )
    axes: list[str] | None = Field(
        None,
        max_length=2,
        description="the axes the word drives, high byte first; every output of the model (each"
        " contribution's, the shadow's) is one of them (default: the first model's outputs, in order)",
    )

    @model_validator(mode="after")
    def _deadband_below_full_scale(self) -> CodecConfig:
        if not self.deadband_um < MAX_MAG * self.lsb_um:
            raise ValueError(
                f"deadband_um {self.deadband_um:g} is not below the word's full scale"
                f" ({MAX_MAG} × lsb_um = {MAX_MAG * self.lsb_um:g} µm): every correction would be sent disabled"
            )
        return self


class LogConfig(Strict):
    """The CSV data log."""

    path: str | None = Field(None, description="log file; none = no log")
    period_s: float = Field(1.0, ge=0.0005, le=86400, description="one row per this period, plus every word change")
    flush_s: float = Field(1.0, ge=0.01, le=3600, description="flush to disk at least this often")
    rotate_bytes: int | None = Field(
        None, ge=1024, le=1 << 40, description="start a new file when the log reaches this size; none = never"
    )
    rotate_s: float | None = Field(
        None, ge=1, le=366 * 86400, description="start a new file after this long (wall time); none = never"
    )
    keep: int = Field(5, ge=0, le=1000, description="rotated files kept (<name>.1 newest)")


class ConsoleConfig(Strict):
    """A live table on stdout (demo, commissioning)."""

    period_s: float = Field(0.0, ge=0, le=86400, description="one row per this much loop time; 0 = off")
    summary: bool = Field(True, description="print RMS without/with compensation at exit")


class AdaptConfig(Strict):
    """Probe-updated compensation (compd.cycle.adapt): a Kalman filter per axis on the model's offset (and gain)."""

    apply: bool = Field(True, description="add the estimate to the prediction; false = estimate and show only")
    gain: bool = Field(False, description="also estimate a gain error g on the prediction (ê = p + b + g p)")
    sigma_um: float = Field(0.3, gt=0, le=100, description="a probe's σ when it does not carry its own, µm")
    gate_sigma: float = Field(
        4.0, ge=1, le=100, description="reject a probe whose innovation exceeds this many of its σ"
    )
    model_sigma_um: float | None = Field(
        None,
        ge=0,
        le=1000,
        description="σ of the model's own error at a probe (it moves from probe to probe, a probe cannot tell it"
        " from an offset), µm; none = the model's held-out RMSE from its fit (its file's fit.held_out_rmse_um),"
        " 0 when the file has none",
    )
    apply_above_sigma: float = Field(
        2.0,
        ge=0,
        le=100,
        description="apply the estimate's correction c only as far as it stands out from its own σ where the axis"
        " is: c·max(0, 1 − (k σ_c/c)²) with this k (0 = apply the estimate as it is)",
    )
    initial_offset_sigma_um: float | None = Field(
        None,
        gt=0,
        le=1000,
        description="σ of the offset before the first probe, µm; none = the model's own error σ_m (5 when it is 0)",
    )
    initial_gain_sigma: float = Field(0.2, gt=0, le=10, description="σ of the gain error before the first probe")
    offset_drift_um_per_sqrt_h: float = Field(
        0.3, ge=0, le=1000, description="random walk of the offset between probes, µm per √h"
    )
    gain_drift_per_sqrt_h: float = Field(0.02, ge=0, le=10, description="random walk of the gain error, per √h")
    slope_position: dict[str, str] = Field(
        default_factory=dict,
        description="axis → the signal of its position (mm): also estimate a slope over the position there",
    )
    slope_ref_mm: float = Field(0.0, ge=-1e5, le=1e5, description="position where the slope term is zero, mm")
    initial_slope_sigma_um_per_m: float = Field(
        10.0, gt=0, le=1e4, description="σ of the slope before the first probe, µm/m"
    )
    slope_drift_um_per_m_sqrt_h: float = Field(
        2.0, ge=0, le=1e4, description="random walk of the slope between probes, µm/m per √h"
    )
    stale_after_s: float = Field(
        14400.0, gt=0, le=30 * 86400, description="no probe for this long: the estimate is stale"
    )
    stale_policy: Literal["hold", "decay"] = Field(
        "hold", description="a stale estimate holds, or decays to zero with decay_tau_s"
    )
    decay_tau_s: float = Field(7200.0, gt=0, le=30 * 86400, description="time constant of the decay, s")
    reject_fault_after: int = Field(
        3, ge=1, le=1000, description="this many probes rejected in a row raise a fault event"
    )
    socket_path: str | None = Field(
        None,
        description="Unix socket `compd probe` talks to (relative to the config); none = beside the status"
        " file (status.json → status.sock), and none without a status file",
    )


class InhibitAxisConfig(Strict):
    """One axis's own signals from the machine."""

    signal: str | None = Field(
        None, description="a signal (any source's) that inhibits this axis when on, beside inhibit.signal"
    )
    referenced: str | None = Field(
        None,
        description="a signal that is on once the axis is referenced; until then (and whenever it is off"
        " or bad) the axis waits at 0 (`waiting for reference`)",
    )


class InhibitConfig(Strict):
    """Compensation held off from the machine: an inhibit bit, and per axis a reference bit.

    A held axis ramps its correction to 0 at its slew limit (never a step) and ramps back
    to the model's correction at the same slew once released. A signal that is not good
    (comms lost, stale) counts as inhibiting, a bad reference signal as not referenced."""

    signal: str | None = Field(
        None,
        description="a signal (any source's: a register bit, `bit` of a modbus channel, or a coil or discrete"
        " input of a modbus source with `function: coils`) that inhibits every axis when on (value not 0)",
    )
    invert: bool = Field(False, description="the inhibit signals are enables: 0 inhibits, not 0 releases")
    stale_after_s: float = Field(
        1.0, gt=0, le=3600, description="an inhibit or reference sample older than this counts as bad"
    )
    axes: dict[str, InhibitAxisConfig] = Field(
        default_factory=dict, description="per axis (a model output): its own inhibit and reference signals"
    )


class StateConfig(Strict):
    """Where model state (AR memory, T0 references) is persisted."""

    path: str | None = Field(None, description="state file (relative to the config); none = not kept")


class StatusConfig(Strict):
    """The live status file that `compd status` reads, rewritten by the daemon's service process."""

    path: str | None = Field(
        None,
        description="JSON status file (relative to the config); none = $RUNTIME_DIRECTORY/status.json"
        " under systemd, else no status file",
    )
    period_s: float = Field(1.0, ge=0.05, le=60, description="how often the file is rewritten")


class MetricsConfig(Strict):
    """Prometheus metrics over HTTP (needs the `metrics` extra: prometheus-client)."""

    enabled: bool = Field(False, description="serve /metrics")
    bind: str = Field("127.0.0.1", min_length=1, description="address to listen on")
    port: int = Field(9105, ge=0, le=65535, description="TCP port; 0 = any free port")


class LoggingConfig(Strict):
    """Event log lines on stderr (journald under systemd): one line per event, never per cycle."""

    level: Literal["debug", "info", "warning", "error"] = Field("info", description="lowest level printed")


SPARKPLUG_ID = r"^[^/+#]+$"  # a Sparkplug group, edge node or device id: no topic separators or wildcards


class TlsConfig(Strict):
    """TLS to the broker: the CA that signed its certificate, and this machine's own when the broker asks for one."""

    ca_file: str = Field(
        description="PEM file of the CA(s) that signed the broker's certificate (relative to the config)"
    )
    cert_file: str | None = Field(
        None, description="this machine's client certificate, PEM; none = no client certificate"
    )
    key_file: str | None = Field(None, description="the client certificate's private key, PEM")
    check_hostname: bool = Field(True, description="the broker's certificate must name `host`")

    @model_validator(mode="after")
    def _pair(self) -> TlsConfig:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("give both cert_file and key_file, or neither")
        return self


class RemoteModelsConfig(Strict):
    """Models published to the machine's command topic (NCMD/DCMD): applied only when allowed here and armed."""

    allow: bool = Field(False, description="accept a model from the command topic at all")
    arm_signal: str | None = Field(
        None, description="a signal (a PMC/NC bit) that arms while its value is ≥ 0.5; none = only `compd arm-model`"
    )
    arm_window_s: float = Field(
        600.0, gt=0, le=86400, description="`compd arm-model` arms for this long, for one model"
    )
    max_bytes: int = Field(1 << 20, ge=1024, le=16 << 20, description="a longer model text is refused")
    shadow_min_interval_s: float = Field(
        60.0,
        ge=0,
        le=86400,
        description="a shadow sent (Model/shadow) less than this long after the last one accepted is refused: each"
        " accepted shadow reloads the daemon and starts the shadow's score on the probes afresh; 0 = no limit",
    )


class TelemetryBufferConfig(Strict):
    """The store-and-forward buffer: samples wait here (on disk) while the broker is unreachable."""

    path: str | None = Field(
        None,
        description="SQLite file (relative to the config); none = $STATE_DIRECTORY/<config name>.telemetry.sqlite"
        " under systemd, else next to the config",
    )
    max_mb: float = Field(
        64.0,
        ge=0.1,
        le=65536,
        description="at most this much data (at least 0.1 MB: a few hundred samples); when full the"
        " oldest is dropped and counted",
    )


class TelemetryConfig(Strict):
    """MQTT Sparkplug B telemetry to the plant's broker (needs the `plant` extra: paho-mqtt, protobuf)."""

    host: str = Field("127.0.0.1", min_length=1, description="the broker's address")
    port: int | None = Field(None, ge=1, le=65535, description="the broker's port; none = 1883, 8883 with tls")
    client_id: str | None = Field(None, description="MQTT client id; none = <group_id>-<edge_node_id>")
    username: str | None = Field(None, min_length=1, description="MQTT user name")
    password_file: str | None = Field(
        None, description="a file holding the MQTT password (relative to the config; keep it 0600)"
    )
    tls: TlsConfig | None = Field(None, description="TLS to the broker; none = plain TCP")
    group_id: str = Field(pattern=SPARKPLUG_ID, description="Sparkplug group id (the plant, a hall, a line)")
    edge_node_id: str = Field(pattern=SPARKPLUG_ID, description="Sparkplug edge node id: this compd")
    device_id: str = Field(
        "machine", pattern=SPARKPLUG_ID, description="Sparkplug device id: the machine it compensates"
    )
    primary_host_id: str | None = Field(
        None,
        pattern=SPARKPLUG_ID,
        description="a Sparkplug primary host (the historian's ingest): data waits on disk while its STATE is not"
        " online",
    )
    period_s: float = Field(1.0, ge=0.1, le=3600, description="one NDATA/DDATA sample per this much wall time")
    full_refresh_s: float = Field(
        60.0,
        ge=0,
        le=86400,
        description="a sample's DDATA carries only the metrics that changed since the last one sent (report by"
        " exception); every this many seconds of sample time, and first after each birth, one carries every metric"
        " (the historian's heartbeat and resynchronisation); 0 = every sample whole",
    )
    keepalive_s: int = Field(30, ge=5, le=3600, description="MQTT keep-alive")
    reconnect_max_s: float = Field(30.0, ge=0.5, le=3600, description="longest wait between two connection attempts")
    buffer: TelemetryBufferConfig = Field(TelemetryBufferConfig(), description="store and forward")
    remote_models: RemoteModelsConfig = Field(RemoteModelsConfig(), description="models from the command topic")


class OpcUaUserConfig(Strict):
    """One user name the OPC UA server accepts."""

    password_file: str = Field(description="a file holding the password (relative to the config)")


class OpcUaConfig(Strict):
    """A read-only OPC UA server (needs the `plant` extra: asyncua)."""

    bind: str = Field("127.0.0.1", min_length=1, description="address to listen on")
    port: int = Field(4840, ge=0, le=65535, description="TCP port; 0 = any free port")
    certificate: str = Field(description="the server's certificate, PEM or DER (relative to the config)")
    private_key: str = Field(description="its private key, PEM")
    trusted_clients: str | None = Field(
        None,
        description="folder of client certificates to trust; none = trust any client certificate (still encrypted)",
    )
    security: list[Literal["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "None"]] = Field(
        ["Basic256Sha256_SignAndEncrypt"], min_length=1, description="security policies offered"
    )
    anonymous: bool = Field(False, description="let clients in without a user name")
    users: dict[str, OpcUaUserConfig] = Field({}, description="user names and their password files")
    namespace_uri: str = Field("urn:compd", min_length=1, description="the namespace of compd's nodes")
    period_s: float = Field(1.0, ge=0.1, le=3600, description="how often the values are refreshed")


class ConfigModel(Strict):
    """The whole file."""

    loop: LoopConfig = Field(LoopConfig(), description="the fixed-period cycle")
    sources: list[dict[str, Any]] = Field(
        min_length=1, description="signal sources, one section per device (see Sources)"
    )
    model: dict[str, Any] = Field(description="the thermal-error model (see Models)")
    shadow: dict[str, Any] | None = Field(
        None,
        description="a candidate model (or a set of contributions) evaluated every cycle beside the active"
        " one, driving nothing, scored on the same probes; `compd promote` makes it active; none = no shadow",
    )
    guard: GuardConfig = Field(GuardConfig(), description="what reaches the machine")
    codec: CodecConfig = Field(CodecConfig(), description="corrections → 16-bit word")
    sink: dict[str, Any] = Field(description="where the correction goes (see Sinks)")
    log: LogConfig = Field(LogConfig(), description="the CSV data log")
    console: ConsoleConfig = Field(ConsoleConfig(), description="live table on stdout")
    state: StateConfig = Field(StateConfig(), description="persisted model state")
    observe: bool = Field(
        False,
        description="observe mode: run the full loop but hold the output disabled"
        " (commissioning); `compd run --observe` sets it too",
    )
    status: StatusConfig = Field(StatusConfig(), description="live status for `compd status`")
    metrics: MetricsConfig = Field(MetricsConfig(), description="Prometheus metrics endpoint")
    logging: LoggingConfig = Field(LoggingConfig(), description="event log lines")
    adapt: AdaptConfig | None = Field(
        None, description="probe-updated compensation (compd.cycle.adapt, the section adapt); none = the model alone"
    )
    inhibit: InhibitConfig | None = Field(
        None, description="the machine's inhibit and axis-referenced signals; none = never held off"
    )
    telemetry: TelemetryConfig | None = Field(
        None, description="MQTT Sparkplug B to the plant's broker (docs/plant.md); none = no telemetry"
    )
    opcua: OpcUaConfig | None = Field(None, description="read-only OPC UA server (docs/plant.md); none = none")


# ---------------------------------------------------------------- plugin sections


class SourceConfig(Strict):
    """Common keys of every source section (drivers subclass it)."""

    kind: str = Field(description="the source kind")
    name: str = Field(min_length=1, description="a name for this source, unique in the config")


class SinkConfig(Strict):
    """Common keys of every sink section (drivers subclass it)."""

    kind: str = Field(description="the sink kind")

    def driven_axes(self) -> tuple[list[str], str] | None:
        """The axes this section says the sink drives and the key that says so, for a sink that
        maps axes to its device's own (siemens: `axes`); None when it does not say: the word's
        axes are then `codec.axes`, else the first model's outputs (`DrivenAxes`)."""
        return None


class ModelSection(Strict):
    """The model section: a model file, or inline params."""

    kind: str = Field(description="the model kind")
    file: str | None = Field(None, description="model YAML written by `compd fit`")
    inputs: list[str] | None = Field(None, description="signal names, in the model's order")
    outputs: list[str] | None = Field(None, description="axis names")
    params: dict[str, Any] | None = Field(None, description="inline parameters (see the kind's params); or give 'file'")
    update_period_s: float | None = Field(None, ge=0, le=86400, description="model step; 0 = every cycle")


NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]*$"  # a contribution's name: in log columns, metric labels, node names


class ContributionSection(ModelSection):
    """One contribution of `model.contributions`: a model (file or params) with its own inputs,
    a name and its own limits; the axis correction is the sum of the contributions."""

    name: str | None = Field(
        None,
        pattern=NAME_PATTERN,
        max_length=32,
        description="the contribution's name (letters, digits, _; in log columns and metric labels); none = its kind",
    )
    max_abs_um: float | None = Field(
        None, gt=0, le=MAX_CORRECTION_UM, description="this contribution's clamp; none = its axis's clamp"
    )
    max_slew_um_per_s: float | None = Field(
        None,
        ge=MIN_SLEW_UM_PER_S,
        le=MAX_SLEW_UM_PER_S,
        description="how fast this contribution may change; none = its axis's slew limit",
    )
    fault_policy: FaultPolicy | None = Field(
        None,
        description="what this contribution does when one of its inputs goes bad and its model cannot"
        " predict from the rest (mlr and lvr with their fit's statistics go on from the others: `degraded`), while"
        " the others keep compensating; disable takes its axes to their own fault policy; none = its axis's",
    )


class ContributionsSection(Strict):
    """A model section that sums several contributions per axis."""

    contributions: list[dict[str, Any]] = Field(
        min_length=1, max_length=16, description="the contributions, each a model section with a name and limits"
    )


SUM_KIND = "contributions"  # the kind of a sum of contributions (a model file `compd fit --kind all` may write)


class ContributionParams(Strict):
    """One contribution as the config resolved it: its model (kind, wiring, params as in its
    file) and its limits per output axis (its own, or its axis's)."""

    name: str
    kind: str
    inputs: list[str]
    outputs: list[str]
    params: dict[str, Any]
    fit: dict[str, Any] = Field(default_factory=dict)
    file: str | None = None
    update_period_s: float | None = None
    max_abs_um: list[float]
    max_slew_um_per_s: list[float]
    fault_policy: list[FaultPolicy]


class ContributionSetParams(Strict):
    """The params of a sum of contributions (compd.cycle.contributions): the contributions and what
    their fault policies share with the guard."""

    contributions: list[ContributionParams]
    ramp_um_per_s: float = 1.0
    recovery_s: float = 5.0


def did_you_mean(name: str, known: list[str] | tuple[str, ...]) -> str:
    """`; did you mean 'z'?` naming the known name `name` most likely stands for: the same name in
    another case first (difflib finds no likeness between `Z` and `z`), else difflib's closest;
    "" when none is close. Names stay case-sensitive: this only suggests."""
    text = str(name)
    close = [k for k in known if k.casefold() == text.casefold()] or difflib.get_close_matches(text, list(known), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""
