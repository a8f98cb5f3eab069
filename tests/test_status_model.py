"""`compd status` reads back what is running: model file, kind, fit date, coefficients, T0, version."""

from __future__ import annotations

import time

import numpy as np
import yaml

from compd import version
from compd.app import App
from compd.cli import main
from compd.config import load_config
from compd.fitting import load_model
from compd.log import write_log
from compd.status import render, snapshot, write_atomic


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


def _config(tmp_path, model):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"""
loop: {{clock: sim, period_s: 1.0}}
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
