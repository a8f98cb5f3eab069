"""Generates docs/configuration.md from the config schema, so the reference cannot drift.

Every key of compd/core/config.py's models and of the `Config`/`Params` model of every
kind in the source, model and sink registries: its type, unit (from the key's
name suffix, STYLE: units in names), default, allowed range and description
(`Field(description=...)`). `python -m compd.commissioning.docgen` or `compd docs --out FILE`.
"""

from __future__ import annotations

import inspect
import sys
import types
import typing
from collections.abc import Iterator
from typing import Annotated, Any, Literal

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from compd.core import config as core_config
from compd.models import MODELS
from compd.sinks import SINKS
from compd.sources import SOURCES

# key-name suffix → unit, longest first (STYLE: `period_s`, `max_step_um`, ...)
UNIT_SUFFIXES = (
    ("_w_m2k_per_krpm", "W/(m²·K) per 1000 rpm"),
    ("_w_per_krpm", "W per 1000 rpm"),
    ("_um_per_s", "µm/s"),
    ("_c_per_h", "°C/h"),
    ("_c_per_s", "°C/s"),
    ("_w_m2k", "W/(m²·K)"),
    ("_per_k", "1/K"),
    ("_per_s", "(signal unit)/s"),
    ("_um", "µm"),
    ("_mm", "mm"),
    ("_ms", "ms"),
    ("_us", "µs"),
    ("_s", "s"),
    ("_c", "°C"),
    ("_k", "K"),
    ("_rpm", "rpm"),
    ("_pct", "%"),
    ("_hz", "Hz"),
    ("_a", "A"),
    ("_w", "W"),
    ("_m", "m"),
)


def unit_of(key: str) -> str:
    """The unit a key's name declares, or '' (e.g. `max_slew_um_per_s` → µm/s)."""
    for suffix, unit in UNIT_SUFFIXES:
        if key.endswith(suffix) and len(key) > len(suffix):
            return unit
    return ""


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _models_in(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType, list, tuple, dict):
        return [m for a in typing.get_args(annotation) for m in _models_in(a)]
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return []


def _bounds(metadata: list[Any]) -> list[str]:
    out = []
    for m in metadata:
        if isinstance(m, at.Gt):
            out.append(f"> {m.gt:g}")
        elif isinstance(m, at.Ge):
            out.append(f"≥ {m.ge:g}")
        elif isinstance(m, at.Lt):
            out.append(f"< {m.lt:g}")
        elif isinstance(m, at.Le):
            out.append(f"≤ {m.le:g}")
        elif isinstance(m, at.MinLen) and m.min_length:
            out.append(f"at least {m.min_length} long")
        elif isinstance(m, at.MaxLen):
            out.append(f"at most {m.max_length} long")
    return out


def _anchor(title: str) -> str:
    keep = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return keep.replace(" ", "-")


