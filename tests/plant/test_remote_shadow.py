"""A remote model sent as the shadow: installed without arming, checked against the shadow section.

Sent by NCMD `Node Control/Shadow` or DCMD `Model/shadow`. The model itself is still armed for; a shadow is refused
where there is no shadow file to replace.
"""

from __future__ import annotations

import hashlib
import json
import math
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from compd.config import load_config
from compd.core.errors import BadInput
from compd.plant import remote_model
from compd.plant.remote_model import RemoteModels
from compd.plant.sparkplug import DataType, MetricDef, encode, topic
from compd.plant.spec import telemetry_spec

from .broker import SIM_SPINDLE, Listener, Mosquitto, compd, daemon
from .test_remote_model import MODEL, results

# the active model: the spindle at 165 mm; the shadow: the same spindle, another length
ORIGINAL = MODEL.format(length_mm=165.0, fitted_at="2026-01-01T00:00:00Z")
OLD_SHADOW = MODEL.format(length_mm=160.0, fitted_at="2026-02-01T00:00:00Z")
NEW_SHADOW = MODEL.format(length_mm=150.0, fitted_at="2026-11-20T10:00:00Z")
# a model of another kind than the shadow section's, on the same input and axis
OTHER_KIND = """kind: mlr
inputs: [T_xi]
outputs: [z]
params: {coef_um_per_k: [[2.0]], intercept_um: [0.0]}
"""

CONFIG = (
    SIM_SPINDLE
    + """\
model: {{kind: xi_spindle, file: model.yaml}}
{shadow}
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
  remote_models: {{allow: true}}
"""
)
SHADOW_FILE = "shadow: {kind: xi_spindle, file: shadow.yaml}"

_request = iter(range(1, 1 << 30))


def send(listener: Listener, name: str, text: str) -> str:
    """`text` in the command metric `name` (an NCMD's `Node Control/…`, else a DCMD to device m1), by
    name; the request id its answers carry (the payload's timestamp, distinct per command)."""
    ts = int(time.time() * 1000) * 1000 + next(_request)
    payload = encode([(MetricDef(name, DataType.String), text)], timestamp_ms=ts, seq=None)
    where = topic("plant", "NCMD", "e1") if name.startswith("Node Control/") else topic("plant", "DCMD", "e1", "m1")
    listener.client.publish(where, payload, qos=1).wait_for_publish(10)
    return str(ts)


def answers(listener: Listener, request: str) -> list[dict[str, Any]]:
    return [r for r in results(listener) if r.get("request") == request]


def answered(listener: Listener, request: str, result: str, timeout_s: float = 60) -> dict[str, Any]:
    """The answer `result` to `request`, waited for (the first answer of another result fails at once)."""
    listener.wait_for(
        lambda: any(r["result"] in (result, "refused", "failed") for r in answers(listener, request)),
        timeout_s=timeout_s,
    )
    got = [r for r in answers(listener, request) if r["result"] in (result, "refused", "failed")]
    assert got[0]["result"] == result, got
    return got[0]


def status_when(folder: Path, cond: Any, timeout_s: float = 60) -> dict[str, Any]:
    """The daemon's status record once `cond` holds for it."""
    deadline = time.monotonic() + timeout_s
    status: dict[str, Any] = {}
    while time.monotonic() < deadline:
        try:
            status = json.loads((folder / "status.json").read_text())
        except (OSError, ValueError):
            status = {}
        if status and cond(status):
            return status
        time.sleep(0.05)
    raise TimeoutError(f"the status did not come to it in {timeout_s} s: {status}")


def born(listener: Listener, kind: str) -> set[str]:
    return {m.name for m in listener.of(kind)[0].payload.metrics}


