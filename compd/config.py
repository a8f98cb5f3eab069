"""The whole config document: the sections resolved with the kinds they name, the model files read and checked.

The top-level sections are pydantic models with unknown keys forbidden. The
`sources`, `model` and `sink` sections are validated in a second pass against the
`Config` (or `Params`) model of the class that their `kind` names, found through the
registries, so each driver owns its options (STYLE: one config section, one module).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from compd.core.config import (
    MODEL_MAX_BYTES,
    MODEL_MAX_VALUES,
    SUM_KIND,
    CodecConfig,
    ConfigModel,
    ContributionParams,
    ContributionSection,
    ContributionSetParams,
    ContributionsSection,
    Document,
    GuardConfig,
    LoopConfig,
    ModelSection,
    PathT,
    SinkConfig,
    SourceConfig,
    Strict,
    did_you_mean,
    load_yaml,
    read_bounded,
    validate,
)
from compd.core.errors import BadInput, ConfigError, format_path
from compd.core.registry import install_hint
from compd.models import MODELS
from compd.sinks import SINKS
from compd.sources import SOURCES

if TYPE_CHECKING:  # the kinds' modules are imported when a config names them (compd.core.registry)
    from compd.core.registry import Registry
    from compd.models.base import Model
    from compd.sinks.base import Sink
    from compd.sources.base import Source

    Device = TypeVar("Device", Source, Sink)


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
                f"{did_you_mean(axis, self.names)}",
                path,
            )


@dataclass
class ModelSpec:
    """A resolved model: its class, validated params and wiring.

    A sum of contributions has no class here (`cls` None, params a ContributionSetParams): it is a
    stage of the cycle, which compd.cycle.pipeline.build_model builds from the params."""

    cls: type[Model] | None
    params: Strict
    inputs: list[str]
    outputs: list[str]
    update_period_s: float | None
    fit: dict[str, Any]
    doc: Document
    path: PathT
    file: str | None = None  # the model file (absolute), None for inline params
    sha256: str | None = None  # the model file's bytes as read (`sha256sum` prints it), None without a file

    @property
    def kind(self) -> str:
        """The model's kind (`contributions` for a sum)."""
        return SUM_KIND if self.cls is None else str(self.cls.kind)


def model_sha256(spec: ModelSpec) -> str:
    """What a resolved model is, as one sha256: its model file's (the bytes it was read from), else
    that of its definition as read (kind, inputs, outputs, update period and params: inline params,
    contributions). Two loads of the same text give the same digest: a running daemon's shadow and
    `compd promote`'s reading of the config are compared by it."""
    if spec.sha256 is not None:
        return spec.sha256
    definition = {
        "kind": spec.kind,
        "inputs": list(spec.inputs),
        "outputs": list(spec.outputs),
        "update_period_s": spec.update_period_s,
        "params": spec.params.model_dump(mode="json"),
    }
    text = json.dumps(definition, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass
class Config:
    """A validated config: top-level sections plus resolved plugin objects."""

    file: str
    doc: Document
    top: ConfigModel
    sources: list[tuple[type[Source], SourceConfig, PathT]]
    model: ModelSpec
    sink: tuple[type[Sink], SinkConfig, PathT]
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


def _plugin(registry: Registry[type[Device]], data: Any, doc: Document, path: PathT) -> tuple[type[Device], Any]:
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
    section: Any,
    doc: Document,
    path: PathT,
    base_dir: Path,
    guard: GuardConfig | None = None,
    axes: DrivenAxes | None = None,
) -> ModelSpec:
    """Resolve a model section (inline, from a file, or `contributions`: several summed) to a
    ModelSpec; a contribution's limits default to its axes' in `guard`. With `axes`, every output
    (each contribution's) must be one of them; without, a sum's first contribution declares them."""
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
            raise doc.error(f"model file {fpath} is of kind {mdata['kind']!r}, not {sec.kind!r}", (*path, "kind"))
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


def _resolve_sum_file(
    section: dict[str, Any],
    doc: Document,
    path: PathT,
    base_dir: Path,
    guard: GuardConfig,
    axes: DrivenAxes | None,
) -> ModelSpec:
    """`{kind: contributions, file: SUM.yaml}`: a model file that sums several contributions (each
    with its kind, inputs, outputs, params and its own fit block, as `compd fit --kind all` writes a
    recommended sum), resolved as a config's `model.contributions` would be, the limits the guard's."""
    extra = set(section) - {"kind", "file", "update_period_s"}
    if extra:
        raise doc.error(
            f"a model file of contributions takes only kind and file here (got {sorted(extra)[0]!r});"
            " limits per contribution: write model.contributions in the config",
            (*path, sorted(extra)[0]),
        )
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
            raise mdoc.error(
                "a contribution is a model (name, kind, inputs, outputs, params, fit)", ("params", "contributions", i)
            )
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
    section: dict[str, Any],
    doc: Document,
    path: PathT,
    base_dir: Path,
    guard: GuardConfig,
    axes: DrivenAxes | None = None,
    fits: list[dict[str, Any]] | None = None,
) -> ModelSpec:
    """`model.contributions`: each item resolved as a model section; the sum's spec (kind
    `contributions`, no class: the cycle's stage compd.cycle.contributions, built by the pipeline)
    with each one's limits settled. Each one's outputs are among `axes`; without them, the first
    contribution's outputs declare the axes."""
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
        name = csec.name or spec.kind
        if name in names:
            raise doc.error(f"contribution name {name!r} is used twice (give each a `name`)", (*where, "name"))
        names.add(name)
        outs = list(spec.outputs)
        parts.append(
            ContributionParams(
                name=name,
                kind=spec.kind,
                inputs=list(spec.inputs),
                outputs=outs,
                params=spec.params.model_dump(mode="json"),
                fit=dict(fits[i] if fits else spec.fit),
                file=spec.file,
                update_period_s=spec.update_period_s,
                max_abs_um=[csec.max_abs_um or guard.clamp_um(a)[0] for a in outs],
                max_slew_um_per_s=[csec.max_slew_um_per_s or guard.slew_um_per_s(a) for a in outs],
                fault_policy=[csec.fault_policy or _axis_policy(guard, a) for a in outs],
            )
        )
    params = ContributionSetParams(contributions=parts, ramp_um_per_s=guard.ramp_um_per_s, recovery_s=guard.recovery_s)
    inputs = list(dict.fromkeys(n for p in parts for n in p.inputs))
    outputs = list(dict.fromkeys(a for p in parts for a in p.outputs))
    return ModelSpec(None, params, inputs, outputs, None, {}, doc, path, None)


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
            raise doc.error(
                f"the default {format_path(path)} ({value:g} s) is not longer than one cycle: set"
                f" {format_path(path)} above {period:g} s in the guard section",
                ("loop", "period_s"),
            )


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
    doc = load_yaml(file, text)
    if doc.data is None:
        raise ConfigError("the config is empty", file=doc.file)
    top = validate(ConfigModel, doc.data, doc, (), what="config")
    _check_timings(top, doc)
    _check_optional(top, doc)
    sources: list[tuple[type[Source], SourceConfig, PathT]] = []
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
    driven = (
        declared
        if set(declared.names) == set(model.outputs)
        else DrivenAxes(tuple(model.outputs), "its outputs", who="the model")
    )
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
