"""The one pipeline builder: sources → frame → model → guard → codec → sink on a loop.

`compd run` (and its observe mode and reloads), `compd check-config`, `compd replay`,
`compd output-test` and `compd bench` all wire their stages here, so the daemon a user runs and the replay a user trusts
before it are the same pipeline. The caller supplies what differs: where the
signals come from (configured sources, or one log), the clock, the sink.
Wiring mistakes are `BadInput` with the config key they concern (`keys`), for the
caller to place in its file.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import overload

from compd.codec import Encoder
from compd.config import Config, ModelSpec, model_sha256
from compd.core.clock import Clock, SimClock, WallClock
from compd.core.config import (
    AdaptConfig,
    CodecConfig,
    GuardConfig,
    InhibitConfig,
    LoopConfig,
    SinkConfig,
    SourceConfig,
)
from compd.core.errors import BadInput
from compd.core.frame import Frame
from compd.core.registry import entry_point, load_entry_point
from compd.cycle.adapt import Adapter
from compd.cycle.contributions import Contributions
from compd.cycle.guard import Guard
from compd.cycle.inhibit import Inhibit
from compd.cycle.loop import Loop
from compd.cycle.shadow import Shadow
from compd.models.base import Model
from compd.sinks.base import Sink
from compd.sinks.observe import ObserveSink
from compd.sources.base import Source


def build_model(spec: ModelSpec) -> Model:
    """Instantiate the model of a resolved model section (a config's or a model file's); a sum of
    contributions (no class in the spec: compd.config) is the cycle's stage `Contributions`."""
    cls = Contributions if spec.cls is None else spec.cls
    model = cls(spec.params, spec.inputs, spec.outputs, spec.fit)
    model.file = spec.file
    if spec.update_period_s is not None:
        model.update_period_s = spec.update_period_s
    return model


def build_clock(lp: LoopConfig, sources: Sequence[Source]) -> Clock:
    """The loop's clock from the `loop` section: simulated time from the sources' start,
    a simulated plant's clock (followed, or in lockstep), or the wall clock."""
    pc = lp.plant_clock
    if lp.clock == "sim":
        start_s = min((0.0 if s.start_s is None else s.start_s for s in sources), default=0.0)
        return SimClock(start_s, lp.speedup)
    if lp.clock == "plant" and pc is not None:  # a simulated plant's clock: the simulator brings it
        ep = entry_point("compd.clocks", "plant")
        if ep is None:
            raise BadInput(
                "loop.clock: plant needs the simulator's plant clock, which is not installed (no 'plant'"
                " in entry point group compd.clocks: install compd from its source tree)",
                path=("loop", "clock"),
            )
        return load_entry_point(ep, "the plant clock", path=("loop", "clock"))(pc)
    return WallClock(lp.spin_margin_s)


IN_SAMPLE_FACTOR = 2.0  # a file without a held-out figure: its in-sample RMSE, doubled (rows it saw flatter it)


def held_out_sigma_um(model: Model) -> dict[str, float]:
    """Per axis how far the model is off at any moment on days it was not fitted to (the probe adapter's
    σ_m): its fit's held-out RMSE (the file's fit.held_out_rmse_um), else twice its in-sample `rmse_um`
    (files written before the held-out figure); nothing for a model without either."""
    out: dict[str, float] = {}
    for key, factor in (("rmse_um", IN_SAMPLE_FACTOR), ("held_out_rmse_um", 1.0)):
        figures = model.fit_info.get(key)
        if not isinstance(figures, dict):
            continue
        for axis, v in figures.items():
            if isinstance(axis, str) and isinstance(v, int | float) and not isinstance(v, bool) and 0 <= v < 1e4:
                out[axis] = factor * float(v)
    return out


@dataclass
class Pipeline:
    """The wired stages and the loop that runs them."""

    sources: list[Source]
    frame: Frame
    model: Model
    guard: Guard
    encoder: Encoder
    sink: Sink
    loop: Loop
    word_axis_names: list[str]
    shadow: Shadow | None = None