def test_a_shadow_is_installed_without_arming_and_the_model_still_needs_it(tmp_path: Path) -> None:
    model, shadow = tmp_path / "model.yaml", tmp_path / "shadow.yaml"
    model.write_text(ORIGINAL)
    shadow.write_text(OLD_SHADOW)
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(port=broker.port, shadow=SHADOW_FILE))
        check = compd("check-config", str(cfg), cwd=tmp_path)
        assert check.stdout.strip() == "ok", check.stderr
        listener = Listener(broker.port)
        try:
            with daemon(cfg, tmp_path / "stderr.txt") as proc:
                listener.wait_for(lambda: listener.of("DBIRTH") and listener.of("NBIRTH"), timeout_s=60)
                # a node that takes remote models declares both commands (each gets an alias)
                assert {"Model/apply", "Model/shadow"} <= born(listener, "DBIRTH")
                assert {"Node Control/Model", "Node Control/Shadow"} <= born(listener, "NBIRTH")
                before = status_when(tmp_path, lambda s: (s.get("shadow") or {}).get("model"))
                assert before["shadow"]["model"]["fitted_at"] == "2026-02-01T00:00:00Z"
                # (b) the model itself: still refused while not armed
                r_apply = send(listener, "Model/apply", NEW_SHADOW)
                assert "not armed" in answered(listener, r_apply, "refused")["reason"]
                # (c) a shadow of another kind than the shadow section's, one on an axis the model lacks
                r_kind = send(listener, "Model/shadow", OTHER_KIND)
                r_axis = send(listener, "Node Control/Shadow", NEW_SHADOW.replace("outputs: [z]", "outputs: [x]"))
                why_kind = answered(listener, r_kind, "refused")["reason"]
                why_axis = answered(listener, r_axis, "refused")["reason"]
                assert why_kind.startswith("invalid shadow:") and "'mlr', not 'xi_spindle'" in why_kind, why_kind
                assert why_axis.startswith("invalid shadow:") and "not among the running model's ['z']" in why_axis
                assert shadow.read_text() == OLD_SHADOW and not list(tmp_path.glob("shadow.yaml.*.bak"))
                # (a) a good shadow, not armed: accepted, the daemon reloads, the reloaded pipeline answers
                births = len(listener.of("NBIRTH"))
                r_good = send(listener, "Model/shadow", NEW_SHADOW)
                accepted = answered(listener, r_good, "accepted")
                applied = answered(listener, r_good, "applied")
                assert len(listener.of("NBIRTH")) > births  # the reloaded pipeline was born again
                after = status_when(
                    tmp_path,
                    lambda s: ((s.get("shadow") or {}).get("model") or {}).get("fitted_at") == "2026-11-20T10:00:00Z",
                )
                # the shadow predicts on the axis once it has good inputs
                status_when(
                    tmp_path, lambda s: isinstance(((s.get("axes") or {}).get("z") or {}).get("shadow_um"), float)
                )
        finally:
            listener.stop()
    text = (tmp_path / "stderr.txt").read_text()
    assert proc.returncode == 0 and "reloaded" in text, text
    assert accepted["target"] == applied["target"] == "shadow"
    assert applied["sha256"] == accepted["sha256"]
    # the shadow is the text sent, the old one kept; the active model is untouched
    assert shadow.read_text() == NEW_SHADOW
    backups = list(tmp_path.glob("shadow.yaml.*.bak"))
    assert len(backups) == 1 and backups[0].read_text() == OLD_SHADOW
    assert model.read_text() == ORIGINAL and not list(tmp_path.glob("model.yaml.*"))
    assert after["shadow"]["model"]["kind"] == "xi_spindle" and after["shadow"]["model"]["file"] == str(shadow)
    assert after["model"]["fit"]["fitted_at"] == "2026-01-01T00:00:00Z"
    assert after["model"]["coefficients"]["length_mm"] == 165.0
    # the refused ones are kept beside the shadow file for the engineer, named for it
    assert len(list(tmp_path.glob("shadow.yaml.rejected-*"))) == 2
    res = results(listener)
    assert not [r for r in res if str(tmp_path) in r.get("reason", "")]  # no folder of this host goes out


