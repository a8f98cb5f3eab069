"""One pipeline builder: run, replay and observe mode wire their stages through compd.cycle.pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import compd.cycle.pipeline
from compd.commissioning.replay import replay_config
from compd.config import load_config
from compd.core.clock import SimClock
from compd.core.config import CodecConfig, GuardConfig
from compd.core.errors import BadInput
from compd.cycle.pipeline import build_model, build_pipeline
from compd.daemon.app import App
from compd.log import write_log
from compd.sinks.observe import ObserveSink
from compd.sources.replay import ReplayConfig, ReplaySource

CONFIG = """\
loop: {{clock: sim, period_s: 1.0}}
sources:
  - {{kind: replay, name: log, path: {log}}}
model:
  kind: mlr
  inputs: [T1]
  outputs: [x, y]
  params: {{intercept_um: [0.0, 0.0], coef_um_per_k: [[2.0, -1.0]], t0_c: [20.0]}}
guard: {{max_slew_um_per_s: 3.0}}
codec: {{lsb_um: 0.5, deadband_um: 0.5}}
sink: {{kind: fanuc_pmc}}
"""


def _log(path: Path, rows: int = 40) -> Path:
    t = np.arange(rows, dtype=float)
    temp = 20.0 + 0.2 * t
    write_log(path, ["t_s", "T1", "err_x_um", "err_y_um"], np.column_stack([t, temp, 2.0 * (temp - 20), -(temp - 20)]))
    return path


@pytest.fixture
def config(tmp_path: Path) -> Path:
    log = _log(tmp_path / "day.csv")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(log=log.name), encoding="utf-8")
    return cfg


def _spy(monkeypatch: pytest.MonkeyPatch, module: str) -> list[dict]:
    calls: list[dict] = []
    real = compd.cycle.pipeline.build_pipeline

    def spy(**kw):
        calls.append(kw)
        return real(**kw)

    monkeypatch.setattr(f"{module}.build_pipeline", spy)
    return calls


def test_run_and_replay_wire_the_same_stages(config: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    replay_calls = _spy(monkeypatch, "compd.commissioning.replay")
    run_calls = _spy(monkeypatch, "compd.cycle.pipeline")  # App builds through pipeline.from_config
    cfg = load_config(config)
    app = App(cfg)
    result = replay_config(config, config.parent / "day.csv")
    assert len(run_calls) == 1 and len(replay_calls) == 1
    run, rep = run_calls[0], replay_calls[0]
    for key in ("guard_cfg", "codec_cfg"):
        assert run[key] == rep[key]
    assert (run["model"].kind, run["model"].inputs, run["model"].outputs) == (
        rep["model"].kind,
        rep["model"].inputs,
        rep["model"].outputs,
    )
    assert type(run["sink"]) is type(rep["sink"])
    # what the builder wired is what both run: the guard's slew and the encoder's band
    assert app.loop.encoder.lsb_um == 0.5 and app.guard.cfg.max_slew_um_per_s == 3.0
    assert set(result.report["axes"]) == {"x", "y"}


def test_observe_mode_is_the_builders_wrap(config: Path) -> None:
    app = App(load_config(config), observe=True)
    assert isinstance(app.sink, ObserveSink) and app.loop.sink is app.sink


def _parts(tmp_path: Path, guard: GuardConfig | None = None, codec: CodecConfig | None = None, twice: bool = False):
    log = _log(tmp_path / "day.csv")
    srcs = [ReplaySource(ReplayConfig(kind="replay", name="a", path=str(log)))]
    if twice:
        srcs.append(ReplaySource(ReplayConfig(kind="replay", name="b", path=str(log))))
    cfg = load_config_text(tmp_path)
    from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink

    return dict(
        sources=srcs,
        model=build_model(cfg.model),
        sink=FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc")),
        clock=SimClock(0.0),
        period_s=1.0,
        guard_cfg=guard,
        codec_cfg=codec,
    )


def load_config_text(tmp_path: Path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(log="day.csv"), encoding="utf-8")
    return load_config(cfg)


@pytest.mark.parametrize(
    ("case", "keys"),
    [
        ("twice", ("sources",)),
        ("guard_signal", ("guard", "signals", "nope")),
        ("codec_axis", ("codec", "axes")),
    ],
)
def test_wiring_mistakes_name_their_key(tmp_path: Path, case: str, keys: tuple) -> None:
    kw = {
        "twice": {"twice": True},
        "guard_signal": {"guard": GuardConfig(signals={"nope": {}})},
        "codec_axis": {"codec": CodecConfig(axes=["x", "q"])},
    }[case]
    with pytest.raises(BadInput) as e:
        build_pipeline(**_parts(tmp_path, **kw))
    assert e.value.keys == keys
