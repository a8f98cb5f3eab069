"""YAML config → typed, validated objects; every error names file, line and key path.

The top-level sections are pydantic models with unknown keys forbidden. The
`sources`, `model` and `sink` sections are validated in a second pass against the
`Config` (or `Params`) model of the class that their `kind` names, found through the
registries, so each driver owns its options (STYLE: one config section, one module).
"""

from __future__ import annotations

import difflib
import hashlib
import importlib
import importlib.util
import json
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

from compd.errors import BadInput, ConfigError, format_path
from compd.registry import install_hint

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
                raise yaml.composer.ComposerError(
                    None, None, f"found undefined alias {ev.anchor!r}", ev.start_mark
                )
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


def validate(
    model: type[Strict], data: Any, doc: Document, base: PathT = (), what: str = "section"
) -> Any:
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
            err = next((x for x in errors if x["type"] == "extra_forbidden"
                        and tuple(x["loc"])[:-1] == tuple(err["loc"])[:-1]), err)
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
            if "input" in err and err["type"] not in ("model_type", "dict_type") and not isinstance(
                err["input"], dict
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
        False, description="lock memory against paging (mlockall; each page from when it is first touched,"
        " MCL_ONFAULT, where the kernel has it)"
    )


class PlantClockConfig(Strict):
    """Where a simulated plant publishes its clock (its clock device's register map, over Modbus TCP)."""

    host: str = Field("127.0.0.1", description="the plant's Modbus TCP address")
    port: int = Field(ge=1, le=65535, description="the plant's Modbus TCP port")
    device_id: int = Field(1, ge=0, le=247, description="unit id of the plant's register map")
    address: int = Field(0, ge=0, le=65534, description="plant time, ms, uint32 in two registers (high first)")
    poll_period_s: float = Field(0.001, ge=0.0001, le=1, description="wall time between clock reads")
    stall_s: float = Field(
        0.5, ge=0.01, le=3600, description="wall time without plant progress before a wait gives up"
    )
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
        0.002, ge=0.0005, le=60,
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
        0.0001, gt=0, le=0.005,
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
            raise ValueError(f"process needs an x86-64 CPU (the mailboxes between processes rely on its store"
                             f" order); this one is {platform.machine() or 'unknown'}: set io: thread")
        return io