def test_a_config_without_a_shadow_section_refuses_a_shadow(tmp_path: Path) -> None:
    (tmp_path / "model.yaml").write_text(ORIGINAL)
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(CONFIG.format(port=broker.port, shadow=""))
        listener = Listener(broker.port)
        try:
            with daemon(cfg, tmp_path / "stderr.txt") as proc:
                listener.wait_for(lambda: listener.of("DBIRTH"), timeout_s=60)
                refused = answered(listener, send(listener, "Model/shadow", NEW_SHADOW), "refused")
        finally:
            listener.stop()
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()
    assert refused["target"] == "shadow" and "no shadow section" in refused["reason"], refused
    assert (tmp_path / "model.yaml").read_text() == ORIGINAL and sorted(p.name for p in tmp_path.glob("*.yaml*")) == [
        "c.yaml",
        "model.yaml",
    ]  # nothing written, nothing kept


# --- RemoteModels on its own: the daemon is this process (its SIGHUP caught) -----------------------


@pytest.fixture
def hups() -> Iterator[list[int]]:
    """SIGHUPs this process receives while the test runs (the reloads a handler asks for)."""
    got: list[int] = []
    old = signal.signal(signal.SIGHUP, lambda signum, frame: got.append(signum))
    try:
        yield got
    finally:
        signal.signal(signal.SIGHUP, old)