def build_pipeline(
    *,
    sources: Sequence[Source],
    model: Model,
    sink: Sink,
    clock: Clock,
    period_s: float,
    guard_cfg: GuardConfig | None = None,
    codec_cfg: CodecConfig | None = None,
    observe: bool = False,
    adapt_cfg: AdaptConfig | None = None,
    inhibit_cfg: InhibitConfig | None = None,
    shadow: Model | None = None,
) -> Pipeline:
    """Wire the stages: one frame of every source's signals, the guard on the model's
    inputs, the word's two axes (`codec.axes`, else the model's first two outputs),
    the sink bound to them (held disabled when `observe`), the probe adapter when
    `adapt_cfg` is given (between the model and the guard), the machine's inhibit and
    referenced signals when `inhibit_cfg` is given (the guard's hold), and the loop."""
    guard_cfg = guard_cfg or GuardConfig()
    codec_cfg = codec_cfg or CodecConfig()
    sources = list(sources)
    names = [n for s in sources for n in s.signal_names()]
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise BadInput(f"signal {n!r} is published by two sources", path=("sources",))
        seen.add(n)
    frame = Frame(names)
    for s in sources:
        s.bind(frame)
    try:
        guard = Guard(guard_cfg, model.outputs, frame, model.inputs)
    except BadInput as e:
        raise BadInput(e.message, path=("model", "inputs")) from None
    for name in guard_cfg.signals:
        if name not in frame.index:
            raise BadInput(f"{name!r} is not a signal of any source", path=("guard", "signals", name))
    model.emit = guard.event  # the model's own events (a contribution's fault, clamp) are the guard's
    inhibit = Inhibit(inhibit_cfg, model.outputs, frame) if inhibit_cfg is not None else None
    word_names = list(codec_cfg.axes or model.outputs[:2])
    for name in word_names:
        if name not in model.outputs:
            raise BadInput(f"{name!r} is not an output of the model", path=("codec", "axes"))
    encoder = Encoder(codec_cfg.lsb_um, codec_cfg.deadband_um)
    encoder.bind_axes(word_names, list(model.outputs))
    if observe:  # commissioning: the full loop, the output held disabled
        sink = ObserveSink(sink, guard_cfg.ramp_um_per_s, codec_cfg.deadband_um)
    sink.bind(encoder.axis_names, codec_cfg.lsb_um)
    sink.bind_model(model)  # sinks that speak per-axis values (siemens) keep it
    loop = Loop(
        period_s=period_s,
        clock=clock,
        frame=frame,
        sources=sources,
        model=model,
        guard=guard,
        encoder=encoder,
        sink=sink,
        adapter=Adapter(adapt_cfg, list(model.outputs), held_out_sigma_um(model)) if adapt_cfg is not None else None,
        inhibit=inhibit,
    )
    if loop.adapter is not None:
        loop.adapter.bind(frame.index)
        for s in sources:
            s.bind_probes(loop.adapter.inbox)
    if shadow is not None:  # a candidate beside the active model, driving nothing (compd.cycle.shadow)
        try:
            loop.shadow = Shadow(shadow, frame, guard_cfg, list(model.outputs))
        except BadInput as e:
            raise BadInput(e.message, path=("shadow", "inputs")) from None
    return Pipeline(sources, frame, model, guard, encoder, sink, loop, word_names, loop.shadow)


@overload
def _built(cfg: Config, path: tuple[str | int, ...], cls: type[Source], section: SourceConfig, base: str) -> Source: ...
@overload
def _built(cfg: Config, path: tuple[str | int, ...], cls: type[Sink], section: SinkConfig, base: str) -> Sink: ...
def _built(
    cfg: Config,
    path: tuple[str | int, ...],
    cls: Callable[..., Source | Sink],
    section: SourceConfig | SinkConfig,
    base: str,
) -> Source | Sink:
    """A source or sink from its section (a source's class with a source's, a sink's with a sink's);
    its own BadInput names the config file and key."""
    try:
        built = cls(section, base_dir=base)
    except BadInput as e:
        if e.file:
            raise
        raise cfg.doc.error(e.message, path) from None
    built.config_path = path
    return built


def from_config(cfg: Config, *, observe: bool | None = None) -> tuple[Pipeline, Clock]:
    """The pipeline a config describes and its clock, built and wired, nothing opened (no
    device, no socket, no file): what `compd run` opens, and what `check` validates. A wiring
    mistake is BadInput naming the config file, line and key."""
    top = cfg.top
    lp = top.loop
    base = str(Path(cfg.file).parent)
    sources = [_built(cfg, path, cls, scfg, base) for cls, scfg, path in cfg.sources]
    sink_cls, sink_cfg, sink_path = cfg.sink
    sink = _built(cfg, sink_path, sink_cls, sink_cfg, base)
    clock = build_clock(lp, sources)
    try:
        shadow = None
        if cfg.shadow is not None:
            shadow = build_model(cfg.shadow)
            shadow.sha256 = model_sha256(cfg.shadow)  # the status says which shadow its score is of (compd promote)
        p = build_pipeline(
            sources=sources,
            model=build_model(cfg.model),
            sink=sink,
            clock=clock,
            period_s=lp.period_s,
            guard_cfg=top.guard,
            codec_cfg=top.codec,
            observe=top.observe if observe is None else observe,
            adapt_cfg=top.adapt,
            inhibit_cfg=top.inhibit,
            shadow=shadow,
        )
    except BadInput as e:
        raise cfg.doc.error(e.message, e.keys) from None
    return p, clock