class SignalLimits(Strict):
    """Plausibility limits of one signal."""

    min: float = Field(
        -40.0, ge=-SIGNAL_ABS_MAX, le=SIGNAL_ABS_MAX,
        description="lowest plausible value (°C for temperatures; any signal's unit: rpm, mm, A)",
    )
    max: float = Field(
        150.0, ge=-SIGNAL_ABS_MAX, le=SIGNAL_ABS_MAX, description="highest plausible value; above min"
    )
    max_rate_per_s: float | None = Field(
        None, gt=0, le=SIGNAL_ABS_MAX, description="largest plausible change per s"
    )
    rate_allowance: float = Field(
        0.3, ge=0, le=SIGNAL_ABS_MAX,
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
    frozen_band: float = Field(
        0.0, ge=0, le=SIGNAL_ABS_MAX, description="a change of at most this much is no change"
    )

    @model_validator(mode="after")
    def _order(self) -> SignalLimits:
        if not self.min < self.max:
            raise ValueError(f"min ({self.min:g}) must be below max ({self.max:g})")
        return self


class AxisGuardConfig(Strict):
    """Per-axis overrides of the guard."""

    fault_policy: Literal["hold", "ramp_to_zero", "disable"] | None = Field(
        None, description="this axis's fault policy; none = guard.fault_policy"
    )
    max_abs_um: float | None = Field(
        None, gt=0, le=MAX_CORRECTION_UM, description="this axis's clamp; none = guard.max_abs_um"
    )
    max_slew_um_per_s: float | None = Field(
        None, ge=MIN_SLEW_UM_PER_S, le=MAX_SLEW_UM_PER_S,
        description="this axis's slew limit; none = guard.max_slew_um_per_s",
    )


class GuardConfig(Strict):
    """What reaches the machine: plausibility, clamp, slew, fault policy."""

    max_abs_um: float = Field(
        63.0, gt=0, le=MAX_CORRECTION_UM,
        description="magnitude clamp on the correction (thermal errors are tens to hundreds of µm)",
    )
    max_slew_um_per_s: float = Field(
        5.0, ge=MIN_SLEW_UM_PER_S, le=MAX_SLEW_UM_PER_S,
        description="largest rate of change (thermal errors drift by µm per minute)",
    )
    fault_policy: Literal["hold", "ramp_to_zero", "disable"] = Field(
        "hold", description="what an axis does when an input it needs goes bad"
    )
    ramp_um_per_s: float = Field(
        1.0, ge=MIN_SLEW_UM_PER_S, le=MAX_SLEW_UM_PER_S, description="ramp_to_zero rate"
    )
    recovery_s: float = Field(5.0, ge=0, le=3600, description="inputs good this long before recovery")
    stale_after_s: float = Field(
        5.0, gt=0, le=86400, description="default staleness limit of a signal; longer than loop.period_s"
    )
    signals: dict[str, SignalLimits] = Field(
        default_factory=dict, description="plausibility limits by signal name"
    )
    axes: dict[str, AxisGuardConfig] = Field(
        default_factory=dict, description="per-axis overrides by axis name"
    )

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
        1.0, ge=0.01, le=100,
        description="µm per magnitude LSB (63 LSB of 0.01 µm to 100 µm: 0.63 µm to 6.3 mm full scale)",
    )
    deadband_um: float = Field(
        1.0, ge=0, le=100,
        description=(
            "|c| at or below this is sent as disabled; the word moves once the correction is"
            " max(deadband_um, lsb_um) from it, one LSB at a time at the slew limit, and settles"
            " within that of it; below full scale (63 × lsb_um)"
        ),
    )
    axes: list[str] | None = Field(
        None, max_length=2, description="the axes the word drives, high byte first; every output of the model (each"
        " contribution's, the shadow's) is one of them (default: the first model's outputs, in order)"
    )

    @model_validator(mode="after")
    def _deadband_below_full_scale(self) -> CodecConfig:
        from compd.cycle.codec import MAX_MAG

        if not self.deadband_um < MAX_MAG * self.lsb_um:
            raise ValueError(
                f"deadband_um {self.deadband_um:g} is not below the word's full scale"
                f" ({MAX_MAG} × lsb_um = {MAX_MAG * self.lsb_um:g} µm): every correction would be sent disabled"
            )
        return self


class LogConfig(Strict):
    """The CSV data log."""

    path: str | None = Field(None, description="log file; none = no log")
    period_s: float = Field(
        1.0, ge=0.0005, le=86400, description="one row per this period, plus every word change"
    )
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
        None, ge=0, le=1000,
        description="σ of the model's own error at a probe (it moves from probe to probe, a probe cannot tell it"
        " from an offset), µm; none = the model's held-out RMSE from its fit (its file's fit.held_out_rmse_um),"
        " 0 when the file has none",
    )
    apply_above_sigma: float = Field(
        2.0, ge=0, le=100,
        description="apply the estimate's correction c only as far as it stands out from its own σ where the axis"
        " is: c·max(0, 1 − (k σ_c/c)²) with this k (0 = apply the estimate as it is)",
    )
    initial_offset_sigma_um: float | None = Field(
        None, gt=0, le=1000,
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
    invert: bool = Field(
        False, description="the inhibit signals are enables: 0 inhibits, not 0 releases"
    )
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

    level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="lowest level printed"
    )


SPARKPLUG_ID = r"^[^/+#]+$"  # a Sparkplug group, edge node or device id: no topic separators or wildcards


class TlsConfig(Strict):
    """TLS to the broker: the CA that signed its certificate, and this machine's own when the broker asks for one."""

    ca_file: str = Field(description="PEM file of the CA(s) that signed the broker's certificate (relative to the config)")
    cert_file: str | None = Field(None, description="this machine's client certificate, PEM; none = no client certificate")
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
        60.0, ge=0, le=86400,
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
    max_mb: float = Field(64.0, ge=0.1, le=65536,
                          description="at most this much data (at least 0.1 MB: a few hundred samples); when full the"
                          " oldest is dropped and counted")


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
    device_id: str = Field("machine", pattern=SPARKPLUG_ID, description="Sparkplug device id: the machine it compensates")
    primary_host_id: str | None = Field(
        None, pattern=SPARKPLUG_ID,
        description="a Sparkplug primary host (the historian's ingest): data waits on disk while its STATE is not online",
    )
    period_s: float = Field(1.0, ge=0.1, le=3600, description="one NDATA/DDATA sample per this much wall time")
    full_refresh_s: float = Field(
        60.0, ge=0, le=86400,
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
        None, description="folder of client certificates to trust; none = trust any client certificate (still encrypted)"
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
        None, description="a candidate model (or a set of contributions) evaluated every cycle beside the active"
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
    params: dict[str, Any] | None = Field(
        None, description="inline parameters (see the kind's params); or give 'file'"
    )
    update_period_s: float | None = Field(
        None, ge=0, le=86400, description="model step; 0 = every cycle"
    )


NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]*$"  # a contribution's name: in log columns, metric labels, node names


