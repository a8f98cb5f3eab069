"""Fits that cannot work say so: parameters at the edge of their range, models that remove nothing,
kinds that lack what they need, and `--kind all`'s per-kind inputs, held-out columns and recommendation."""

from __future__ import annotations

import numpy as np
import pytest

from compd.cli import main
from compd.commissioning import fitting
from compd.log import Log, write_log


def _lathe(n_h: float = 24.0, dt: float = 60.0) -> Log:
    """A lathe day: Z = bed growth − spindle growth (AR(1) of the speed), T7 the air."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, n_h * 3600, dt)
    h = t / 3600
    speed = np.select([(h >= 1) & (h < 6), (h >= 8) & (h < 13)], [2000.0, 1500.0], 0.0)
    s, S = 0.0, np.zeros(t.size)
    for k in range(1, t.size):
        s = 0.995 * s + 0.2 * (speed[k] / 2000.0) ** 1.5
        S[k] = s
    bed = 20 + 2.0 * (1 - np.exp(-np.maximum(h - 1, 0) / 6))
    head = 20 + 0.25 * S + rng.normal(0, 0.02, t.size)
    air = 20 + 0.3 * np.sin(h / 3)
    err = 12.0 * (bed - bed[0]) - S + rng.normal(0, 0.1, t.size)
    return Log(
        "lathe.csv",
        ["t_s", "speed_rpm", "T1", "T3", "T7", "err_z_um"],
        np.column_stack([t, speed, head, bed + rng.normal(0, 0.02, t.size), air, err]),
    )


def test_a_model_that_removes_nothing_warns():
    log = _lathe()
    flat = log.data.copy()
    flat[:, -1] = np.random.default_rng(1).normal(0, 1.0, len(log))  # an error no temperature explains
    oc = fitting.fit_model("mlr", Log(log.file, log.columns, flat), ["T3"], None, {}, baseline=False)
    assert any("removes almost nothing" in w for w in oc.warnings)


def test_an_ar1_whose_spindle_term_predicts_nothing_warns():
    log = _lathe()
    data = log.data.copy()
    data[:, -1] = 12.0 * (data[:, 3] - data[0, 3])  # no spindle at all: C2 = 0, C1 anywhere
    oc = fitting.fit_model(
        "ar1", Log(log.file, log.columns, data), ["T3"], None, {"c1_by_speed": False, "lag": "off"}, baseline=False
    )
    assert any("C2 is 0 at every speed" in w for w in oc.warnings), oc.warnings


def test_ar1_without_a_structure_sensor_is_refused_and_chooses_its_own_otherwise(tmp_path, capsys):
    log = _lathe()
    only = tmp_path / "speed.csv"
    write_log(only, ["t_s", "speed_rpm", "T_amb", "err_z_um"], log.data[:, [0, 1, 4, 5]])
    rc = main(["fit", "--kind", "ar1", "--log", str(only), "--out", str(tmp_path / "m.yaml")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "--inputs" in err and "spindle_sign=1" in err
    oc = fitting.fit_model("ar1", log, None, None, {"lag": "off"}, baseline=False)
    assert oc.report["details"]["inputs_chosen"]["inputs"]  # chosen held out, and said so
    assert set(oc.model.inputs) - {"speed_rpm"} <= {"T1", "T3", "T7"}


def test_a_log_with_blank_error_cells_fits_on_the_rows_measured():
    log = _lathe()
    data = log.data.copy()
    data[::3, -1] = np.nan  # the interferometer read two rows in three
    oc = fitting.fit_model("mlr", Log(log.file, log.columns, data), ["T1", "T3"], None, {}, baseline=False)
    full = fitting.fit_model("mlr", log, ["T1", "T3"], None, {}, baseline=False)
    np.testing.assert_allclose(oc.model.params.coef_um_per_k, full.model.params.coef_um_per_k, rtol=0.05, atol=0.05)


def test_fit_all_gives_each_kind_its_inputs_says_held_out_and_recommends(tmp_path, capsys):
    log = tmp_path / "lathe.csv"
    lg = _lathe()
    write_log(log, lg.columns, lg.data)
    rc = main(
        [
            "fit",
            "--kind",
            "all",
            "--log",
            str(log),
            "--out",
            str(tmp_path / "m"),
            "--option",
            "lag=off",
            "--report",
            str(tmp_path / "all.json"),
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert "in-sample" in out and "held-out" in out  # the table says which is which
    assert "skipped: no pos_<axis>_mm column" in out  # feed_axis lacks its position
    assert "recommended: " in out and "expected on an unseen day, axis z: RMS" in out
    assert (tmp_path / "m" / "recommended.yaml").exists()
    import json

    rep = json.loads((tmp_path / "all.json").read_text())
    assert rep["recommended"]["label"] in rep and rep["recommended"]["expected_unseen"]["z"]["rms_um"] > 0
    assert rep["ar1"]["inputs"][0] == "speed_rpm" and len(rep["ar1"]["inputs"]) >= 2  # its own structure sensors
    assert rep["lvr"]["inputs"] == ["T1", "T3", "T7"]  # every temperature


@pytest.mark.parametrize("warned", ["blocking", "advice", None])
def test_only_a_warning_that_rules_a_fit_out_keeps_it_from_the_recommendation(warned):
    """A fit that did not converge or predicts nothing is never the recommendation; one whose warning
    only advises (a parameter at the edge of its range, a lag at the longest tried) is judged on its
    held-out error like any other (a better LVR lost to MLR over a lag warning)."""
    from compd.commissioning import recommend as rec

    class Oc:
        def __init__(self, kind, held, warnings, blocking):
            self.kind = kind
            self.warnings, self.blocking = warnings, blocking
            self.fold_rms_um = {"z": [held * 0.8, held * 1.2]}
            self.report = {
                "axes": {"z": {"rmse_um": 0.1, "max_abs_err_um": 0.2}},
                "fit_time_s": 0.0,
                "held_out_rmse_um": {"z": held},
            }

    why = ["ar1: C1 … at the edge"] if warned else []
    rows = [
        ("ar1", "ar1", Oc("ar1", 0.5, why, why if warned == "blocking" else []), None),
        ("mlr", "mlr", Oc("mlr", 0.9, [], []), None),
    ]
    pick = rec.choose(rec.candidates(rows, [], fitting.held_out_of), ["z"], {"z": 10.0})
    assert pick.candidate.label == ("mlr" if warned == "blocking" else "ar1")
    assert pick.stated["z"].rms_um == (0.9 if warned == "blocking" else 0.5)


def test_a_named_structure_sensor_the_fit_pins_at_zero_warns(tmp_path, capsys):
    # the error shrinks as T5 warms (its gain would be negative): the bound (≥ 0) pins it at 0 and it
    # contributes nothing; the fit says which sensor and what to do, on stderr and in the report
    log = _lathe()
    h = log.t_s / 3600
    t5 = 20.0 + 0.5 * np.sin(h / 2.5) + np.random.default_rng(4).normal(0, 0.02, h.size)
    err = log.col("err_z_um") - 3.0 * (t5 - t5[0])
    f = tmp_path / "lathe.csv"
    write_log(f, [*log.columns[:-1], "T5", "err_z_um"], np.column_stack([log.data[:, :-1], t5, err]))
    rep = tmp_path / "r.json"
    rc = main(
        [
            "fit",
            "--kind",
            "ar1",
            "--log",
            str(f),
            "--inputs",
            "T3",
            "T5",
            "--option",
            "lag=off",
            "--option",
            "c1_by_speed=false",
            "--option",
            "ambient=none",
            "--out",
            str(tmp_path / "m.yaml"),
            "--report",
            str(rep),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 0, err
    line = next(x for x in err.splitlines() if "T5" in x)
    assert line.startswith("compd: warning: ar1: the structure sensor T5 (named with --inputs) has gain 0")
    assert "drop it from --inputs" in line and "bed_gains=free" in line
    assert "T3" not in line  # the sensor the fit uses is not warned about
    import json

    assert any("structure sensor T5" in w for w in json.loads(rep.read_text())["warnings"])
