"""A model from the plant's command topic: refused unless allowed and armed, validated like a reload, applied.

It is acknowledged; it is refused if it would drive an axis into the guard's clamp over its fit range.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from compd.config import ModelSpec, load_model_file, resolve_model
from compd.core.config import GuardConfig
from compd.models.ar1 import AR1, AR1Params
from compd.models.feed_axis import FeedAxis, FeedAxisParams, PositionPoly
from compd.models.mlr import MLR, RiseLinearParams
from compd.plant import remote_model
from compd.plant.remote_model import clamp_check, largest_predictions
from compd.plant.sparkplug import AliasResolver, DataType, MetricDef, encode, topic

from .broker import SIM_SPINDLE, Listener, Mosquitto, compd, daemon

MODEL = """kind: xi_spindle
inputs: [T_xi]
outputs: [z]
params: {{alpha_per_k: 13.6e-6, length_mm: {length_mm}}}
fit: {{fitted_at: "{fitted_at}", input_range: {{T_xi: [18.0, 30.0]}}}}
"""

CONFIG = (
    SIM_SPINDLE
    + """\
model: {{kind: xi_spindle, file: model.yaml}}
guard: {{max_abs_um: 40, max_slew_um_per_s: 2.0}}
sink: {{kind: pci1756}}
status: {{path: status.json, period_s: 0.2}}
telemetry:
  port: {port}
  group_id: plant
  edge_node_id: e1
  device_id: m1
  period_s: 0.2
  reconnect_max_s: 1
  remote_models: {{allow: {allow}}}
"""
)


def results(listener: Listener) -> list[dict]:
    """The answers to the model commands, in order, each once (a birth repeats the last one); the
    NDATA's metrics come by alias, named from the NBIRTH before them."""
    out: list[dict] = []
    seen: set[str] = set()
    resolver = AliasResolver()
    with listener._lock:
        msgs = [m for m in copy.deepcopy(listener.messages) if m.kind in ("NDATA", "NBIRTH")]
    for m in msgs:
        assert not resolver.resolve(m.topic, m.payload), m.topic
        for x in m.payload.metrics:
            if x.name == "Model/result" and x.value and x.value not in seen:
                seen.add(x.value)
                out.append(json.loads(x.value))
    return out


def send_model(listener: Listener, text: str, uuid: str) -> None:
    payload = encode(
        [(MetricDef("Node Control/Model", DataType.String), text)], timestamp_ms=int(time.time() * 1000), seq=None
    )
    listener.client.publish(topic("plant", "NCMD", "e1"), payload, qos=1).wait_for_publish(10)