def remote(tmp_path: Path, model: str, shadow: str | None, remote_models: str = "{allow: true}") -> RemoteModels:
    """The remote model handler of a daemon on config `model`/`shadow` sections (this process its daemon)."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        CONFIG.format(port=1883, shadow=f"shadow: {shadow}" if shadow else "")
        .replace("model: {kind: xi_spindle, file: model.yaml}", f"model: {model}")
        .replace("remote_models: {allow: true}", f"remote_models: {remote_models}")
    )
    c = load_config(cfg)
    tspec = telemetry_spec(c, [], list(c.model.outputs), 0.2)
    assert tspec.remote is not None
    return RemoteModels(tspec.remote)


MODEL_FILE = "{kind: xi_spindle, file: model.yaml}"
INLINE = "{kind: xi_spindle, inputs: [T_xi], outputs: [z], params: {alpha_per_k: 13.6e-6, length_mm: 165.0}}"
CONTRIBUTIONS = "{contributions: [{name: spindle, kind: xi_spindle, file: model.yaml}]}"


@pytest.fixture
def files(tmp_path: Path) -> Path:
    (tmp_path / "model.yaml").write_text(ORIGINAL)
    (tmp_path / "shadow.yaml").write_text(OLD_SHADOW)
    return tmp_path


@pytest.mark.parametrize(
    ("model", "shadow", "says"),
    [
        (MODEL_FILE, None, "the config has no shadow section"),
        (MODEL_FILE, INLINE, "the config's shadow is given as inline params"),
        (MODEL_FILE, CONTRIBUTIONS, "the config's shadow is a set of contributions"),
        # the shadow's file is the model's: sending a shadow would change what drives the machine
        (MODEL_FILE, "{kind: xi_spindle, file: model.yaml}", "one the active model reads"),
        (CONTRIBUTIONS, "{kind: xi_spindle, file: model.yaml}", "one the active model reads"),
    ],
)
def test_a_shadow_with_no_file_of_its_own_to_replace_is_refused(
    files: Path, hups: list[int], model: str, shadow: str | None, says: str
) -> None:
    rm = remote(files, model, shadow)
    answer = rm.handle(NEW_SHADOW, "r1", "shadow")
    assert answer["result"] == "refused" and says in answer["reason"], answer
    assert (files / "model.yaml").read_text() == ORIGINAL and (files / "shadow.yaml").read_text() == OLD_SHADOW
    assert not hups and not rm.spec.pending_path.exists()
    assert sorted(p.name for p in files.iterdir() if "yaml" in p.name) == ["c.yaml", "model.yaml", "shadow.yaml"]


def test_remote_models_for_the_shadow_alone(files: Path, hups: list[int]) -> None:
    """A model of contributions and a shadow file: allowed; Model/apply is refused (no file to
    replace, armed or not), a shadow is taken. Neither a model file nor a shadow file: a config error."""
    rm = remote(files, CONTRIBUTIONS, "{kind: xi_spindle, file: shadow.yaml}")
    assert rm.spec.model_file is None and rm.spec.model_sha256 is None
    assert rm.spec.shadow_file == files / "shadow.yaml"
    rm.arm(60)
    answer = rm.handle(NEW_SHADOW, "r1", "model")
    assert answer["result"] == "refused" and "the config's model is a set of contributions" in answer["reason"]
    assert rm.armed() and not hups
    assert rm.handle(NEW_SHADOW, "r2", "shadow")["result"] == "accepted"
    assert rm.armed()  # a shadow is not armed for: the arming is still there for a model
    with pytest.raises(BadInput, match=r"telemetry\.remote_models\.allow"):
        remote(files, CONTRIBUTIONS, INLINE)
    with pytest.raises(BadInput, match=r"telemetry\.remote_models\.allow"):
        remote(files, INLINE, None)


def test_a_shadow_applied_is_answered_by_the_reloaded_pipeline(files: Path, hups: list[int]) -> None:
    rm = remote(files, MODEL_FILE, "{kind: xi_spindle, file: shadow.yaml}")
    assert not rm.armed()
    accepted = rm.handle(NEW_SHADOW, "r1", "shadow")
    assert accepted["result"] == "accepted" and accepted["target"] == "shadow", accepted
    assert hups == [signal.SIGHUP]
    pending = json.loads(rm.spec.pending_path.read_text())
    assert pending["target"] == "shadow" and pending["file"] == str(files / "shadow.yaml")
    assert (files / "shadow.yaml").read_text() == NEW_SHADOW and (files / "model.yaml").read_text() == ORIGINAL
    # one at a time: a model (or shadow) sent while this one waits for its reload is refused
    assert "still being applied" in rm.handle(NEW_SHADOW, "r2", "shadow")["reason"]
    # the reload: a new service with the spec of the config read again answers
    after = remote(files, MODEL_FILE, "{kind: xi_spindle, file: shadow.yaml}")
    assert after.spec.shadow_sha256 == accepted["sha256"] and after.spec.model_sha256 == rm.spec.model_sha256
    assert after.started() == {"request": "r1", "result": "applied", "target": "shadow", "sha256": accepted["sha256"]}
    assert after.started() is None  # once


def test_a_shadow_the_reload_did_not_take_is_put_back(files: Path, hups: list[int]) -> None:
    rm = remote(files, MODEL_FILE, "{kind: xi_spindle, file: shadow.yaml}")
    assert rm.handle(NEW_SHADOW, "r1", "shadow")["result"] == "accepted"
    assert rm.observe({}) is None  # still waiting for the reload
    assert rm._pending is not None
    rm._pending["deadline"] = -math.inf  # RELOAD_WAIT_S gone by, the old pipeline still running
    late = rm.observe({})
    assert late is not None and late["result"] == "failed" and late["target"] == "shadow", late
    assert "previous shadow file back" in late["reason"]
    assert (files / "shadow.yaml").read_text() == OLD_SHADOW  # the right file back ...
    assert (files / "model.yaml").read_text() == ORIGINAL and not list(files.glob("model.yaml.*"))  # ... and only it
    assert [p.read_text() for p in files.glob("shadow.yaml.rejected-*")] == [NEW_SHADOW]
    assert not rm.spec.pending_path.exists()


def test_a_shadow_is_checked_against_the_shadow_section_not_the_clamp(files: Path, hups: list[int]) -> None:
    """What the model must pass and a shadow need not (the guard's clamp: it drives nothing), and
    what both must (the size limit, the pipeline building: its inputs signals a source gives)."""
    rm = remote(files, MODEL_FILE, "{kind: xi_spindle, file: shadow.yaml}")
    absurd = MODEL.format(length_mm=100000, fitted_at="x").replace("13.6e-6", "9.9e-4")
    assert remote_model.validate(rm.spec, files / "shadow.yaml", "model") is None  # a file as it is
    candidate = files / "absurd.yaml"
    candidate.write_text(absurd)
    why = remote_model.validate(rm.spec, candidate, "model")
    assert why is not None and "sit at the guard's clamp" in why
    assert remote_model.validate(rm.spec, candidate, "shadow") is None
    candidate.write_text(NEW_SHADOW.replace("inputs: [T_xi]", "inputs: [T_nowhere]"))
    why = remote_model.validate(rm.spec, candidate, "shadow")
    assert why is not None and "T_nowhere" in why, why
    # a shadow file the active model reads too (here, a contribution's): replacing it is refused
    same = remote(files, CONTRIBUTIONS, "{kind: xi_spindle, file: model.yaml}")
    candidate.write_text(NEW_SHADOW)
    why = remote_model.validate(same.spec, candidate, "shadow")
    assert why is not None and "model.yaml is one the active model reads" in why, why
    rm = remote(files, MODEL_FILE, "{kind: xi_spindle, file: shadow.yaml}")
    big = NEW_SHADOW + "#" * rm.spec.max_bytes
    answer = rm.handle(big, "r1", "shadow")
    assert answer["result"] == "refused" and "remote_models.max_bytes" in answer["reason"]
    assert not hups and (files / "shadow.yaml").read_text() == OLD_SHADOW


# --- a shadow sent again: each accepted one reloads the daemon and starts the shadow's score afresh -----

SHADOW_SECTION = "{kind: xi_spindle, file: shadow.yaml}"


def test_a_shadow_within_shadow_min_interval_s_of_the_last_is_refused(files: Path, hups: list[int]) -> None:
    """The interval holds across the reload (a new handler): the last accepted shadow is recorded beside
    the shadow file; the text the file holds already is refused (nothing to reload); 0 = no limit."""
    rm = remote(files, MODEL_FILE, SHADOW_SECTION)
    assert rm.spec.shadow_min_interval_s == 60.0
    same = rm.handle(OLD_SHADOW, "r0", "shadow")
    assert same["result"] == "refused" and "holds this text already" in same["reason"], same
    assert rm.handle(NEW_SHADOW, "r1", "shadow")["result"] == "accepted"
    record = json.loads((files / "shadow.yaml.remote.json").read_text())
    assert record["request"] == "r1" and record["sha256"] == hashlib.sha256(NEW_SHADOW.encode()).hexdigest()
    after = remote(files, MODEL_FILE, SHADOW_SECTION)  # the reloaded pipeline's handler
    assert after.started()["result"] == "applied"
    third = MODEL.format(length_mm=140.0, fitted_at="2026-11-21T10:00:00Z")
    answer = after.handle(third, "r2", "shadow")
    assert answer["result"] == "refused", answer
    assert "a shadow was accepted 0 s ago (request r1)" in answer["reason"]
    assert "remote_models.shadow_min_interval_s (60 s)" in answer["reason"]
    assert hups == [signal.SIGHUP] and (files / "shadow.yaml").read_text() == NEW_SHADOW
    assert not list(files.glob("shadow.yaml.rejected-*"))  # refused before anything was written
    # without a limit it is taken
    free = remote(files, MODEL_FILE, SHADOW_SECTION, "{allow: true, shadow_min_interval_s: 0}")
    assert free.handle(third, "r3", "shadow")["result"] == "accepted"


def test_backups_of_the_shadow_file_are_bounded_and_none_is_deleted(files: Path, hups: list[int]) -> None:
    """With MAX_SHADOW_BACKUPS backups beside the shadow file a shadow sent is refused: a backup is what a
    reload that fails puts back, so it is not written without one, and none is deleted to make room."""
    for k in range(remote_model.MAX_SHADOW_BACKUPS - 1):
        (files / f"shadow.yaml.2026010{k % 10}T00000{k}.000000Z.bak").write_text(f"backup {k}\n")
    mine = {p.name: p.read_text() for p in files.glob("shadow.yaml.*.bak")}
    rm = remote(files, MODEL_FILE, SHADOW_SECTION, "{allow: true, shadow_min_interval_s: 0}")
    assert rm.handle(NEW_SHADOW, "r1", "shadow")["result"] == "accepted"  # the last backup there is room for
    assert len(list(files.glob("shadow.yaml.*.bak"))) == remote_model.MAX_SHADOW_BACKUPS
    after = remote(files, MODEL_FILE, SHADOW_SECTION, "{allow: true, shadow_min_interval_s: 0}")
    after.started()
    answer = after.handle(OLD_SHADOW, "r2", "shadow")
    assert answer["result"] == "refused", answer
    assert f"{remote_model.MAX_SHADOW_BACKUPS} backups of shadow.yaml are kept beside it already" in answer["reason"]
    assert (files / "shadow.yaml").read_text() == NEW_SHADOW and len(hups) == 1
    assert len(list(files.glob("shadow.yaml.*.bak"))) == remote_model.MAX_SHADOW_BACKUPS
    assert all((files / name).read_text() == text for name, text in mine.items())  # none deleted


def probe(folder: Path, cfg: Path, error_um: float) -> None:
    r = compd("probe", "--axis", "z", "--error-um", f"{error_um:.4f}", "--config", str(cfg), cwd=folder)
    assert r.returncode == 0, r.stderr


def test_a_shadow_sent_again_starts_its_score_afresh_and_promote_refuses_it(tmp_path: Path) -> None:
    """A scored shadow, then the plant sends it again: the very text is refused (the score goes on); a
    changed one reloads the daemon, its score starts at no probe, and `compd promote` refuses it, saying
    which request sent it; a third within shadow_min_interval_s is refused."""
    first = MODEL.format(length_mm=80.0, fitted_at="2026-02-01T00:00:00Z")  # half the model's: half its prediction
    (tmp_path / "model.yaml").write_text(ORIGINAL)
    (tmp_path / "shadow.yaml").write_text(first)
    with Mosquitto(tmp_path / "broker") as broker:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(
            CONFIG.format(port=broker.port, shadow=SHADOW_FILE + "\nadapt: {apply: false}").replace(
                "speedup: 1}", "speedup: 50}"
            )
        )  # the spindle warms faster: the two models' predictions apart
        listener = Listener(broker.port)
        try:
            with daemon(cfg, tmp_path / "stderr.txt") as proc:
                listener.wait_for(lambda: listener.of("DBIRTH"), timeout_s=60)
                status_when(tmp_path, lambda s: abs(s["axes"]["z"].get("prediction_um") or 0.0) > 2.0)
                for k in range(3):  # probes that measure what the shadow predicts just then
                    probe(tmp_path, cfg, status_of_file(tmp_path)["axes"]["z"]["shadow_um"])
                    status_when(tmp_path, lambda s, k=k: s["shadow"]["axes"]["z"]["probes"] > k)
                scored = compd("promote", str(cfg), "--dry-run", cwd=tmp_path)
                assert scored.returncode == 0, scored.stderr  # 3 probes on this shadow: it could be promoted
                # the same text again: refused, nothing reloaded, the score goes on
                same = answered(listener, send(listener, "Model/shadow", first), "refused")
                assert "holds this text already" in same["reason"], same
                assert status_of_file(tmp_path)["shadow"]["axes"]["z"]["probes"] == 3
                # another text: accepted, the daemon reloads, the score starts afresh
                r_new = send(listener, "Model/shadow", NEW_SHADOW)
                answered(listener, r_new, "applied")
                new_sha = hashlib.sha256(NEW_SHADOW.encode()).hexdigest()
                status = status_when(
                    tmp_path, lambda s: (s.get("shadow") or {}).get("model", {}).get("sha256") == new_sha
                )
                assert status["shadow"]["axes"]["z"]["probes"] == 0
                refused = compd("promote", str(cfg), cwd=tmp_path)
                # a third within the interval: refused
                third = MODEL.format(length_mm=140.0, fitted_at="2026-11-21T10:00:00Z")
                limited = answered(listener, send(listener, "Node Control/Shadow", third), "refused")
        finally:
            listener.stop()
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()
    assert refused.returncode == 2 and "too few probes (z 0; at least 3 per axis" in refused.stderr, refused.stderr
    assert (
        f"compd promote: the shadow came from: the plant (Model/shadow, request {r_new}, accepted " in refused.stdout
    ), refused.stdout
    assert "remote_models.shadow_min_interval_s (60 s)" in limited["reason"], limited
    assert (tmp_path / "shadow.yaml").read_text() == NEW_SHADOW
    assert "shadow: {kind: xi_spindle, file: shadow.yaml}" in cfg.read_text()  # not promoted


def status_of_file(folder: Path) -> dict[str, Any]:
    return json.loads((folder / "status.json").read_text())
