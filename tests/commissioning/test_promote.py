"""`compd promote` checks the shadow as a model sent to be applied is, and puts the config back on a failed reload.

The check is the clamp over its fitted range; a shadow without enough probes scored on it is refused. The config is
put back when the reload does not take it.
"""

from __future__ import annotations

import hashlib
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from compd.cli import main
from compd.config import load_config
from compd.plant.remote_model import clamp_check
from tests.cycle.test_shadow import EXTRA, SHADOW, _probe_at, daemon  # noqa: F401  (the fixture: a daemon with a shadow)
from tests.plant.test_remote_model import ABSURD, SANE
from tests.service.test_probe import ENV, compd, status_of, until
from tests.service_helpers import sim_config

CLAMP_40 = "guard: {max_abs_um: 40}\n"


def _config(tmp_path: Path, shadow: str, extra: str = "") -> Path:
    """The sim spindle's config (no daemon) with `shadow` in shadow.yaml as its shadow."""
    (tmp_path / "shadow.yaml").write_text(shadow)
    return sim_config(tmp_path, "shadow: {kind: xi_spindle, file: shadow.yaml}\n" + extra)


def test_an_absurd_shadow_is_refused_with_the_figure_even_forced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every parameter within its bounds, 455 400 µm over its own fit range: check-config takes it
    (a shadow drives nothing), promote does not, --force or not, and says why with the figure."""
    cfg = _config(tmp_path, ABSURD, CLAMP_40)
    before = cfg.read_bytes()
    assert main(["check-config", str(cfg)]) == 0
    capsys.readouterr()
    assert main(["promote", str(cfg), "--force"]) == 2
    out, err = capsys.readouterr()
    assert len(err.strip().splitlines()) == 1, err
    line = cfg.read_text().splitlines().index("shadow: {kind: xi_spindle, file: shadow.yaml}") + 1
    assert err.startswith(
        f"compd: {cfg}:{line}: shadow: the shadow cannot be made the model: axis z would sit at the"
        " guard's clamp: over its input range (fit.input_range) the model predicts a |correction| of"
        " 455400.0 µm (at T_xi 24.6 from 20 at start), beyond guard.max_abs_um 40 µm"
    ), err
    # what it was about to make the model was said first: kind, file, sha256, where it came from
    sha = hashlib.sha256(ABSURD.encode()).hexdigest()
    assert out.splitlines()[:3] == [
        f"compd promote: about to make the shadow the model: xi_spindle, file {tmp_path / 'shadow.yaml'}, sha256 {sha}",
        "compd promote: the shadow came from: fitted 2026-11-20T10:00:00Z",
        "compd promote: no daemon runs this config: no prediction now, no score on the probes",
    ]
    assert cfg.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["shadow.yaml", "sim.yaml"]


def test_an_unscored_shadow_is_refused_unless_forced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """No daemon runs the config: no score, refused; --force promotes it, unverified (no daemon loaded it)."""
    cfg = _config(tmp_path, SANE)
    before = cfg.read_bytes()
    capsys.readouterr()
    assert main(["promote", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "not promoted: no daemon runs this config, so the shadow has no score on the probes (give --force" in err
    assert cfg.read_bytes() == before
    assert main(["promote", str(cfg), "--dry-run"]) == 2 and cfg.read_bytes() == before
    capsys.readouterr()
    assert main(["promote", str(cfg), "--force"]) == 0
    out = capsys.readouterr().out
    assert "no daemon runs this config: the file is promoted unverified (no daemon has loaded it)" in out
    new = load_config(cfg)
    assert new.shadow is None and new.model.file == str(tmp_path / "shadow.yaml")
    assert [p.read_bytes() for p in tmp_path.glob("sim.yaml.*.bak")] == [before]


def test_a_sum_of_contributions_is_checked_contribution_by_contribution(tmp_path: Path) -> None:
    """A shadow of contributions: each over its own file's fit range, against its own clamp."""
    (tmp_path / "sane.yaml").write_text(SANE)  # 20.4 µm at most
    (tmp_path / "absurd.yaml").write_text(ABSURD)
    cfg = sim_config(
        tmp_path,
        CLAMP_40
        + """shadow:
  contributions:
    - {name: spindle, kind: xi_spindle, file: sane.yaml}
    - {name: other, kind: xi_spindle, file: absurd.yaml, max_abs_um: 30}
""",
    )
    why = clamp_check(load_config(cfg).shadow, load_config(cfg).top.guard)
    assert why == (
        "contribution 'other': axis z would sit at its clamp: over its input range (fit.input_range) the"
        " model predicts a |correction| of 455400.0 µm (at T_xi 24.6 from 20 at start), beyond"
        " contribution other's max_abs_um 30 µm"
    )
    cfg.write_text(cfg.read_text().replace("file: absurd.yaml, max_abs_um: 30", "file: sane.yaml, max_abs_um: 30"))
    assert clamp_check(load_config(cfg).shadow, load_config(cfg).top.guard) is None
    cfg.write_text(cfg.read_text().replace("max_abs_um: 30", "max_abs_um: 20"))  # 20.4 µm: beyond its own clamp
    why = clamp_check(load_config(cfg).shadow, load_config(cfg).top.guard)
    assert why is not None and "20.4 µm" in why and "contribution other's max_abs_um 20 µm" in why


