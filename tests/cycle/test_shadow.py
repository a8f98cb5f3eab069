"""The shadow model: run beside the active one, driving nothing, scored on the same probes, promoted by a reload."""

from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from compd.cli import main
from compd.commissioning.promote import promoted_text
from compd.commissioning.replay import replay_config
from compd.config import load_config
from compd.core.errors import BadInput
from compd.log import read_log
from tests.cycle.test_contributions import plant  # noqa: F401  (the fixture: two fitted contributions, an unseen day)
from tests.service.test_probe import ENV, compd, status_of, until
from tests.service_helpers import sim_config

# the shadow: the same spindle, another length, fitted over 20…45 °C (34 µm at most: inside the guard's 63 µm clamp)
SHADOW = """kind: xi_spindle
inputs: [T_xi]
outputs: [z]
params: {{alpha_per_k: 13.6e-6, length_mm: {length_mm}}}
fit: {{fitted_at: "2026-11-20T10:00:00Z", log: day1.csv, input_range: {{T_xi: [20.0, 45.0]}}}}
"""
EXTRA = """
shadow: {kind: xi_spindle, file: shadow.yaml}
status: {path: status.json, period_s: 0.1}
log: {path: log.csv, period_s: 10}
adapt: {apply: false}
"""


def test_a_replay_scores_a_shadow_on_the_logged_error(plant: Path) -> None:  # noqa: F811
    cfg = plant / "shadow.yaml"
    cfg.write_text("""\
loop: {clock: sim, period_s: 60.0}
sources:
  - {kind: replay, name: log, path: unseen.csv}
model: {kind: xi_spindle, file: spindle.yaml}
shadow:
  contributions:
    - {name: spindle, kind: xi_spindle, file: spindle.yaml}
    - {name: column, kind: mlr, file: column.yaml}
guard: {max_slew_um_per_s: 0.05, stale_after_s: 200.0}
sink: {kind: pci1756}
""")
    alone = replay_config(cfg, plant / "unseen.csv")
    sc = alone.report["shadow"]["axes"]["z"]["error"]
    assert sc["rows"] == len(alone.t_s)
    assert sc["shadow_rms_um"] < 0.2 * sc["active_rms_um"]  # the column the active model lacks
    # the shadow drove nothing: the same replay without it commands the same words
    cfg.write_text(cfg.read_text().split("shadow:")[0] + "guard:" + cfg.read_text().split("guard:")[1])
    np.testing.assert_array_equal(replay_config(cfg, plant / "unseen.csv").word, alone.word)


def test_promoted_text_keeps_the_old_model_as_comments() -> None:
    text = (
        "loop: {period_s: 1.0}\n# the model\nmodel: {kind: mlr, file: a.yaml}\n"
        "shadow:\n  kind: mlr\n  file: b.yaml\nsink: {kind: pci1756}\n"
    )
    out = promoted_text(text, "c.yaml", "STAMP")
    assert out == (
        "loop: {period_s: 1.0}\n# the model\n# model before `compd promote` of STAMP (the shadow became the"
        " model):\n# model: {kind: mlr, file: a.yaml}\nmodel:\n  kind: mlr\n  file: b.yaml\n"
        "sink: {kind: pci1756}\n"
    )
    with pytest.raises(BadInput, match="no shadow"):
        promoted_text("model: {kind: mlr}\n", "c.yaml", "S")


