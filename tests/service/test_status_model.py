"""`compd status` reads back what is running: model file, kind, fit date, coefficients, T0, version."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from compd import version
from compd.cli import main
from compd.commissioning.fitting import load_model
from compd.config import load_config
from compd.daemon.app import App
from compd.log import write_log
from compd.service.status import render, snapshot, write_atomic


def _log(path, n=200):
    rng = np.random.default_rng(0)
    t = np.arange(n) * 30.0
    T = 20 + np.outer(1 - np.exp(-t / 3000), [3.0, 2.0]) + rng.normal(0, 0.03, (n, 2))
    E = (T - T[0]) @ np.array([[2.0, 1.5], [1.0, -1.0]]) + rng.normal(0, 0.2, (n, 2))
    write_log(path, ["t_s", "T1", "T2", "err_x1_um", "err_x2_um"], np.column_stack([t, T, E]))


def _fitted(tmp_path):
    _log(tmp_path / "log.csv")
    model = tmp_path / "m.yaml"
    assert main(["fit", "--kind", "mlr", "--log", str(tmp_path / "log.csv"), "--out", str(model)]) == 0
    return model


def _config(tmp_path, model, loop="{clock: sim, period_s: 1.0}", extra=""):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"""
loop: {loop}
{extra}
sources: [{{kind: replay, name: log, path: log.csv}}]
model: {{kind: mlr, file: {model.name}}}
guard: {{stale_after_s: 60}}
sink: {{kind: pci1756}}
""",
        encoding="utf-8",
    )
    return cfg


def _snap_mid_run(cfg):
    app = App(load_config(cfg))
    taken: dict = {}

    def take(loop, now):  # from inside the cycle, so nothing moves under us
        if loop.stats.cycles == 300:
            taken["snap"] = snapshot(loop, state="running", observe=False)
            taken["x0"] = [float(v) for v in loop.model.x0]

    app.loop.observers.append(take)
    app.run()
    return taken


def test_fit_writes_the_fit_date_and_compd_version(tmp_path):
    doc = yaml.safe_load(_fitted(tmp_path).read_text())
    fitted = doc["fit"]["fitted_at"]
    assert fitted.endswith("Z") and time.strptime(fitted, "%Y-%m-%dT%H:%M:%SZ")
    assert doc["fit"]["compd_version"] == version()


def test_status_shows_the_model_file_kind_fit_date_coefficients_t0_and_version(tmp_path, capsys):
    model = _fitted(tmp_path)
    taken = _snap_mid_run(_config(tmp_path, model))
    snap = taken["snap"]
    m = snap["model"]
    assert snap["version"] == version()
    assert m["file"] == str(model.resolve()) and m["kind"] == "mlr"
    fitted_at = yaml.safe_load(model.read_text())["fit"]["fitted_at"]
    assert m["fit"]["fitted_at"] == fitted_at and m["fit"]["rows"] == 200
    coef = load_model(model).params.coef_um_per_k
    assert m["coefficients"]["coef_um_per_k"]["x2"] == [float(f"{row[1]:.4g}") for row in coef]
    assert m["state"]["t0_c"] == taken["x0"]

    status = tmp_path / "status.json"
    write_atomic(status, {**snap, "status_period_s": 1.0, "written_unix_s": time.time()})
    assert main(["status", "--status", str(status)]) == 0
    out = capsys.readouterr().out
    assert f"compd {version()}" in out
    assert f"file: {model.resolve()}; fitted {fitted_at} on log.csv (200 rows)" in out
    x1 = next(ln for ln in out.splitlines() if ln.strip().startswith("axis x1:"))
    assert "mlr" in x1 and "fit RMSE" in x1 and "coef_um_per_k [" in x1 and "intercept_um" in x1
    t0 = next(ln for ln in out.splitlines() if "T0 (latched at start)" in ln)
    assert f"T1 {taken['x0'][0]:g} C" in t0 and "T2 " in t0


def test_an_older_model_file_without_a_fit_date_loads_and_says_so(tmp_path):
    model = _fitted(tmp_path)
    doc = yaml.safe_load(model.read_text())
    del doc["fit"]["fitted_at"], doc["fit"]["compd_version"]
    model.write_text(yaml.safe_dump(doc), encoding="utf-8")
    snap = _snap_mid_run(_config(tmp_path, model))["snap"]
    text = render(snap, True, "running")
    assert "fitted unknown (no fit date in the file)" in text
    assert f"file: {model.resolve()}" in text


def test_inline_params_say_so_and_a_model_without_t0_before_start(tmp_path):
    from compd.models import MODELS

    cls = MODELS.get("xi_spindle")
    m = cls(cls.Params.model_validate({"alpha_per_k": 13.6e-6, "length_mm": 165.0}), ["T_xi"], ["z"])
    text = render({"model": m.get_status(), "axes": {}, "signals": {}}, True, "running")
    assert "(inline params in the config)" in text
    assert "alpha_per_k 1.36e-05" in text and "length_mm 165" in text
    assert "T0 (latched at start): not yet" in text


def test_a_running_daemon_s_status_shows_them(tmp_path):
    """`compd run` as a real process (the log replayed at 20x), `compd status --config` beside it."""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    model = _fitted(tmp_path)
    cfg = _config(
        tmp_path,
        model,
        loop="{clock: sim, period_s: 1.0, speedup: 20}",
        extra="status: {path: status.json, period_s: 0.1}",
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "compd", "run", cfg.name],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60.0  # an upper bound, never a sleep
        snap: dict = {}
        while not (snap.get("state") == "running" and (snap.get("model") or {}).get("state", {}).get("t0_c")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
            try:
                snap = json.loads((tmp_path / "status.json").read_text(encoding="utf-8"))
            except (OSError, ValueError):
                snap = {}
        out = subprocess.run(
            [sys.executable, "-m", "compd", "status", "--config", cfg.name],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    assert out.returncode == 0, out.stderr
    text = out.stdout
    fitted_at = yaml.safe_load(model.read_text())["fit"]["fitted_at"]
    assert f"compd running — pid {proc.pid}" in text and f"compd {version()}" in text
    assert f"file: {model.resolve()}; fitted {fitted_at}" in text
    for axis in ("x1", "x2"):
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(f"axis {axis}:"))
        assert "mlr, fit RMSE" in line and "coef_um_per_k [" in line
    assert "T0 (latched at start): T1 " in text