class _Doc:
    """Collects sections; nested models become their own sections, linked by anchor."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.queue: list[tuple[str, type[BaseModel], int]] = []
        self.titles: dict[type[BaseModel], str] = {}

    def type_of(self, annotation: Any, prefix: str, key: str) -> tuple[str, list[str]]:
        """(human type, bounds found inside it)."""
        origin = typing.get_origin(annotation)
        args = typing.get_args(annotation)
        if origin is Annotated:
            inner, extra = self.type_of(args[0], prefix, key)
            meta = [m for a in args[1:] for m in (a.metadata if isinstance(a, FieldInfo) else [a])]
            return inner, extra + _bounds(meta)
        if origin in (typing.Union, types.UnionType):
            parts, bounds = [], []
            for a in args:
                if a is type(None):
                    continue
                t, b = self.type_of(a, prefix, key)
                parts.append(t)
                bounds += b
            none = " or none" if type(None) in args else ""
            return " or ".join(parts) + none, bounds
        if origin is Literal:
            return "one of " + ", ".join(f"`{a}`" for a in args), []
        if origin is tuple and args and args[-1] is not Ellipsis:  # a fixed pair, triple, …
            parts, bounds = [], []
            for i, a in enumerate(args, start=1):
                t, b = self.type_of(a, f"{prefix}{key}[]", "")
                parts.append(t)
                bounds += [f"item {i} {x}" for x in b]
            return "(" + ", ".join(parts) + ")", bounds
        if origin in (list, tuple):
            t, b = self.type_of(args[0], f"{prefix}{key}[]", "") if args else ("any", [])
            return f"list of {t}", [x if x.startswith("each ") else f"each {x}" for x in b]
        if origin is dict and args and args[1] is Any:
            return "mapping", []
        if origin is dict:
            t, b = self.type_of(args[1], f"{prefix}{key}.<name>", "") if args else ("any", [])
            return f"mapping of name → {t}", [f"each {x}" for x in b]
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            title = self.titles.get(annotation)
            if title is None:
                title = (prefix + key).strip(".")
                self.titles[annotation] = title
                self.queue.append((title, annotation, 3))
            return f"[{title}](#{_anchor(title)})", []  # a section of its own
        names = {float: "number", int: "integer", str: "text", bool: "true/false", Any: "any"}
        return names.get(annotation, getattr(annotation, "__name__", str(annotation))), []

    def table(self, model: type[BaseModel], prefix: str, skip: tuple[str, ...] = ()) -> None:
        self.lines.append("| key | type | unit | default | range | description |")
        self.lines.append("|---|---|---|---|---|---|")
        for key, f in model.model_fields.items():
            if key in skip:
                continue
            typ, bounds = self.type_of(f.annotation, prefix, key)
            bounds = _bounds(f.metadata) + bounds
            self.lines.append(
                f"| `{key}` | {typ} | {unit_of(key) or '—'} | {_default(f)} | {', '.join(bounds) or '—'} |"
                f" {_cell(f.description or '—')} |"
            )
        self.lines.append("")

    def section(self, title: str, model: type[BaseModel], level: int, intro: str = "") -> None:
        self.titles.setdefault(model, title)
        self.lines.append(f"{'#' * level} {title}")
        self.lines.append("")
        doc = intro or _first_paragraph(model)
        if doc:
            self.lines += [doc, ""]
        self.table(model, title + ".")
        self.drain()

    def drain(self) -> None:
        while self.queue:
            title, model, level = self.queue.pop(0)
            self.lines.append(f"{'#' * level} {title}")
            self.lines.append("")
            doc = _first_paragraph(model)
            if doc:
                self.lines += [doc, ""]
            self.table(model, title + ".")


def _first_paragraph(obj: Any) -> str:
    doc = inspect.getdoc(obj) or ""
    if doc.startswith(("Usage docs:", "!!! abstract")) or obj in (BaseModel,):
        return ""
    return " ".join(doc.split("\n\n")[0].split())


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _default(f: FieldInfo) -> str:
    if f.is_required():
        return "**required**"
    value = f.default_factory() if f.default_factory is not None else f.default  # type: ignore[call-arg]
    if value is PydanticUndefined:
        return "**required**"
    if value is None:
        return "none"
    if isinstance(value, BaseModel):
        return "(section)"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, float):
        return f"`{value:g}`"
    return f"`{value}`"


def _kinds(registry: Any) -> Iterator[tuple[str, type]]:
    for kind in registry.kinds():
        yield kind, registry.get(kind)


def generate() -> str:
    """The whole of docs/configuration.md."""
    d = _Doc()
    d.lines += [
        "# Configuration reference",
        "",
        "<!-- generated by `compd docs --out docs/configuration.md` from compd/core/config.py and the",
        "     Config/Params classes of every registered kind; do not edit by hand. -->",
        "",
        "A config is one YAML file. Unknown keys are errors (the message names the file, the line",
        "and the key path, and suggests the nearest known key). Relative paths in a config are",
        "relative to the config file's folder. A key's unit is the suffix of its name:",
        "`_s` seconds, `_um` µm, `_mm` mm, `_c` °C, `_per_k` 1/K, `_um_per_s` µm/s, `_rpm` rpm.",
        "`compd check-config FILE` validates a config without running it. The files compd reads and",
        "writes (log CSV, model file, the 16-bit word, reports, status file) are in [formats.md](formats.md).",
        "",
        "Every number must be finite (`.inf` and `.nan` are refused) and inside the range its",
        "key states below; where a key's limit depends on another key (a signal's `min` below its",
        "`max`, `codec.deadband_um` below the word's full scale 63 × `lsb_um`, staleness and frozen",
        "limits longer than `loop.period_s`), its description says so.",
        "",
        "Limits of the YAML reader (config and model files alike; exceeding one is a one-line error,",
        f"exit 2): a config is a regular file of at most {core_config.CONFIG_MAX_BYTES} bytes holding at most",
        f"{core_config.CONFIG_MAX_VALUES} values; a model file (`model.file`) at most {core_config.MODEL_MAX_BYTES}"
        " bytes",
        f"and {core_config.MODEL_MAX_VALUES} values; mappings and lists nest at most {core_config.MAX_DEPTH} levels;"
        " aliases",
        f"(`*name`, `<<: *name`) expand to at most {core_config.MAX_ALIAS_VALUES} values in all; one YAML document",
        "per file. A merge (`<<`) is overridden by the mapping's own keys.",
        "",
    ]
    sections = []
    for key, f in core_config.ConfigModel.model_fields.items():
        for model in _models_in(f.annotation):
            d.titles[model] = key
            sections.append((key, model))
    d.section("Top level", core_config.ConfigModel, 2)
    for key, model in sections:
        d.section(key, model, 2)
    d.lines += [
        "## Sources",
        "",
        "`sources` is a list; each entry has a `kind` and a unique `name` and publishes named",
        "signals (the signal names are what `model.inputs` and `guard.signals` refer to).",
        "",
    ]
    plugins = SOURCES.plugins()
    for kind, cls in _kinds(SOURCES):
        intro = _first_paragraph(cls.Config) or _first_paragraph(cls)
        if kind in plugins:  # not compd's own: say where it comes from
            intro += (
                f"\n\nNot part of compd: added by an installed package through the entry point"
                f" `{kind} = {plugins[kind].value}` (group `{SOURCES.group}`)."
            )
        d.section(f"sources: kind {kind}", cls.Config, 3, intro)
    d.lines += ["## Models", ""]
    d.section("model", core_config.ModelSection, 3)
    d.section("model: contributions", core_config.ContributionsSection, 3, CONTRIBUTIONS_INTRO)
    d.section(
        "model: contributions, each item",
        core_config.ContributionSection,
        3,
        "A model section as above (kind, file or params, inputs, outputs, update_period_s) with these further keys.",
    )
    for kind, cls in _kinds(MODELS):
        intro = _first_paragraph(sys.modules[cls.__module__])
        d.section(f"model: kind {kind}, params", cls.Params, 3, intro)
    d.lines += ["## Sinks", ""]
    for kind, cls in _kinds(SINKS):
        d.section(f"sink: kind {kind}", cls.Config, 3, _first_paragraph(cls.Config) or _first_paragraph(cls))
    return "\n".join(d.lines).rstrip() + "\n"


CONTRIBUTIONS_INTRO = """\
An axis with several heat sources: `model: {contributions: [...]}` instead of one model. Each
contribution is a model section (its own kind, file or params, inputs and outputs) with an
optional `name` and its own limits; the axis's prediction is the sum of the contributions on
it, and the guard's clamp and slew still bound that sum. A contribution whose inputs go bad
follows its own `fault_policy` while the others keep compensating. Each contribution shows in
the status (`axes.<axis>.contributions.<name>`), the data log (`pred_<axis>_<name>_um`), the
metrics (`compd_contribution_*`), Sparkplug (`Axis/<axis>/Contribution/<name>/…`), OPC UA
(`compd.Axes.<axis>.Contributions.<name>`) and the replay report (`contributions`).

Every contribution's outputs are axes the sink drives: the sink's own `axes` (siemens), else
`codec.axes`, else the first contribution's outputs. Contributions on two axes (a lathe's z and
x) name both in `codec.axes`; an output that is none of them (`Z` beside `z`) is refused, with
the axis it most likely means, never driven as an axis of its own.

```yaml
model:
  contributions:
    - {name: spindle, kind: xi_spindle, file: spindle.yaml, max_abs_um: 40}
    - {name: column, kind: mlr, file: column.yaml, max_slew_um_per_s: 0.5, fault_policy: ramp_to_zero}
```

The top-level `shadow` section takes the same forms as `model` (one model, or contributions):
a candidate evaluated every cycle beside the active model on the axes it names, driving
nothing, scored on the same probes; `compd promote CONFIG` makes it the model."""


def main(argv: list[str] | None = None) -> int:
    """`python -m compd.commissioning.docgen [FILE]`: write the reference (stdout without FILE)."""
    argv = sys.argv[1:] if argv is None else argv
    text = generate()
    if argv:
        with open(argv[0], "w", encoding="utf-8") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
