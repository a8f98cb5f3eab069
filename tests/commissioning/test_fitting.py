"""`compd fit`, `compd predict`, `compd xi` end to end; bad input exits 2; a fitted model runs in the loop."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.commissioning.fitting import load_model
from compd.config import load_config
from compd.log import is_temperature_column, read_log, write_log


def _write_log(path, n=300, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 30.0
    T = 20 + np.outer(1 - np.exp(-t / 3000), [3.0, 2.0, 1.0]) + rng.normal(0, 0.03, (n, 3))
    E = (T - T[0]) @ np.array([[2.0, 1.5], [1.0, -1.0], [0.5, 3.0]]) + rng.normal(0, 0.2, (n, 2))
    speed = np.where((t // 1800) % 2 == 0, 2000.0, 0.0)
    cols = ["t_s", "T1", "T2", "T3", "speed_rpm", "err_x1_um", "err_x2_um"]
    write_log(path, cols, np.column_stack([t, T, speed, E]))
    return cols


def test_temperature_columns_exclude_compd_outputs():
    for name in ("pred_x_um", "corr_x_um", "applied_x_um", "word", "t_s", "err_x_um", "speed_rpm"):
        assert not is_temperature_column(name)
    assert is_temperature_column("T_spindle")


@pytest.mark.parametrize("kind", ["lvr", "mlr"])
def test_fit_writes_model_report_plot_and_predicts(tmp_path, kind, capsys):
    log = tmp_path / "log.csv"
    _write_log(log)
    out, rep, png, pred = (tmp_path / f for f in ("m.yaml", "r.json", "p.png", "pred.csv"))
    rc = main(["fit", "--kind", kind, "--log", str(log), "--out", str(out), "--report", str(rep), "--plot", str(png)])
    assert rc == 0
    doc = yaml.safe_load(out.read_text())
    assert doc["kind"] == kind and doc["inputs"] == ["T1", "T2", "T3"] and doc["outputs"] == ["x1", "x2"]
    assert set(doc["fit"]["rmse_um"]) == {"x1", "x2"} and doc["fit"]["rows"] == 300
    report = json.loads(rep.read_text())
    assert report["rows"] == 300 and report["axes"]["x1"]["rmse_um"] < 0.5
    if kind == "lvr":
        assert len(doc["fit"]["q2"]) == 3 and "influence" in report["details"]
        # which selection chose the components, with its PRESS per component and its blocks
        fit = doc["fit"]
        assert fit["selection"] == "blocked" and len(fit["press"]) == 3 and fit["n_components"] >= 1
        assert fit["cv"]["split"] == "equal" and len(fit["cv"]["blocks"]) == 5
        assert fit["cv"] == report["details"]["cv"] and fit["press"] == report["details"]["press"]
    assert png.stat().st_size > 10_000
    assert main(["predict", str(out), "--log", str(log), "--out", str(pred)]) == 0
    p = read_log(pred)
    assert p.columns == ["t_s", "pred_x1_um", "pred_x2_um"] and len(p) == 300
    model = load_model(out)
    np.testing.assert_allclose(
        p.col("pred_x1_um"), model.predict(read_log(log).matrix(model.inputs), read_log(log).t_s)[:, 0], atol=1e-4
    )


def test_fit_ar1_reports_ljung_box(tmp_path):
    log = tmp_path / "log.csv"
    _write_log(log)
    rep = tmp_path / "r.json"
    rc = main(
        [
            "fit",
            "--kind",
            "ar1",
            "--log",
            str(log),
            "--out",
            str(tmp_path / "a.yaml"),
            "--target",
            "err_x1_um",
            "--inputs",
            "T1",
            "--ambient",
            "T3",
            "--report",
            str(rep),
        ]
    )
    assert rc == 0
    r = json.loads(rep.read_text())
    assert {"q", "p_value", "lags"} <= set(r["details"]["ljung_box"])
    assert r["inputs"] == ["speed_rpm", "T1", "T3"]
    # which C2 the model uses at speeds the log has no error at: in the report and the model file
    assert r["details"]["c2_at_unseen_speeds"]["method"] == "linear"
    model = yaml.safe_load((tmp_path / "a.yaml").read_text())
    assert model["fit"]["c2_at_unseen_speeds"]["method"] == "linear"
    assert model["params"]["recursion_start"] == "zero"


def test_fit_all_prints_comparison(tmp_path, capsys):
    log = tmp_path / "log.csv"
    _write_log(log)
    rc = main(
        [
            "fit",
            "--kind",
            "all",
            "--log",
            str(log),
            "--out",
            str(tmp_path / "models"),
            "--report",
            str(tmp_path / "all.json"),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    for label in ("lvr", "mlr", "ar1_x1", "ar1_x2"):
        assert label in text
    assert "skipped" in text  # feed_axis: no position column
    assert (tmp_path / "models" / "lvr.yaml").exists() and (tmp_path / "models" / "ar1_x2.yaml").exists()


def _bad(tmp_path, capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("compd: ") and err.count("\n") == 1
    return err


def test_bad_inputs_exit_2(tmp_path, capsys):
    log = tmp_path / "log.csv"
    cols = _write_log(log)
    out = str(tmp_path / "m.yaml")
    err = _bad(tmp_path, capsys, ["fit", "--kind", "mlr", "--log", str(log), "--out", out, "--inputs", "T9"])
    assert "T9" in err
    short = tmp_path / "short.csv"
    write_log(short, cols, read_log(log).data[:4])
    err = _bad(
        tmp_path, capsys, ["fit", "--kind", "lvr", "--log", str(short), "--out", out, "--option", "n_components=3"]
    )
    assert "too few" in err
    const = tmp_path / "const.csv"
    data = read_log(log).data.copy()
    data[:, 2] = 21.0
    write_log(const, cols, data)
    err = _bad(tmp_path, capsys, ["fit", "--kind", "lvr", "--log", str(const), "--out", out])
    assert "T2" in err and "constant" in err
    nan = tmp_path / "nan.csv"
    data = read_log(log).data.copy()
    data[10, 1] = np.nan
    write_log(nan, cols, data)
    err = _bad(tmp_path, capsys, ["fit", "--kind", "mlr", "--log", str(nan), "--out", out])
    assert "nan.csv:12" in err and "T1" in err
    err = _bad(tmp_path, capsys, ["fit", "--kind", "lvr", "--log", str(log), "--out", out, "--option", "bogus=1"])
    assert "bogus" in err
    err = _bad(
        tmp_path, capsys, ["fit", "--kind", "lvr", "--log", str(log), "--out", out, "--option", "selection=kfold"]
    )
    assert "--option selection: Input should be 'blocked' or 'loo' (got 'kfold')" in err
    err = _bad(tmp_path, capsys, ["fit", "--kind", "lvr", "--log", str(log), "--out", out, "--option", "cv_blocks=1"])
    assert "--option cv_blocks" in err and "greater than or equal to 2" in err


def test_lvr_library_span_too_long_exits_2(tmp_path, capsys):
    # 300 rows, 3 inputs: the paper's LOO Q² selection tries 3 components, which need 6 library rows;
    # eq. 11 keeps s − P* rows, so a span of 294 is the longest accepted
    log = tmp_path / "log.csv"
    _write_log(log)
    out = tmp_path / "m.yaml"
    rep = tmp_path / "r.json"
    argv = [
        "fit",
        "--kind",
        "lvr",
        "--log",
        str(log),
        "--out",
        str(out),
        "--report",
        str(rep),
        "--option",
        "selection=loo",
    ]
    assert main([*argv, "--option", "library_span=294"]) == 0
    assert json.loads(rep.read_text())["details"]["fit_rows"] == 6
    out.unlink()
    capsys.readouterr()  # the accepted fit's output
    err = _bad(tmp_path, capsys, [*argv, "--option", "library_span=295"])
    assert "log.csv: --option library_span: span 295 keeps 5 of the log's 300 rows" in err
    assert "at most 294" in err and not out.exists()


def test_xi_command(tmp_path, capsys):
    prof = tmp_path / "p.csv"
    x = np.linspace(0, 165, 12)
    prof.write_text("x_mm,T_c\n" + "".join(f"{a},{30 - 8 * a / 165}\n" for a in x))
    assert main(["xi", "--profile", str(prof)]) == 0
    assert capsys.readouterr().out.startswith("xi_mm 82.50")


def test_fitted_model_runs_in_loop_from_replay(tmp_path, capsys):
    log = tmp_path / "log.csv"
    _write_log(log)
    assert main(["fit", "--kind", "lvr", "--log", str(log), "--out", str(tmp_path / "lvr.yaml")]) == 0
    cfg = tmp_path / "run.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 10.0}\n"
        "sources:\n  - {kind: replay, name: log, path: log.csv}\n"
        "model: {kind: lvr, file: lvr.yaml}\n"
        "guard: {max_slew_um_per_s: 50.0, stale_after_s: 100.0}\n"
        "sink: {kind: pci1756, device: emulated}\n"
        "console: {summary: false}\n"
    )
    load_config(cfg)
    js = tmp_path / "run.json"
    assert main(["run", str(cfg), "--json", str(js)]) == 0
    result = json.loads(js.read_text())
    comp = result["compensation"]
    assert set(comp) == {"x1", "x2"}
    assert not result["faults"], result["faults"]
    for axis in comp.values():
        assert axis["reduction_pct"] > 50.0, comp


def test_a_fit_records_its_input_range_and_a_fitted_model_passes_the_remote_clamp_check(tmp_path):
    """`fit.input_range` is each input's finite readings in the fit's log; the remote-model check
    (compd.plant.remote_model.clamp_check) evaluates the model over it: a model fitted on the log
    stays inside a clamp its errors fit in, and is refused under one they do not."""
    from compd.config import load_model_file, resolve_model
    from compd.core.config import GuardConfig
    from compd.plant.remote_model import clamp_check

    log = tmp_path / "log.csv"
    _write_log(log)
    out = tmp_path / "m.yaml"
    assert main(["fit", "--kind", "mlr", "--log", str(log), "--out", str(out)]) == 0
    doc = yaml.safe_load(out.read_text())
    data = read_log(log)
    assert doc["fit"]["input_range"] == {
        n: [pytest.approx(data.col(n).min()), pytest.approx(data.col(n).max())] for n in ("T1", "T2", "T3")
    }
    fdoc, _ = load_model_file(out)
    spec = resolve_model({"kind": "mlr", "file": str(out)}, fdoc, (), tmp_path)
    assert clamp_check(spec, GuardConfig(max_abs_um=63)) is None  # errors of ~12 µm at most
    why = clamp_check(spec, GuardConfig(max_abs_um=2))
    assert why is not None and "fit.input_range" in why and "guard.max_abs_um 2" in why
