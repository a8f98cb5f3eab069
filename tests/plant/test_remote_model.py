"""A model from the plant's command topic: refused unless allowed and armed, validated like a reload, applied, acknowledged."""

from __future__ import annotations

import json
import time
from pathlib import Path

from compd.plant.sparkplug import DataType, MetricDef, encode, topic

from .broker import SIM_SPINDLE, Listener, Mosquitto, compd, daemon

MODEL = """kind: xi_spindle
inputs: [T_xi]
outputs: [z]
params: {{alpha_per_k: 13.6e-6, length_mm: {length_mm}}}
fit: {{fitted_at: "{fitted_at}"}}
"""

CONFIG = SIM_SPINDLE + """\
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


def results(listener: Listener) -> list[dict]:
    """The answers to the model commands, in order, each once (a birth repeats the last one)."""
    out: list[dict] = []
    seen: set[str] = set()
    with listener._lock:
        msgs = [m for m in listener.messages if m.kind in ("NDATA", "NBIRTH")]
    for m in msgs:
        for x in m.payload.metrics:
            if x.name == "Model/result" and x.value and x.value not in seen:
                seen.add(x.value)
                out.append(json.loads(x.value))
    return out


def send_model(listener: Listener, text: str, uuid: str) -> None:
    payload = encode([(MetricDef("Node Control/Model", DataType.String), text)], timestamp_ms=int(time.time() * 1000),
                     seq=None)
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
                assert model.read_text() == original  # nothing of theirs reached the file
                births = len(listener.of("NBIRTH"))
                send_model(listener, refit, "r4")
                listener.wait_for(lambda: any(r["result"] == "applied" for r in results(listener)), timeout_s=60)
                assert len(listener.of("NBIRTH")) > births  # the reloaded pipeline was born again
                send_model(listener, MODEL.format(length_mm=140.0, fitted_at="x"), "r5")  # one model per arming
                listener.wait_for(lambda: len([r for r in results(listener) if r["result"] != "applied"]) >= 10)
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
