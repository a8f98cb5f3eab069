"""`compd fit --on-residual-of`: a model fitted on what models fitted before leave.

It is scored held out against single-stage fits.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import compd.commissioning.fitting as fitting
from compd.cli import main
from compd.identify import holdout
from compd.log import read_log, write_log

SPINDLE_UM_PER_K = 2.0  # the spindle's growth per K of T_spindle's rise
COLUMN_UM_PER_K = (1.5, -0.8)  # the column's, per K of T_col1's and T_col2's rise
COLUMNS = ["t_s", "speed_rpm", "T_spindle", "T_col1", "T_col2", "err_z_um"]


def _first_order(drive: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    """A sensor's temperature following `drive` (°C) with time constant `tau_s`, from 20 °C."""
    out = np.empty_like(drive)
    out[0] = 20.0
    for k in range(1, drive.size):
        out[k] = out[k - 1] + (drive[k] - out[k - 1]) * (1.0 - np.exp(-dt_s / tau_s))
    return out


def _day(path: Path, seed: int, column_heat: bool, n: int = 360, dt_s: float = 60.0) -> np.ndarray:
    """A day of two heat sources on axis z: the spindle (three speeds, T_spindle) and the column
    (hydraulics on mid-day, T_col1 and T_col2 with other time constants), each a known linear
    growth of its sensors' rises, plus noise. Without `column_heat` the column stays cold."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt_s
    speed = np.select([t < 2 * 3600, t < 3 * 3600, t < 4.5 * 3600], [8000.0, 0.0, 12000.0], 3000.0)
    t_spindle = _first_order(20.0 + 1.2e-3 * speed, 1500.0, dt_s)
    heat = ((t > 3600) & (t < 4 * 3600)).astype(float) * column_heat
    t_col1 = _first_order(20.0 + 4.0 * heat, 4000.0, dt_s)
    t_col2 = _first_order(20.0 + 2.5 * heat, 1200.0, dt_s)
    err = (
        SPINDLE_UM_PER_K * (t_spindle - 20.0)
        + COLUMN_UM_PER_K[0] * (t_col1 - 20.0)
        + COLUMN_UM_PER_K[1] * (t_col2 - 20.0)
        + rng.normal(0.0, 0.1, n)
    )
    data = np.column_stack([t, speed, t_spindle, t_col1, t_col2, err])
    data[:, 2:5] += rng.normal(0.0, 0.01, (n, 3))
    write_log(path, COLUMNS, data)
    return data


@pytest.fixture()
def logs(tmp_path: Path) -> dict[str, Path]:
    """The spindle's own day (the column cold) and a day of both sources; the spindle model
    (xi_spindle on T_spindle) fitted on the first."""
    files = {
        "spindle_day": tmp_path / "spindle_day.csv",
        "both": tmp_path / "both.csv",
        "spindle": tmp_path / "spindle.yaml",
    }
    _day(files["spindle_day"], 1, column_heat=False)
    _day(files["both"], 2, column_heat=True)
    assert (
        main(
            [
                "fit",
                "--kind",
                "xi_spindle",
                "--log",
                str(files["spindle_day"]),
                "--inputs",
                "T_spindle",
                "--out",
                str(files["spindle"]),
            ]
        )
        == 0
    )
    return files


def _fit_column(logs: dict[str, Path], *extra: str, kind: str = "mlr") -> tuple[dict, dict]:
    out, rep = logs["both"].with_name("column.yaml"), logs["both"].with_name("column.json")
    rc = main(
        [
            "fit",
            "--kind",
            kind,
            "--log",
            str(logs["both"]),
            "--inputs",
            "T_col1",
            "T_col2",
            "--on-residual-of",
            str(logs["spindle"]),
            "--out",
            str(out),
            "--report",
            str(rep),
            *extra,
        ]
    )
    assert rc == 0
    return yaml.safe_load(out.read_text()), json.loads(rep.read_text())


def test_the_second_stage_recovers_the_second_source_and_names_the_first(logs, capsys) -> None:
    capsys.readouterr()
    doc, report = _fit_column(logs)
    coef = np.asarray(doc["params"]["coef_um_per_k"])[:, 0]
    np.testing.assert_allclose(coef, COLUMN_UM_PER_K, atol=0.05)
    spindle = yaml.safe_load(logs["spindle"].read_text())
    first = {
        "file": "spindle.yaml",
        "sha256": hashlib.sha256(logs["spindle"].read_bytes()).hexdigest(),
        "kind": "xi_spindle",
        "fitted_at": spindle["fit"]["fitted_at"],
    }
    assert doc["fit"]["on_residual_of"] == [first]
    assert report["on_residual_of"] == [
        {**first, "path": str(logs["spindle"]), "inputs": ["T_spindle"], "outputs": ["z"], "log": "spindle_day.csv"}
    ]
    # the sum fits the whole error to its noise (0.1 um); the in-sample figures are the sum's
    assert doc["fit"]["rmse_um"]["z"] < 0.2
    printed = capsys.readouterr().out
    assert (
        "fitting on what spindle.yaml (xi_spindle, fitted on spindle_day.csv) leaves: err_z_um less its prediction"
    ) in printed


def test_the_report_compares_the_sum_held_out_on_the_baselines_folds(logs, capsys) -> None:
    capsys.readouterr()
    doc, report = _fit_column(logs)
    st = report["stagewise"]
    assert {
        "method",
        "folds",
        "first",
        "first_refitted_per_fold",
        "note",
        "kind",
        "inputs",
        "mlr_inputs",
        "forms",
        "axes",
    } <= set(st)
    assert st["method"] == holdout.METHOD and st["first"] == ["spindle.yaml"] and st["kind"] == "mlr"
    assert st["first_refitted_per_fold"] is False and "not refitted per fold" in st["note"]
    assert "spindle.yaml (spindle_day.csv) was fitted on another log" in st["note"]
    assert st["inputs"] == ["T_col1", "T_col2"] and st["mlr_inputs"] == ["T_spindle", "T_col1", "T_col2"]
    z = st["axes"]["z"]
    assert set(z) == {
        "on_residual",
        "residual_of",
        "rows_without_prediction",
        "held_out_rows",
        "sum_held_out_rmse_um",
        "alone_held_out_rmse_um",
        "first_alone_rmse_um",
        "mlr_all_inputs_held_out_rmse_um",
    }
    assert z["on_residual"] is True and z["residual_of"] == ["spindle.yaml"] and z["rows_without_prediction"] == 0

    # the same definitions computed here: the folds of the held-out baseline, each predicted by least
    # squares on the other folds' rows; the spindle model as given (its prediction as compd predict makes it)
    log = read_log(logs["both"])
    pred1 = fitting.predict_log(fitting.load_model(logs["spindle"]), log)[:, 0]
    err = log.col("err_z_um")
    cut, how = holdout.folds(log)
    assert how == st["folds"] == "levels"

    def held_out(target: np.ndarray, names: list[str]) -> float:
        rises = log.matrix(names) - log.matrix(names)[0]
        A = np.column_stack([np.ones(len(log)), rises])
        sq = rows = 0
        for fold in cut:
            hide = np.zeros(len(log), dtype=bool)
            for lo, hi in fold:
                hide[lo:hi] = True
            coef, *_ = np.linalg.lstsq(A[~hide], target[~hide], rcond=None)
            sq += float(np.sum((target[hide] - A[hide] @ coef) ** 2))
            rows += int(hide.sum())
        return float(np.sqrt(sq / rows))

    scored = np.zeros(len(log), dtype=bool)
    for fold in cut:
        for lo, hi in fold:
            scored[lo:hi] = True
    assert z["held_out_rows"] == int(scored.sum())
    assert z["sum_held_out_rmse_um"] == pytest.approx(held_out(err - pred1, ["T_col1", "T_col2"]), rel=1e-9)
    assert z["alone_held_out_rmse_um"] == pytest.approx(held_out(err, ["T_col1", "T_col2"]), rel=1e-9)
    assert z["mlr_all_inputs_held_out_rmse_um"] == pytest.approx(
        held_out(err, ["T_spindle", "T_col1", "T_col2"]), rel=1e-9
    )
    assert z["first_alone_rmse_um"] == pytest.approx(float(np.sqrt(np.mean((err - pred1)[scored] ** 2))), rel=1e-9)
    # the model file's held-out figure is the sum's (what the axis is left with), as the report's own
    assert report["held_out_rmse_um"]["z"] == z["sum_held_out_rmse_um"] == doc["fit"]["held_out_rmse_um"]["z"]

    # two heat sources: the sum predicts the unseen folds far better than either stage alone
    assert z["sum_held_out_rmse_um"] < 0.2
    assert z["sum_held_out_rmse_um"] < 0.2 * min(z["alone_held_out_rmse_um"], z["first_alone_rmse_um"])
    printed = capsys.readouterr().out
    assert (
        f"mlr axis z held out: spindle.yaml + mlr {z['sum_held_out_rmse_um']:.3f} um, mlr on T_col1 T_col2"
        f" alone {z['alone_held_out_rmse_um']:.3f} um, spindle.yaml alone {z['first_alone_rmse_um']:.3f} um"
        f" (as given, not refitted), MLR on T_spindle T_col1 T_col2"
        f" {z['mlr_all_inputs_held_out_rmse_um']:.3f} um"
    ) in printed


def test_the_residual_is_what_compd_predict_gives_for_the_first_model(logs, tmp_path) -> None:
    """The first model evaluated as the daemon does (here with a sensor lead, run through the whole
    log), not a shortcut: the second is the least squares of the error less compd predict's output,
    and the two predictions add up to the error less the fit's residual."""
    led = tmp_path / "spindle_led.yaml"
    assert (
        main(
            [
                "fit",
                "--kind",
                "xi_spindle",
                "--log",
                str(logs["spindle_day"]),
                "--inputs",
                "T_spindle",
                "--option",
                "lag=600",
                "--out",
                str(led),
            ]
        )
        == 0
    )
    out = tmp_path / "column.yaml"
    assert (
        main(
            [
                "fit",
                "--kind",
                "mlr",
                "--log",
                str(logs["both"]),
                "--inputs",
                "T_col1",
                "T_col2",
                "--on-residual-of",
                str(led),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    p1, p2 = tmp_path / "p1.csv", tmp_path / "p2.csv"
    assert main(["predict", str(led), "--log", str(logs["both"]), "--out", str(p1)]) == 0
    assert main(["predict", str(out), "--log", str(logs["both"]), "--out", str(p2)]) == 0
    log = read_log(logs["both"])
    err = log.col("err_z_um")
    pred1, pred2 = read_log(p1).col("pred_z_um"), read_log(p2).col("pred_z_um")
    # the lead matters: the bare gain times the rise is another prediction
    gain = float(yaml.safe_load(led.read_text())["params"]["length_mm"]) * 1.36e-2
    assert np.max(np.abs(pred1 - gain * (log.col("T_spindle") - log.col("T_spindle")[0]))) > 0.5
    rises = log.matrix(["T_col1", "T_col2"]) - log.matrix(["T_col1", "T_col2"])[0]
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(len(log)), rises]), err - pred1, rcond=None)
    doc = yaml.safe_load(out.read_text())
    np.testing.assert_allclose(doc["params"]["intercept_um"][0], coef[0], atol=2e-4)
    np.testing.assert_allclose(np.asarray(doc["params"]["coef_um_per_k"])[:, 0], coef[1:], atol=2e-4)
    left = err - (pred1 + pred2)
    assert doc["fit"]["rmse_um"]["z"] == pytest.approx(float(np.sqrt(np.mean(left**2))), abs=2e-4)
    assert doc["fit"]["max_abs_err_um"]["z"] == pytest.approx(float(np.max(np.abs(left))), abs=2e-4)