class ContributionSection(ModelSection):
    """One contribution of `model.contributions`: a model (file or params) with its own inputs,
    a name and its own limits; the axis correction is the sum of the contributions."""

    name: str | None = Field(
        None, pattern=NAME_PATTERN, max_length=32,
        description="the contribution's name (letters, digits, _; in log columns and metric labels); none = its kind",
    )
    max_abs_um: float | None = Field(
        None, gt=0, le=MAX_CORRECTION_UM, description="this contribution's clamp; none = its axis's clamp"
    )
    max_slew_um_per_s: float | None = Field(
        None, ge=MIN_SLEW_UM_PER_S, le=MAX_SLEW_UM_PER_S,
        description="how fast this contribution may change; none = its axis's slew limit",
    )
    fault_policy: Literal["hold", "ramp_to_zero", "disable"] | None = Field(
        None, description="what this contribution does when one of its inputs goes bad and its model cannot"
        " predict from the rest (mlr and lvr with their fit's statistics go on from the others: `degraded`), while"
        " the others keep compensating; disable takes its axes to their own fault policy; none = its axis's",
    )


class ContributionsSection(Strict):
    """A model section that sums several contributions per axis."""

    contributions: list[dict[str, Any]] = Field(
        min_length=1, max_length=16, description="the contributions, each a model section with a name and limits"
    )