def test_a_remote_model_is_applied_only_when_armed(tmp_path: Path) -> None:
    model = tmp_path / "model.yaml"
    original = MODEL.format(length_mm=165.0, fitted_at="2026-01-01T00:00:00Z")
    model.write_text(original)
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(port=broker.port, allow="true"))
        assert compd("check-config", str(cfg), cwd=tmp_path).stdout.strip() == "ok"
        listener = Listener(broker.port)
        try:
            with daemon(cfg, tmp_path / "stderr.txt") as proc:
                listener.wait_for(lambda: listener.of("DBIRTH"), timeout_s=60)
                refit = MODEL.format(length_mm=150.0, fitted_at="2026-11-20T10:00:00Z")
                send_model(listener, refit, "r1")  # not armed
                listener.wait_for(lambda: len(results(listener)) >= 1)
                assert results(listener)[0]["result"] == "refused" and "not armed" in results(listener)[0]["reason"]
                arm = compd("arm-model", str(cfg), "--seconds", "120", cwd=tmp_path)
                assert arm.returncode == 0, arm.stderr
                assert "armed for 120 s" in arm.stdout
                # what a model file cannot do: carry limits, or change the axes
                send_model(listener, refit + "guard: {max_abs_um: 10000}\n", "r2")
                send_model(listener, refit.replace("outputs: [z]", "outputs: [x]"), "r3")
                listener.wait_for(lambda: len(results(listener)) >= 3)
                bad = results(listener)[1:3]
                assert [r["result"] for r in bad] == ["refused", "refused"], bad
                assert "unknown key" in bad[0]["reason"] and "axes" in bad[1]["reason"]
                # a peer cannot fill the disk: 5 rejected models are kept, no more
                for i in range(5):
                    send_model(listener, refit.replace("outputs: [z]", f"outputs: [x{i}]"), f"r3.{i}")
                listener.wait_for(lambda: len(results(listener)) >= 8)
                more = results(listener)[3:8]
                assert all(r["result"] == "refused" for r in more), more
                assert ["not kept" in r["reason"] for r in more] == [False, False, False, True, True], more
                assert len(list(tmp_path.glob("model.yaml.rejected-*"))) == 5
                # within every parameter's bounds, but 455 400 µm over its own fit range: the axis
                # would sit at the clamp (guard.max_abs_um 40)
                send_model(listener, ABSURD, "r3.absurd")
                listener.wait_for(lambda: len(results(listener)) >= 9)
                absurd = results(listener)[8]
                assert absurd["result"] == "refused" and absurd["reason"].startswith(f"invalid model: {ABSURD_REASON}")
                assert model.read_text() == original  # nothing of theirs reached the file
                births = len(listener.of("NBIRTH"))
                send_model(listener, refit, "r4")
                listener.wait_for(lambda: any(r["result"] == "applied" for r in results(listener)), timeout_s=60)
                assert len(listener.of("NBIRTH")) > births  # the reloaded pipeline was born again
                send_model(listener, MODEL.format(length_mm=140.0, fitted_at="x"), "r5")  # one model per arming
                listener.wait_for(lambda: len([r for r in results(listener) if r["result"] != "applied"]) >= 11)
                status = json.loads((tmp_path / "status.json").read_text())
        finally:
            listener.stop()
    res = results(listener)
    kinds = [r["result"] for r in res]
    assert kinds.count("accepted") == 1 and kinds.count("applied") == 1, res
    assert kinds[-1] == "refused" and "not armed" in res[-1]["reason"]
    assert not [r for r in res if str(tmp_path) in r.get("reason", "")]  # no folder of this host goes out
    assert model.read_text() == refit  # the new model is the file: a restart runs it too
    backups = list(tmp_path.glob("model.yaml.*.bak"))
    assert len(backups) == 1 and backups[0].read_text() == original  # the old one is kept
    assert status["model"]["fit"]["fitted_at"] == "2026-11-20T10:00:00Z"
    assert status["model"]["coefficients"]["length_mm"] == 150.0
    text = (tmp_path / "stderr.txt").read_text()
    assert "reloaded" in text and proc.returncode == 0, text
    # the refusal is an event of the daemon's too, naming the axis, the size and the clamp
    said = [ln for ln in text.splitlines() if "model_remote" in ln and "sit at the guard's clamp" in ln]
    assert len(said) == 1 and "455400.0 µm" in said[0] and "guard.max_abs_um 40" in said[0], text


def test_remote_models_not_allowed_and_arm_model_says_why(tmp_path: Path) -> None:
    (tmp_path / "model.yaml").write_text(MODEL.format(length_mm=165.0, fitted_at="x"))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(port=1883, allow="false"))
    r = compd("arm-model", str(cfg), cwd=tmp_path)
    assert r.returncode == 2
    assert "telemetry.remote_models.allow" in r.stderr and "Traceback" not in r.stderr
    # allowed, but no daemon runs
    cfg.write_text(CONFIG.format(port=1883, allow="true"))
    r = compd("arm-model", str(cfg), cwd=tmp_path)
    assert r.returncode == 1 and "no compd running" in r.stderr


# --- the clamp check on its own ------------------------------------------------------------------

