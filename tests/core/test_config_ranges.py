"""Every number in a config is finite and in its stated range, and whatever
`check-config` accepts runs: a property test drives accepted configs, drawn across the
ranges and their edges, through the simulator for a few hundred cycles."""

from __future__ import annotations

import contextlib
import io
import math
import threading
import types
import typing
from pathlib import Path
from typing import Annotated, Any

import annotated_types as at
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from compd import config as c
from compd.cli import main
from compd.codec import MAX_MAG
from compd.config import load_config
from compd.core.errors import ConfigError
from compd.daemon.app import App
from compd.log import read_log
from compd.sinks import SINKS
from compd.sources import SOURCES

BASE: dict[str, Any] = {
    "loop": {"clock": "sim", "period_s": 0.1},
    "sources": [
        {
            "kind": "sim",
            "name": "spindle",
            "plant": "spindle",
            "scenario": {"segments": [{"duration_s": 1e6, "speed_rpm": 8000}]},
        }
    ],
    "model": {
        "kind": "xi_spindle",
        "inputs": ["T_xi"],
        "outputs": ["z"],
        "params": {"alpha_per_k": 13.6e-6, "length_mm": 165.0},
    },
    "guard": {"max_slew_um_per_s": 2.0, "signals": {"T_xi": {"min": 0.0, "max": 80.0}}},
    "sink": {"kind": "pci1756"},
}


def _with(path: str, value: Any) -> dict[str, Any]:
    data = yaml.safe_load(yaml.safe_dump(BASE))
    *parents, last = path.split(".")
    node = data
    for p in parents:
        node = node.setdefault(p, {})
    node[last] = value
    return data


# ------------------------------------------------ the audit's cases: refused, exit 2


AUDIT = [
    ("guard.max_slew_um_per_s", math.inf, "finite"),
    ("guard.signals.T_xi.min", math.nan, "finite"),
    ("guard.signals.T_xi.max", math.nan, "finite"),
    ("codec.deadband_um", math.inf, "finite"),
    ("loop.period_s", 1e-320, "0.0005"),
    ("codec.lsb_um", 1e-320, "0.01"),
    ("log.flush_s", math.inf, "finite"),
    ("guard.max_abs_um", 1e300, "10000"),
    ("guard.ramp_um_per_s", 1e-320, "0.0001"),
    ("guard.stale_after_s", math.inf, "finite"),
    ("model.params.alpha_per_k", math.inf, "finite"),
    ("sources.0.sample_period_s", math.nan, "finite"),
]


def _yaml_number(v: float) -> str:
    if math.isnan(v):
        return ".nan"
    if math.isinf(v):
        return ".inf" if v > 0 else "-.inf"
    return repr(v)


def _refused(tmp_path: Path, data: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> str:
    p = tmp_path / "c.yaml"
    text = yaml.safe_dump(data)
    for v in (math.inf, math.nan):  # PyYAML writes .inf/.nan itself; keep the test explicit
        text = text.replace(yaml.safe_dump(v).split("\n")[0], _yaml_number(v))
    p.write_text(text)
    code = main(["check-config", str(p)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.count("\n") == 0 and str(p) in err and "Traceback" not in err
    return err


@pytest.mark.parametrize(("path", "value", "word"), AUDIT, ids=[a[0] for a in AUDIT])
def test_audit_values_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], path: str, value: float, word: str
) -> None:
    if path.startswith("sources.0."):
        data = yaml.safe_load(yaml.safe_dump(BASE))
        data["sources"][0][path.split(".")[-1]] = value
        key = "sources[0]." + path.split(".")[-1]
    else:
        data, key = _with(path, value), path
    err = _refused(tmp_path, data, capsys)
    assert f": {key}: " in err and word in err, err


@pytest.mark.parametrize(
    ("path", "value", "key", "word"),
    [
        ("guard.signals.T_xi", {"min": 50.0, "max": 50.0}, "guard.signals.T_xi", "below max"),
        ("codec", {"lsb_um": 0.01, "deadband_um": 0.63}, "codec", "full scale"),
        ("guard.stale_after_s", 0.05, "guard.stale_after_s", "one cycle"),
        ("guard.signals.T_xi", {"frozen_after_s": 0.1}, "guard.signals.T_xi.frozen_after_s", "one cycle"),
    ],
)
def test_cross_field_limits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], path: str, value: Any, key: str, word: str
) -> None:
    err = _refused(tmp_path, _with(path, value), capsys)
    assert f": {key}: " in err and word in err, err


# ------------------------------------ every numeric key of every config class has a range


def _config_classes() -> list[type[BaseModel]]:
    roots: list[type[BaseModel]] = [c.ConfigModel, c.ModelSection]
    roots += [SOURCES.get(k).Config for k in SOURCES.kinds()] + [SINKS.get(k).Config for k in SINKS.kinds()]
    seen: list[type[BaseModel]] = []
    stack = list(roots)
    while stack:
        m = stack.pop()
        if m in seen:
            continue
        seen.append(m)
        for f in m.model_fields.values():
            todo = [f.annotation]
            while todo:
                a = todo.pop()
                todo.extend(typing.get_args(a))
                if isinstance(a, type) and issubclass(a, BaseModel):
                    stack.append(a)
    return seen