@pytest.fixture
def daemon(tmp_path: Path):
    """A daemon on the simulated spindle (20× real time) with a shadow, stopped with SIGTERM at the end.

    The shadow is a third shorter: it predicts a third less.
    """
    cfg = sim_config(tmp_path, EXTRA, duration_s=1e6, speedup=20)
    (tmp_path / "shadow.yaml").write_text(SHADOW.format(length_mm=100.0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "compd", "run", cfg.name],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        until(
            lambda: (
                ((status_of(tmp_path).get("axes") or {}).get("z", {}).get("shadow_um") or 0.0) > 1.0
                or proc.poll() is not None
            ),
            "the daemon and its shadow, the spindle warming",
        )
        assert proc.poll() is None, proc.communicate()
        yield proc, cfg
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


def _probe_at(folder: Path, which: str, n: int) -> None:
    """`n` probes each measuring what the `which` model ("shadow" or "active") predicts just then."""
    for k in range(n):
        z = status_of(folder)["axes"]["z"]
        value = z["shadow_um"] if which == "shadow" else z["prediction_um"]
        r = compd("probe", "--axis", "z", "--error-um", f"{value:.4f}", "--config", "sim.yaml", cwd=folder)
        assert r.returncode == 0, r.stderr
        until(
            lambda k=k: ((status_of(folder).get("shadow") or {}).get("axes", {}).get("z", {}).get("probes") or 0) > k,
            "the probe scored",
        )


def test_a_shadow_scored_on_probes_is_promoted_through_a_reload(daemon, tmp_path: Path) -> None:
    proc, cfg = daemon
    status = status_of(tmp_path)
    assert status["shadow"]["model"]["kind"] == "xi_spindle"
    z = status["axes"]["z"]
    assert z["shadow_um"] != z["prediction_um"]  # another length: another prediction
    # the score is of this very shadow: the file's sha256
    sha = hashlib.sha256((tmp_path / "shadow.yaml").read_bytes()).hexdigest()
    assert status["shadow"]["model"]["sha256"] == sha
    # probes that measure what the active model predicts: the shadow is scored worse and not promoted
    _probe_at(tmp_path, "active", 3)
    sc = status_of(tmp_path)["shadow"]["axes"]["z"]
    assert sc["shadow_rms_um"] > sc["active_rms_um"]
    before = cfg.read_text()
    r = compd("promote", cfg.name, cwd=tmp_path)
    assert r.returncode == 2 and "worse than the active model" in r.stderr and cfg.read_text() == before
    # more probes that measure what the shadow predicts: now it is the better one, and it is promoted
    _probe_at(tmp_path, "shadow", 6)
    sc = status_of(tmp_path)["shadow"]["axes"]["z"]
    assert sc["shadow_rms_um"] < sc["active_rms_um"] and sc["better"] == "shadow"
    until(lambda: _logged_shadow(tmp_path / "log.csv"), "the shadow's column in the data log")
    r = compd("promote", cfg.name, cwd=tmp_path, timeout=120)
    assert r.returncode == 0, r.stderr
    # what it is about to make the model, said first: kind, file, sha256, where it came from, its predictions now
    said = r.stdout.splitlines()
    assert said[0] == (
        f"compd promote: about to make the shadow the model: xi_spindle, file {tmp_path / 'shadow.yaml'}, sha256 {sha}"
    )
    assert said[1] == "compd promote: the shadow came from: fitted 2026-11-20T10:00:00Z on day1.csv"
    assert said[2].startswith(f"compd promote: now (daemon pid {proc.pid}): z: the shadow predicts ")
    assert ", the active model " in said[2]
    assert said[3].startswith("compd promote: its score on the probes: z: 9 probes, shadow RMS ")
    assert "reloaded and runs the promoted model" in said[-1]
    new = load_config(cfg)
    assert new.shadow is None and new.model.params.length_mm == 100.0
    assert "# model: {kind: xi_spindle" in cfg.read_text()  # the old model kept, as comments
    backups = list(tmp_path.glob("sim.yaml.*.bak"))
    assert len(backups) == 1 and backups[0].read_text() == before
    status = status_of(tmp_path)
    assert "shadow" not in status and status["model"]["coefficients"]["length_mm"] == 100.0
    assert status["axes"]["z"]["state"] == "normal"
    assert proc.poll() is None


def _logged_shadow(path: Path) -> bool:
    """The data log has rows with the shadow's prediction."""
    try:
        log = read_log(path, allow_nan=True)
    except Exception:  # noqa: BLE001  (not there yet, or a row being written)
        return False
    return "shadow_z_um" in log.columns and bool(np.isfinite(log.col("shadow_z_um")).any())


def test_promote_without_a_shadow_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = sim_config(tmp_path)
    capsys.readouterr()
    assert main(["promote", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no shadow" in err and "sim.yaml" in err


def test_a_shadow_on_an_axis_the_model_lacks_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = sim_config(
        tmp_path,
        "shadow: {kind: xi_spindle, inputs: [T_xi], outputs: [x], params: {alpha_per_k: 13.6e-6, length_mm: 150.0}}",
    )
    capsys.readouterr()
    assert main(["check-config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "shadow.outputs[0]" in err and "'x' is not an axis the sink drives (z: the outputs of model)" in err