ABSURD = """kind: xi_spindle
inputs: [T_xi]
outputs: [z]
params: {alpha_per_k: 9.9e-4, length_mm: 100000}
fit: {fitted_at: "2026-11-20T10:00:00Z", input_range: {T_xi: [20.0, 24.6]}}
"""
SANE = ABSURD.replace("alpha_per_k: 9.9e-4, length_mm: 100000", "alpha_per_k: 13.6e-6, length_mm: 150").replace(
    "[20.0, 24.6]", "[20.0, 30.0]"
)
ABSURD_REASON = (
    "axis z would sit at the guard's clamp: over its input range (fit.input_range) the model predicts a"
    " |correction| of 455400.0 µm (at T_xi 24.6 from 20 at start), beyond guard.max_abs_um 40 µm"
)


def spec_of(tmp_path: Path, text: str) -> ModelSpec:
    """A model file's text as the config loader resolves it."""
    path = tmp_path / "m.yaml"
    path.write_text(text)
    doc, data = load_model_file(path)
    return resolve_model({"kind": data["kind"], "file": str(path)}, doc, (), tmp_path)


def spec_for(cls: type, params: Any, inputs: list[str], outputs: list[str], fit: dict | None = None) -> ModelSpec:
    return ModelSpec(cls, params, inputs, outputs, None, fit or {}, None, ())  # type: ignore[arg-type]


def test_an_absurd_model_is_refused_with_the_axis_the_size_the_inputs_and_the_clamp(tmp_path: Path) -> None:
    guard = GuardConfig(max_abs_um=40)
    assert clamp_check(spec_of(tmp_path, ABSURD), guard) == ABSURD_REASON
    assert clamp_check(spec_of(tmp_path, SANE), guard) is None  # 2.04 µm/K over 10 K: 20.4 µm
    # the axis's own clamp is the one it is held to, and named
    tight = GuardConfig(max_abs_um=40, axes={"z": {"max_abs_um": 20}})
    assert clamp_check(spec_of(tmp_path, SANE), tight) == (
        "axis z would sit at the guard's clamp: over its input range (fit.input_range) the model predicts a"
        " |correction| of 20.4 µm (at T_xi 30 from 20 at start), beyond guard.axes.z.max_abs_um 20 µm"
    )


def test_without_a_fit_range_the_guards_signal_limits_or_a_refusal(tmp_path: Path) -> None:
    bare = SANE.replace(", input_range: {T_xi: [20.0, 30.0]}", "")
    why = clamp_check(spec_of(tmp_path, bare), GuardConfig(max_abs_um=40))
    assert why is not None and "records no fit range" in why and "guard.signals.T_xi" in why
    # the readings the guard lets through: 15…33 °C, 18 K × 2.04 µm/K = 36.7 µm, inside 40
    assert (
        clamp_check(spec_of(tmp_path, bare), GuardConfig(max_abs_um=40, signals={"T_xi": {"min": 15, "max": 33}}))
        is None
    )
    why = clamp_check(spec_of(tmp_path, bare), GuardConfig(max_abs_um=40, signals={"T_xi": {"min": 15, "max": 45}}))
    assert why is not None and "(guard.signals)" in why and "61.2 µm" in why and "T_xi 45 from 15 at start" in why


@pytest.mark.parametrize(
    ("fit", "says"),
    [
        ("input_range: [20, 30]", "is not a mapping"),
        ("input_range: {T_xi: [20, 30], T_bed: [20, 22]}", "names 'T_bed', which is not one of its inputs"),
        ("input_range: {T_xi: [30, 20]}", "T_xi: min 30 is above max 20"),
        ("input_range: {T_xi: [20, .nan]}", "T_xi is not [min, max]"),
        ("input_range: {T_xi: [20, true]}", "T_xi is not [min, max]"),
        ("input_range: {T_xi: [20]}", "T_xi is not [min, max]"),
        ("input_range: {}", "T_xi is not [min, max]"),
    ],
)
def test_a_fit_range_of_the_wrong_shape_is_a_refusal(tmp_path: Path, fit: str, says: str) -> None:
    text = SANE.replace(
        'fit: {fitted_at: "2026-11-20T10:00:00Z", input_range: {T_xi: [20.0, 30.0]}}', f"fit: {{{fit}}}"
    )
    why = clamp_check(spec_of(tmp_path, text), GuardConfig(max_abs_um=40))
    assert why is not None and says in why, why