def _numbers(annotation: Any, meta: list[Any]) -> list[list[Any]]:
    """The metadata of every int/float inside an annotation (Optional, list, dict, Annotated)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is Annotated:
        return _numbers(args[0], meta + list(args[1:]))
    if origin in (typing.Union, types.UnionType):
        return [m for a in args for m in _numbers(a, meta)]
    if origin in (list, tuple, dict):
        return [m for m in _numbers(args[-1], [])] if args else []
    if annotation in (int, float):
        return [meta]
    return []


def test_every_numeric_key_has_a_stated_range() -> None:
    missing = []
    for model in _config_classes():
        for key, f in model.model_fields.items():
            for meta in _numbers(f.annotation, list(f.metadata)):
                flat = [x for m in meta for x in (getattr(m, "metadata", None) or [m])]
                low = any(isinstance(x, at.Ge | at.Gt) for x in flat)
                high = any(isinstance(x, at.Le | at.Lt) for x in flat)
                if not (low and high):
                    missing.append(f"{model.__name__}.{key}")
    assert not missing, f"numeric keys without a lower and upper bound: {missing}"


# ------------------------------------------- accepted configs run (property test)


def _between(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Anywhere in [lo, hi], the edges drawn often (a range's edges are where bugs live)."""
    return st.one_of(st.sampled_from([lo, hi]), st.floats(lo, hi, allow_nan=False, allow_infinity=False))


@st.composite
def accepted_config(draw: st.DrawFn) -> dict[str, Any]:
    period = draw(_between(0.0005, 60.0))
    lsb = draw(_between(0.01, 100.0))
    lo = draw(_between(-1e6, 1e6 - 1))
    hi = draw(_between(lo, 1e6).filter(lambda x: x > lo))
    stale = draw(_between(period * 1.001, 86400.0))
    signal: dict[str, Any] = {"min": lo, "max": hi}
    if draw(st.booleans()):
        signal["max_rate_per_s"] = draw(_between(1e-9, 1e6))
        signal["rate_allowance"] = draw(_between(0.0, 1e6))
    if draw(st.booleans()):
        signal["stale_after_s"] = draw(_between(period * 1.001, 86400.0))
    if draw(st.booleans()):
        signal["frozen_after_s"] = draw(_between(period * 1.001, 7 * 86400.0))
        signal["frozen_band"] = draw(_between(0.0, 1e6))
    data = yaml.safe_load(yaml.safe_dump(BASE))
    data["loop"] = {
        "clock": "sim",
        "period_s": period,
        "speedup": draw(st.sampled_from([0.0, 1e6])),
        "spin_margin_s": draw(_between(0.0, 0.01)),
        "gil_switch_interval_s": draw(_between(1e-9, 0.005)),
    }
    data["sources"][0]["sample_period_s"] = draw(_between(0.0, 3600.0))
    data["model"]["update_period_s"] = draw(st.none() | _between(0.0, 86400.0))
    data["guard"] = {
        "max_abs_um": draw(_between(1e-9, 10_000.0)),
        "max_slew_um_per_s": draw(_between(1e-4, 1000.0)),
        "ramp_um_per_s": draw(_between(1e-4, 1000.0)),
        "recovery_s": draw(_between(0.0, 3600.0)),
        "fault_policy": draw(st.sampled_from(["hold", "ramp_to_zero", "disable"])),
        "stale_after_s": stale,
        "signals": {"T_xi": signal},
    }
    if draw(st.booleans()):
        data["guard"]["axes"] = {
            "z": {
                "max_abs_um": draw(_between(1e-9, 10_000.0)),
                "max_slew_um_per_s": draw(_between(1e-4, 1000.0)),
                "fault_policy": draw(st.sampled_from(["hold", "ramp_to_zero", "disable"])),
            }
        }
    data["codec"] = {"lsb_um": lsb, "deadband_um": draw(_between(0.0, min(100.0, MAX_MAG * lsb * 0.999)))}
    data["log"] = {
        "path": "run.csv",
        "period_s": draw(_between(0.0005, 86400.0)),
        "flush_s": draw(_between(0.01, 3600.0)),
        "rotate_bytes": draw(st.none() | st.sampled_from([1024, 1 << 40])),
        "rotate_s": draw(st.none() | _between(1.0, 366 * 86400.0)),
        "keep": draw(st.sampled_from([0, 1, 1000])),
    }
    data["console"] = {"period_s": draw(_between(0.0, 86400.0))}
    data["state"] = {"path": "state.json"}
    data["status"] = {"path": "status.json", "period_s": draw(_between(0.05, 60.0))}
    return data


@pytest.mark.slow
@settings(
    max_examples=int(__import__("os").environ.get("COMPD_RANGE_EXAMPLES", "40")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(accepted_config())
def test_accepted_configs_run(tmp_path_factory: pytest.TempPathFactory, data: dict[str, Any]) -> None:
    d = tmp_path_factory.mktemp("run")
    p = d / "c.yaml"
    p.write_text(yaml.safe_dump(data))
    try:
        cfg = load_config(p)
    except ConfigError as e:  # the strategy should only draw accepted configs
        assume(False)
        raise AssertionError(e) from None
    crashed: list[str] = []
    hook = threading.excepthook
    threading.excepthook = lambda a: crashed.append(f"{a.thread.name if a.thread else '?'}: {a.exc_value!r}")
    try:
        app = App(cfg, out=io.StringIO())
        app.open()
        try:
            app.loop.run(max_cycles=300)
        finally:
            app.close()
    finally:
        threading.excepthook = hook
    assert not crashed, crashed
    s = app.summary_dict()
    assert s["log_error"] is None and s["state_error"] is None, s
    assert app.loop.stats.cycles == 300
    log = read_log(d / "run.csv", allow_nan=True)
    assert len(log) >= 1
    with contextlib.suppress(FileNotFoundError):
        (d / "run.csv").unlink()