def test_several_models_before_are_summed(logs, tmp_path) -> None:
    col2 = tmp_path / "col2.yaml"
    assert main(["fit", "--kind", "mlr", "--log", str(logs["both"]), "--inputs", "T_col2", "--out", str(col2)]) == 0
    out, rep = tmp_path / "col1.yaml", tmp_path / "col1.json"
    assert (
        main(
            [
                "fit",
                "--kind",
                "mlr",
                "--log",
                str(logs["both"]),
                "--inputs",
                "T_col1",
                "--on-residual-of",
                str(logs["spindle"]),
                "--on-residual-of",
                str(col2),
                "--out",
                str(out),
                "--report",
                str(rep),
            ]
        )
        == 0
    )
    log = read_log(logs["both"])
    pred = sum(fitting.predict_log(fitting.load_model(f), log)[:, 0] for f in (logs["spindle"], col2))
    rise = log.col("T_col1") - log.col("T_col1")[0]
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(len(log)), rise]), log.col("err_z_um") - pred, rcond=None)
    doc = yaml.safe_load(out.read_text())
    np.testing.assert_allclose(doc["params"]["coef_um_per_k"][0][0], coef[1], rtol=1e-9)
    assert [f["file"] for f in doc["fit"]["on_residual_of"]] == ["spindle.yaml", "col2.yaml"]
    st = json.loads(rep.read_text())["stagewise"]
    assert st["first"] == ["spindle.yaml", "col2.yaml"]
    assert st["axes"]["z"]["residual_of"] == ["spindle.yaml", "col2.yaml"]
    # col2.yaml was fitted on this very log: the report says what that does to the figures
    assert "col2.yaml (both.csv) was fitted on this log" in st["note"]
    assert "spindle.yaml (spindle_day.csv) was fitted on another log" in st["note"]