def did_you_mean(name: str, known: list[str] | tuple[str, ...]) -> str:
    """`; did you mean 'z'?` naming the known name `name` most likely stands for: the same name in
    another case first (difflib finds no likeness between `Z` and `z`), else difflib's closest;
    "" when none is close. Names stay case-sensitive: this only suggests."""
    text = str(name)
    close = [k for k in known if k.casefold() == text.casefold()] or difflib.get_close_matches(text, list(known), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


@dataclass(frozen=True)
class DrivenAxes:
    """The axes the machine is driven on, declared once, and where: a sink's own list (`sink.axes`
    of a sink that maps axes to its device's), else `codec.axes`, else the outputs of the first
    model (of the first contribution, for a sum). Every output of the model, of each contribution
    and of the shadow, and every axis a per-axis section names, must be one of them: a misspelt
    axis (`Z` beside `z`) is refused, never an axis of its own that drives the word's other byte."""

    names: tuple[str, ...]
    origin: str  # the key (or the model) that declares them, for the error
    who: str = "the sink"  # ... "the model" for the outputs of a model narrower than the sink's axes

    def check(self, axis: Any, doc: Document, path: PathT, note: str = "") -> None:
        """A ConfigError at `path` of `doc` unless `axis` is one of the driven axes."""
        if axis not in self.names:
            raise doc.error(
                f"{axis!r} is not an axis {self.who} drives ({', '.join(self.names)}: {self.origin}){note}"
                f"{did_you_mean(axis, self.names)}", path,
            )


@dataclass
class ModelSpec:
    """A resolved model: its class, validated params and wiring."""

    cls: type
    params: Any
    inputs: list[str]
    outputs: list[str]
    update_period_s: float | None
    fit: dict[str, Any]
    doc: Document
    path: PathT
    file: str | None = None  # the model file (absolute), None for inline params
    sha256: str | None = None  # the model file's bytes as read (`sha256sum` prints it), None without a file


def model_sha256(spec: ModelSpec) -> str:
    """What a resolved model is, as one sha256: its model file's (the bytes it was read from), else
    that of its definition as read (kind, inputs, outputs, update period and params: inline params,
    contributions). Two loads of the same text give the same digest: a running daemon's shadow and
    `compd promote`'s reading of the config are compared by it."""
    if spec.sha256 is not None:
        return spec.sha256
    definition = {"kind": spec.cls.kind, "inputs": list(spec.inputs), "outputs": list(spec.outputs),
                  "update_period_s": spec.update_period_s, "params": spec.params.model_dump(mode="json")}
    text = json.dumps(definition, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass
class Config:
    """A validated config: top-level sections plus resolved plugin objects."""

    file: str
    doc: Document
    top: ConfigModel
    sources: list[tuple[type, Any, PathT]]
    model: ModelSpec
    sink: tuple[type, Any, PathT]
    shadow: ModelSpec | None = None

    @property
    def loop(self) -> LoopConfig:
        return self.top.loop

    @property
    def guard(self) -> GuardConfig:
        return self.top.guard

    @property
    def codec(self) -> CodecConfig:
        return self.top.codec

    def resolve_path(self, p: str) -> Path:
        """A path from the config, relative to the config file's folder."""
        path = Path(p)
        return path if path.is_absolute() else Path(self.file).parent / path


def _plugin(registry: Any, data: Any, doc: Document, path: PathT) -> tuple[type, Any]:
    if not isinstance(data, dict):
        raise doc.error("expected a mapping with a 'kind'", path)
    if "kind" not in data:
        raise doc.error(f"'kind' is missing (known: {', '.join(registry.kinds())})", path)
    if not isinstance(data["kind"], str):
        raise doc.error(f"'kind' must be a name (known: {', '.join(registry.kinds())})", (*path, "kind"))
    try:
        cls = registry.get(data["kind"])
    except BadInput as e:
        raise doc.error(e.message, (*path, "kind")) from None
    return cls, validate(cls.Config, data, doc, path)


def load_model_file(file: str | Path, text: str | None = None) -> tuple[Document, dict[str, Any]]:
    """Read a model YAML (kind, inputs, outputs, params, fit: docs/formats.md); at most MODEL_MAX_BYTES
    (`text`: the file's text, read already)."""
    doc = load_yaml(file, text, max_bytes=MODEL_MAX_BYTES, max_values=MODEL_MAX_VALUES)
    data = doc.data
    if not isinstance(data, dict):
        raise doc.error("a model file is a mapping with kind, inputs, outputs, params", ())
    for key in ("kind", "inputs", "outputs", "params"):
        if key not in data:
            raise doc.error("required key is missing", (key,))
    extra = set(data) - {"kind", "inputs", "outputs", "params", "fit"}
    if extra:
        raise doc.error("unknown key (known: kind, inputs, outputs, params, fit)", (sorted(extra)[0],))
    return doc, data


def resolve_model(
    section: Any, doc: Document, path: PathT, base_dir: Path, guard: GuardConfig | None = None,
    axes: DrivenAxes | None = None,
) -> ModelSpec:
    """Resolve a model section (inline, from a file, or `contributions`: several summed) to a
    ModelSpec; a contribution's limits default to its axes' in `guard`. With `axes`, every output
    (each contribution's) must be one of them; without, a sum's first contribution declares them."""
    from compd.models import MODELS

    if isinstance(section, dict) and "contributions" in section:
        return _resolve_contributions(section, doc, path, base_dir, guard or GuardConfig(), axes)
    if isinstance(section, dict) and section.get("kind") == SUM_KIND:
        return _resolve_sum_file(section, doc, path, base_dir, guard or GuardConfig(), axes)
    sec = validate(ModelSection, section, doc, path)
    try:
        cls = MODELS.get(sec.kind)
    except BadInput as e:
        raise doc.error(e.message, (*path, "kind")) from None
    fit: dict[str, Any] = {}
    sha256: str | None = None
    pdoc, ppath = doc, (*path, "params")
    if sec.file is not None:
        if sec.params is not None:
            raise doc.error("give either 'file' or 'params', not both", (*path, "params"))
        fpath = Path(sec.file)
        if not fpath.is_absolute():
            fpath = base_dir / fpath
        ftext = read_bounded(str(fpath), MODEL_MAX_BYTES)
        mdoc, mdata = load_model_file(fpath, ftext)
        sha256 = hashlib.sha256(ftext.encode("utf-8")).hexdigest()  # the bytes read (strict UTF-8 round-trips)
        if mdata["kind"] != sec.kind:
            raise doc.error(
                f"model file {fpath} is of kind {mdata['kind']!r}, not {sec.kind!r}", (*path, "kind")
            )
        raw_params, pdoc, ppath = mdata["params"], mdoc, ("params",)
        inputs = sec.inputs or mdata["inputs"]
        outputs = sec.outputs or mdata["outputs"]
        fit = mdata.get("fit") or {}
        if sec.inputs and len(sec.inputs) != len(mdata["inputs"]):
            raise doc.error(
                f"model file has {len(mdata['inputs'])} inputs, config names {len(sec.inputs)}",
                (*path, "inputs"),
            )
    else:
        if sec.params is None:
            raise doc.error("give 'file' (a fitted model) or 'params'", path)
        raw_params = sec.params
        if sec.inputs is None or sec.outputs is None:
            raise doc.error("inline models need 'inputs' and 'outputs'", path)
        inputs, outputs = sec.inputs, sec.outputs
    upgrade = getattr(cls.Params, "upgrade", None)  # params as written before a key existed
    if upgrade is not None:
        raw_params = upgrade(raw_params)
    params = validate(cls.Params, raw_params, pdoc, ppath, what="params")
    base = ppath[:-1]  # where the model section sits in pdoc (the file's top, or `path`)

    def where(key: str) -> tuple[Document, PathT]:
        """The file and key path of the model's `inputs` or `outputs` (the config may override them)."""
        if pdoc is doc or getattr(sec, key) is not None:
            return doc, (*path, key)
        return pdoc, (key,)

    for what, names in (("inputs", inputs), ("outputs", outputs)):
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            wdoc, wpath = where(what)
            raise wdoc.error(f"{what} must be a list of names", wpath)
    try:
        cls.check_wiring(params, list(inputs), list(outputs))
    except BadInput as e:
        keys = e.keys
        if keys and keys[0] in ("inputs", "outputs"):
            wdoc, wpath = where(str(keys[0]))
            raise wdoc.error(e.message, (*wpath, *keys[1:])) from None
        raise pdoc.error(e.message, (*base, *keys) if keys else ppath) from None
    if axes is not None:
        wdoc, wpath = where("outputs")
        note = "" if wdoc is doc else f" (the model file of {format_path(path)})"
        for j, axis in enumerate(outputs):
            axes.check(axis, wdoc, (*wpath, j), note)
    mfile = None if sec.file is None else str(fpath.resolve())
    return ModelSpec(cls, params, list(inputs), list(outputs), sec.update_period_s, fit, pdoc, path, mfile, sha256)


SUM_KIND = "contributions"  # a model file of several contributions summed (`compd fit --kind all` may write one)


def _resolve_sum_file(
    section: dict[str, Any], doc: Document, path: PathT, base_dir: Path, guard: GuardConfig,
    axes: DrivenAxes | None,
) -> ModelSpec:
    """`{kind: contributions, file: SUM.yaml}`: a model file that sums several contributions (each
    with its kind, inputs, outputs, params and its own fit block, as `compd fit --kind all` writes a
    recommended sum), resolved as a config's `model.contributions` would be, the limits the guard's."""
    extra = set(section) - {"kind", "file", "update_period_s"}
    if extra:
        raise doc.error(f"a model file of contributions takes only kind and file here (got {sorted(extra)[0]!r});"
                        " limits per contribution: write model.contributions in the config", (*path, sorted(extra)[0]))
    if not isinstance(section.get("file"), str):
        raise doc.error(f"kind {SUM_KIND!r} names a model file of contributions: give 'file'", (*path, "file"))
    fpath = Path(section["file"])
    if not fpath.is_absolute():
        fpath = base_dir / fpath
    ftext = read_bounded(str(fpath), MODEL_MAX_BYTES)
    mdoc, mdata = load_model_file(fpath, ftext)
    if mdata["kind"] != SUM_KIND:
        raise doc.error(f"model file {fpath} is of kind {mdata['kind']!r}, not {SUM_KIND!r}", (*path, "kind"))
    params = mdata["params"]
    if not isinstance(params, dict) or not isinstance(params.get("contributions"), list):
        raise mdoc.error("a model file of contributions holds params.contributions: a list of models", ("params",))
    items, fits = [], []
    for i, item in enumerate(params["contributions"]):
        if not isinstance(item, dict):
            raise mdoc.error("a contribution is a model (name, kind, inputs, outputs, params, fit)",
                             ("params", "contributions", i))
        fits.append(item.get("fit") or {})
        items.append({k: v for k, v in item.items() if k != "fit"})
    spec = _resolve_contributions({"contributions": items}, mdoc, ("params",), fpath.parent, guard, axes, fits)
    spec.path = path
    spec.fit = mdata.get("fit") or {}
    spec.file = str(fpath.resolve())
    spec.sha256 = hashlib.sha256(ftext.encode("utf-8")).hexdigest()
    if axes is not None:
        for j, axis in enumerate(spec.outputs):
            axes.check(axis, mdoc, ("outputs", j), f" (the model file of {format_path(path)})")
    return spec


def _resolve_contributions(
    section: dict[str, Any], doc: Document, path: PathT, base_dir: Path, guard: GuardConfig,
    axes: DrivenAxes | None = None, fits: list[dict[str, Any]] | None = None,
) -> ModelSpec:
    """`model.contributions`: each item resolved as a model section; the sum's spec (kind
    `contributions`: compd.models.contributions) with each one's limits settled. Each one's
    outputs are among `axes`; without them, the first contribution's outputs declare the axes."""
    from compd.models.contributions import ContributionParams, Contributions, ContributionSetParams

    sec = validate(ContributionsSection, section, doc, path)
    parts: list[ContributionParams] = []
    names: set[str] = set()
    for i, item in enumerate(sec.contributions):
        where = (*path, "contributions", i)
        if not isinstance(item, dict):
            raise doc.error("a contribution is a model section (kind, file or params, ...)", where)
        if "contributions" in item:
            raise doc.error("a contribution cannot itself have contributions", (*where, "contributions"))
        csec = validate(ContributionSection, item, doc, where)
        own = {k: v for k, v in item.items() if k not in ("name", "max_abs_um", "max_slew_um_per_s", "fault_policy")}
        spec = resolve_model(own, doc, where, base_dir, axes=axes)
        if axes is None:  # declared by none: the first contribution's outputs declare them
            axes = DrivenAxes(tuple(spec.outputs), f"the outputs of {format_path(where)}; codec.axes declares more")
        name = csec.name or spec.cls.kind
        if name in names:
            raise doc.error(f"contribution name {name!r} is used twice (give each a `name`)", (*where, "name"))
        names.add(name)
        outs = list(spec.outputs)
        parts.append(ContributionParams(
            name=name, kind=spec.cls.kind, inputs=list(spec.inputs), outputs=outs,
            params=spec.params.model_dump(mode="json"), fit=dict(fits[i] if fits else spec.fit), file=spec.file,
            update_period_s=spec.update_period_s,
            max_abs_um=[csec.max_abs_um or guard.clamp_um(a)[0] for a in outs],
            max_slew_um_per_s=[csec.max_slew_um_per_s or guard.slew_um_per_s(a) for a in outs],
            fault_policy=[csec.fault_policy or _axis_policy(guard, a) for a in outs],
        ))
    params = ContributionSetParams(contributions=parts, ramp_um_per_s=guard.ramp_um_per_s,
                                   recovery_s=guard.recovery_s)
    inputs = list(dict.fromkeys(n for p in parts for n in p.inputs))
    outputs = list(dict.fromkeys(a for p in parts for a in p.outputs))
    return ModelSpec(Contributions, params, inputs, outputs, None, {}, doc, path, None)


def _axis_policy(guard: GuardConfig, axis: str) -> str:
    own = guard.axes.get(axis)
    return (own.fault_policy if own is not None else None) or guard.fault_policy


def _check_timings(top: ConfigModel, doc: Document) -> None:
    """Limits measured in time must exceed one cycle: the loop looks once per period, so a
    sample it reads is up to a period old and a shorter limit would fault every input."""
    period = top.loop.period_s
    limits: list[tuple[float | None, PathT]] = [(top.guard.stale_after_s, ("guard", "stale_after_s"))]
    for name, lim in top.guard.signals.items():
        limits.append((lim.stale_after_s, ("guard", "signals", name, "stale_after_s")))
        limits.append((lim.frozen_after_s, ("guard", "signals", name, "frozen_after_s")))
    for value, path in limits:
        if value is not None and not value > period:
            if tuple(path) in doc.lines:
                raise doc.error(f"{value:g} s is not longer than one cycle (loop.period_s = {period:g} s)", path)
            # a default the file does not write: the line is the period's, and the message names the key to add
            raise doc.error(f"the default {format_path(path)} ({value:g} s) is not longer than one cycle: set"
                            f" {format_path(path)} above {period:g} s in the guard section", ("loop", "period_s"))


# An optional feature a config can switch on: the key that switches it on, the module it
# imports and the extra of pyproject.toml that installs that module.
OPTIONAL_MODULES: dict[PathT, tuple[str, str]] = {
    ("metrics", "enabled"): ("prometheus_client", "metrics"),
    ("telemetry",): ("paho.mqtt.client", "plant"),
    ("opcua",): ("asyncua", "plant"),
}


def _check_optional(top: ConfigModel, doc: Document) -> None:
    """A ConfigError naming the key of an optional feature the config enables whose module is missing."""
    for path, (module, extra) in OPTIONAL_MODULES.items():
        value: Any = top
        for key in path:
            value = getattr(value, str(key), None)
        if not value:
            continue
        try:
            found = importlib.util.find_spec(module) is not None  # found, not imported: the loop process stays lean
        except ImportError:
            found = False
        if not found:
            raise doc.error(
                f"needs the Python module {module}, which is not installed: {install_hint(extra)}",
                path,
            ) from None


def _declared_axes(top: ConfigModel, sink: SinkConfig) -> DrivenAxes | None:
    """The axes the config declares the machine is driven on: the sink's own list, else
    `codec.axes`; None when neither says (the first model's outputs then declare them)."""
    own = sink.driven_axes()
    if own is not None:
        return DrivenAxes(tuple(own[0]), f"sink.{own[1]}")
    if top.codec.axes:
        return DrivenAxes(tuple(top.codec.axes), "codec.axes")
    return None


def load_config(file: str | Path, text: str | None = None) -> Config:
    """Load and validate a config file; raises ConfigError (exit 2) on any problem."""
    from compd.sinks import SINKS
    from compd.sources import SOURCES

    doc = load_yaml(file, text)
    if doc.data is None:
        raise ConfigError("the config is empty", file=doc.file)
    top = validate(ConfigModel, doc.data, doc, (), what="config")
    _check_timings(top, doc)
    _check_optional(top, doc)
    sources = []
    names: set[str] = set()
    for i, sec in enumerate(top.sources):
        cls, cfg = _plugin(SOURCES, sec, doc, ("sources", i))
        if cfg.name in names:
            raise doc.error(f"source name {cfg.name!r} is used twice", ("sources", i, "name"))
        names.add(cfg.name)
        sources.append((cls, cfg, ("sources", i)))
    sink_cls, sink_cfg = _plugin(SINKS, top.sink, doc, ("sink",))
    base_dir = Path(doc.file).parent
    declared = _declared_axes(top, sink_cfg)
    model = resolve_model(top.model, doc, ("model",), base_dir, top.guard, axes=declared)
    if len(model.outputs) > 2 and top.codec.axes is None:
        raise doc.error("the word carries two axes: name them in codec.axes", ("model", "outputs"))
    # what the model drives, for the sections that name an axis: the declared axes when it drives
    # all of them (else a narrower list the error then names)
    if declared is None:
        first = ("model", "contributions", 0) if "contributions" in top.model else ("model",)
        declared = DrivenAxes(tuple(model.outputs), f"the outputs of {format_path(first)}")
    driven = declared if set(declared.names) == set(model.outputs) else DrivenAxes(
        tuple(model.outputs), "its outputs", who="the model")
    for i, axis in enumerate(top.codec.axes or []):
        declared.check(axis, doc, ("codec", "axes", i))
        driven.check(axis, doc, ("codec", "axes", i))
    for axis in top.inhibit.axes if top.inhibit is not None else {}:
        driven.check(axis, doc, ("inhibit", "axes", axis))
    for axis in top.guard.axes:
        driven.check(axis, doc, ("guard", "axes", axis))
    for axis in top.adapt.slope_position if top.adapt is not None else {}:
        driven.check(axis, doc, ("adapt", "slope_position", axis))
    shadow = None
    if top.shadow is not None:  # it stands beside the active model, on its axes
        shadow = resolve_model(top.shadow, doc, ("shadow",), base_dir, top.guard, axes=driven)
    return Config(doc.file, doc, top, sources, model, (sink_cls, sink_cfg, ("sink",)), shadow)


__all__ = [
    "Config",
    "ConfigError",
    "Document",
    "ModelSpec",
    "SinkConfig",
    "SourceConfig",
    "Strict",
    "format_path",
    "load_config",
    "load_yaml",
    "resolve_model",
    "validate",
]