def test_a_linear_model_with_many_inputs_is_searched_exactly() -> None:
    """8 inputs: 4^8 combinations, more than are tried one by one; the coordinate search finds the
    exact largest |prediction| of a linear model: |b| + Σ |B_i| (max_i − min_i), the references free."""
    rng = np.random.default_rng(3)
    coef = rng.normal(0, 2, size=(8, 2))
    params = RiseLinearParams(coef_um_per_k=coef.tolist(), intercept_um=[1.5, -2.0])
    names = [f"T{i}" for i in range(8)]
    ranges = {n: (20.0 + i, 25.0 + 2 * i) for i, n in enumerate(names)}
    span = np.array([hi - lo for lo, hi in ranges.values()])
    peaks = largest_predictions(spec_for(MLR, params, names, ["x", "z"]), ranges)
    for a, (peak, reference, reading) in enumerate(peaks):
        exact = abs(params.intercept_um[a]) + float(np.abs(coef[:, a]) @ span)
        assert abs(peak) == pytest.approx(exact)
        rise = reading - reference
        assert np.allclose(np.abs(rise), span) and np.all(np.sign(rise) * np.sign(coef[:, a]) * np.sign(peak) > 0)
    # a fixed reference (t0_c) is the model's: only the readings move
    fixed = RiseLinearParams(coef_um_per_k=[[2.0]], intercept_um=[0.0], t0_c=[20.0])
    ((peak, _, reading),) = largest_predictions(spec_for(MLR, fixed, ["T0"], ["z"]), {"T0": (15.0, 22.0)})
    assert peak == pytest.approx(-10.0) and reading[0] == 15.0


def test_a_recursive_model_is_held_until_it_settles() -> None:
    """ar1: S grows by C2 a step toward C2/(1 − C1); 8 h of 60 s steps at the top speed: 480 steps."""
    params = AR1Params(dt_s=60, c1=0.99, c2_table=[(2000.0, 0.2)], bed_gain_um_per_k=[1.0])
    spec = spec_for(
        AR1, params, ["speed_rpm", "T_bed"], ["z"], {"input_range": {"speed_rpm": [0.0, 2000.0], "T_bed": [20.0, 23.0]}}
    )
    ((peak, _, reading),) = largest_predictions(spec, {"speed_rpm": (0.0, 2000.0), "T_bed": (20.0, 23.0)})
    steps = int(remote_model.HORIZON_S / 60)
    s_um = 0.2 * (1 - 0.99**steps) / (1 - 0.99)  # the start row (a cold start) adds nothing, then 480 steps
    assert abs(peak) == pytest.approx(s_um + 3.0, rel=1e-6) and reading[0] == 2000.0
    why = clamp_check(spec, GuardConfig(max_abs_um=15))
    assert why is not None and f"{abs(peak):.1f} µm" in why and "speed_rpm 2000" in why


def test_a_position_input_is_swept_along_its_range() -> None:
    """A position polynomial whose largest error is in the middle of the stroke (4u − 4u²): found there."""
    params = FeedAxisParams(
        length_mm=600,
        input_roles=["position", "rise"],
        position_poly=PositionPoly(degree=2, coef_um_per_k=[[0.0, 4.0, -4.0]]),
    )
    spec = spec_for(FeedAxis, params, ["pos_y_mm", "T_slide"], ["y"])
    ((peak, reference, reading),) = largest_predictions(spec, {"pos_y_mm": (0.0, 600.0), "T_slide": (20.0, 30.0)})
    assert abs(peak) == pytest.approx(10.0) and reading[0] == 300.0 and reference[0] == 300.0