def test_an_axis_the_first_model_does_not_predict_is_fitted_as_is(logs, tmp_path, capsys) -> None:
    data = np.loadtxt(logs["both"], delimiter=",", skiprows=1)
    err_x = 0.7 * (data[:, 3] - data[0, 3])
    two = tmp_path / "two.csv"
    write_log(two, [*COLUMNS, "err_x_um"], np.column_stack([data, err_x]))
    out, rep = tmp_path / "c.yaml", tmp_path / "c.json"
    capsys.readouterr()
    assert (
        main(
            [
                "fit",
                "--kind",
                "mlr",
                "--log",
                str(two),
                "--inputs",
                "T_col1",
                "T_col2",
                "--on-residual-of",
                str(logs["spindle"]),
                "--out",
                str(out),
                "--report",
                str(rep),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "err_z_um less its prediction, err_x_um as is (no model before predicts it)" in printed
    assert "mlr axis x: spindle.yaml predicts no axis x: mlr fitted on err_x_um as is" in printed
    st = json.loads(rep.read_text())["stagewise"]
    assert st["axes"]["x"] == {
        "on_residual": False,
        "note": "spindle.yaml predicts no axis x: mlr fitted on err_x_um as is",
    }
    assert st["axes"]["z"]["on_residual"] is True
    coef = np.asarray(yaml.safe_load(out.read_text())["params"]["coef_um_per_k"])
    np.testing.assert_allclose(coef[:, 1], [0.7, 0.0], atol=1e-3)  # x: its own error, nothing subtracted
    np.testing.assert_allclose(coef[:, 0], COLUMN_UM_PER_K, atol=0.05)


def test_rows_without_a_finite_prediction_are_left_out(logs, monkeypatch) -> None:
    log = read_log(logs["both"])
    real = fitting.predict_log

    def gappy(model, lg):  # noqa: ANN001, ANN202
        p = real(model, lg)
        p[10:20] = np.nan
        return p

    monkeypatch.setattr(fitting, "predict_log", gappy)
    stage = fitting.residual_stage(log, [str(logs["spindle"])], None)
    assert stage.left_out == {"err_z_um": 10}
    for lg in (stage.log, stage.whole):
        assert (
            np.isnan(lg.col("err_z_um")[10:20]).all()
            and np.isfinite(np.delete(lg.col("err_z_um"), range(10, 20))).all()
        )
    oc = fitting.fit_model("mlr", log, ["T_col1", "T_col2"], None, {}, stage=stage)
    assert oc.report["stagewise"]["axes"]["z"]["rows_without_prediction"] == 10
    np.testing.assert_allclose(np.asarray(oc.model.params.coef_um_per_k)[:, 0], COLUMN_UM_PER_K, atol=0.05)


def test_kind_all_fits_each_kind_on_the_residual(logs, tmp_path, capsys) -> None:
    data = np.loadtxt(logs["both"], delimiter=",", skiprows=1)
    quiet = tmp_path / "nospeed.csv"  # no speed column: ar1 does not apply (and the test stays short)
    write_log(quiet, [c for c in COLUMNS if c != "speed_rpm"], np.delete(data, 1, axis=1))
    folder, rep = tmp_path / "all", tmp_path / "all.json"
    capsys.readouterr()
    assert (
        main(
            [
                "fit",
                "--kind",
                "all",
                "--log",
                str(quiet),
                "--inputs",
                "T_col1",
                "T_col2",
                "--on-residual-of",
                str(logs["spindle"]),
                "--out",
                str(folder),
                "--report",
                str(rep),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert (
        "held out, each kind fitted on what spindle.yaml leaves (spindle.yaml as given, not refitted per fold):"
    ) in printed
    report = json.loads(rep.read_text())
    for label in ("lvr", "mlr"):
        assert (
            yaml.safe_load((folder / f"{label}.yaml").read_text())["fit"]["on_residual_of"][0]["file"] == "spindle.yaml"
        )
        z = report[label]["stagewise"]["axes"]["z"]
        assert any(
            line.split()[:2] == [label, "z"] and f"{z['sum_held_out_rmse_um']:.3f}" in line
            for line in printed.splitlines()
        )
    assert "skipped" in report["ar1"]


def test_a_missing_input_of_the_first_model_is_one_line_exit_2(logs, tmp_path, capsys) -> None:
    data = np.loadtxt(logs["both"], delimiter=",", skiprows=1)
    short = tmp_path / "short.csv"
    write_log(short, [c for c in COLUMNS if c != "T_spindle"], np.delete(data, 2, axis=1))
    capsys.readouterr()
    rc = main(
        [
            "fit",
            "--kind",
            "mlr",
            "--log",
            str(short),
            "--inputs",
            "T_col1",
            "--on-residual-of",
            str(logs["spindle"]),
            "--out",
            str(tmp_path / "c.yaml"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert err == (
        f"compd: {short}: column 'T_spindle', an input of {logs['spindle']} (--on-residual-of), is not in the log\n"
    )
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("case", ["overwrite", "twice", "no_axis"])
def test_bad_stage_arguments_are_one_line_exit_2(logs, tmp_path, capsys, case) -> None:
    argv = [
        "fit",
        "--kind",
        "mlr",
        "--log",
        str(logs["both"]),
        "--inputs",
        "T_col1",
        "--on-residual-of",
        str(logs["spindle"]),
        "--out",
        str(tmp_path / "c.yaml"),
    ]
    expect = {
        "overwrite": "--out: would overwrite",
        "twice": "--on-residual-of: given twice",
        "no_axis": "--on-residual-of: spindle.yaml predicts axis z, and no target is of that axis (targets: err_x_um)",
    }[case]
    if case == "overwrite":
        argv[-1] = str(logs["spindle"])
    elif case == "twice":
        argv += ["--on-residual-of", str(logs["spindle"])]
    else:
        data = np.loadtxt(logs["both"], delimiter=",", skiprows=1)
        write_log(tmp_path / "x.csv", [*COLUMNS[:-1], "err_x_um"], data)
        argv[4] = str(tmp_path / "x.csv")
    before = logs["spindle"].read_bytes()
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expect in err, err
    assert logs["spindle"].read_bytes() == before