def test_too_few_probes_or_a_score_of_another_shadow_is_no_score(daemon, tmp_path: Path) -> None:  # noqa: F811
    proc, cfg = daemon
    before = cfg.read_bytes()
    r = compd("promote", cfg.name, cwd=tmp_path)
    assert r.returncode == 2 and "too few probes (z 0; at least 3 per axis" in r.stderr, r.stderr
    _probe_at(tmp_path, "shadow", 2)
    r = compd("promote", cfg.name, cwd=tmp_path)
    assert r.returncode == 2 and "too few probes (z 2; at least 3 per axis" in r.stderr, r.stderr
    assert "its score on the probes: z: 2 probes, shadow RMS" in r.stdout
    # a dry run with --min-probes 2 passes: the new config on stdout, what it says on stderr, nothing changed
    r = compd("promote", cfg.name, "--min-probes", "2", "--dry-run", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "# model before `compd promote`" in r.stdout and "model: {kind: xi_spindle, file: shadow.yaml}" in r.stdout
    assert "compd promote: about to make the shadow the model: xi_spindle" in r.stderr
    assert cfg.read_bytes() == before and not list(tmp_path.glob("sim.yaml.*"))
    _probe_at(tmp_path, "shadow", 1)
    # the shadow file edited since the daemon read it: its score is of another shadow
    (tmp_path / "shadow.yaml").write_text(SHADOW.format(length_mm=101.0))
    r = compd("promote", cfg.name, cwd=tmp_path)
    assert r.returncode == 2 and "the running daemon's score is of another shadow" in r.stderr, r.stderr
    assert cfg.read_bytes() == before and not list(tmp_path.glob("sim.yaml.*"))
    # --force: promoted all the same, through the reload
    r = compd("promote", cfg.name, "--force", cwd=tmp_path, timeout=120)
    assert r.returncode == 0 and "reloaded and runs the promoted model" in r.stdout, r.stderr
    assert status_of(tmp_path)["model"]["coefficients"]["length_mm"] == 101.0
    assert proc.poll() is None


@contextmanager
def _daemon_with(tmp_path: Path, extra: str) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """The shadow test's daemon (the sim spindle at 60×: warm sooner) with `extra` in its config."""
    cfg = sim_config(tmp_path, EXTRA + extra, duration_s=1e6, speedup=60)
    (tmp_path / "shadow.yaml").write_text(SHADOW.format(length_mm=100.0))
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "compd", "run", cfg.name],
            cwd=tmp_path,
            env=ENV,
            stdout=subprocess.DEVNULL,
            stderr=err,
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
        assert proc.poll() is None, (tmp_path / "stderr.txt").read_text()
        yield proc, cfg
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_a_promote_the_reload_refuses_leaves_the_config_as_it_was(tmp_path: Path) -> None:
    """The promoted config checks but cannot open (its metrics port, edited since the daemon read it,
    is someone else's): the daemon keeps its old pipeline, and the config is put back byte for byte,
    so the next start runs what the daemon ran; the promoted text is kept beside it."""
    with socket.socket() as mine, socket.socket() as taken:
        mine.bind(("127.0.0.1", 0))
        port = mine.getsockname()[1]
        mine.close()
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with _daemon_with(tmp_path, f"metrics: {{enabled: true, port: {port}}}\n") as (proc, cfg):
            _probe_at(tmp_path, "shadow", 3)
            cfg.write_text(cfg.read_text().replace(f"port: {port}", f"port: {taken.getsockname()[1]}"))
            before = cfg.read_bytes()
            r = compd("promote", cfg.name, "--wait-s", "5", cwd=tmp_path, timeout=120)
            assert r.returncode == 1, (r.stdout, r.stderr)
            assert "did not show the promoted model within 5 s" in r.stderr and "is back as it was" in r.stderr
            assert cfg.read_bytes() == before  # byte for byte
            kept = list(tmp_path.glob("sim.yaml.promoted-rejected-*"))
            assert len(kept) == 1 and "# model before `compd promote`" in kept[0].read_text()
            assert [p.read_bytes() for p in tmp_path.glob("sim.yaml.*.bak")] == [before]
            # the daemon runs on with the old pipeline and its shadow: it refused the promoted config, and
            # then the one put back (asked to reload it: the port is still taken)
            until(lambda: (tmp_path / "stderr.txt").read_text().count("reload failed") >= 2, "the second reload")
            status = status_of(tmp_path)
            assert proc.poll() is None and status["shadow"]["model"]["kind"] == "xi_spindle"
            assert status["model"]["coefficients"]["length_mm"] == 165.0
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()
    assert "compd: reloaded" not in (tmp_path / "stderr.txt").read_text()
