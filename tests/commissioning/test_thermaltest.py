"""The thermal test's own figures (compd.commissioning.thermaltest): ISO 230-3's drift per axis and the
idle stretches from a hil_sim test log with probe rows, checked against a direct computation, in
`compd fit --report`, on `compd report`'s page and in its --test-json; every bad input one line, exit 2."""

from __future__ import annotations

import csv
import json
import math
import os
import re

import numpy as np
import pytest

from compd.cli import main
from compd.log import read_log, write_log

PROBE_EVERY_S = 600.0  # a measurement every 10 min
PROBE_SIGMA_UM = 0.3

# a short test: idle 1 h (the environment), two speeds with a pause between, idle 1.5 h at the end
SCENARIO = """\
machine: spindle
seed: 5
ambient: {start_c: 20.0, drift_c_per_h: 0.2}
segments:
  - {duration_s: 3600, speed_rpm: 0}
  - {duration_s: 5400, speed_rpm: 6000}
  - {duration_s: 1800, speed_rpm: 0}
  - {duration_s: 5400, speed_rpm: 12000}
  - {duration_s: 5400, speed_rpm: 0}
"""


def with_probes(src, out, every_s=PROBE_EVERY_S, keep_err=True, seed=3):
    """The log with probe_z_um every `every_s` (the true error plus the probe's noise), blank between."""
    log = read_log(src, allow_nan=True)
    t = log.t_s
    at = np.isclose(np.mod(t - t[0], every_s), 0.0)
    rng = np.random.default_rng(seed)
    probe = np.where(at, log.col("err_z_um") + rng.normal(0.0, PROBE_SIGMA_UM, len(t)), np.nan)
    cols = [c for c in log.columns if keep_err or c != "err_z_um"]
    data = np.column_stack([log.col(c) for c in cols] + [probe])
    write_log(out, [*cols, "probe_z_um"], data)


@pytest.fixture(scope="module")
def test_day(tmp_path_factory):
    """A hil_sim thermal test (60 s rows, 6.5 h) with probe rows every 10 min; a model fitted on it,
    an unseen day replayed: fit.json and replay.json as the commands write them (relative names)."""
    from hil_sim.logcmd import load_plant, run_log

    d = tmp_path_factory.mktemp("thermal")
    (d / "test.yaml").write_text(SCENARIO)
    run_log(load_plant(str(d / "test.yaml")), d / "sim.csv", 60.0)
    with_probes(d / "sim.csv", d / "test.csv")
    run_log(load_plant("hil_sim/scenarios/spindle_unseen.yaml"), d / "unseen.csv", 60.0, 4 * 3600)
    cwd = os.getcwd()
    try:
        os.chdir(d)
        assert (
            main(
                [
                    "fit",
                    "--kind",
                    "xi_spindle",
                    "--log",
                    "test.csv",
                    "--inputs",
                    "T_xi",
                    "speed_rpm",
                    "--target",
                    "err_z_um",
                    "--out",
                    "model.yaml",
                    "--report",
                    "fit.json",
                ]
            )
            == 0
        )
        assert main(["replay", "--model", "model.yaml", "--log", "unseen.csv", "--report", "replay.json"]) == 0
    finally:
        os.chdir(cwd)
    return d


def columns(path):
    """The CSV as {column: floats}, empty cells NaN: read without compd."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return {name: np.array([float(r[i]) if r[i] else math.nan for r in rows[1:]]) for i, name in enumerate(rows[0])}


def direct(log_csv, model_yaml=None):
    """The figures computed here, from the CSV: the probe rows, the drift from the first probe, and the
    residual against `compd predict`'s prediction."""
    c = columns(log_csv)
    rows = np.flatnonzero(np.isfinite(c["probe_z_um"]))
    m = c["probe_z_um"][rows]
    drift = m - m[0]
    k = int(np.argmax(np.abs(drift)))
    out = {
        "rows": rows,
        "t_s": c["t_s"][rows],
        "drift": drift,
        "max_abs": abs(drift[k]),
        "at_t_s": c["t_s"][rows][k],
        "range": m.max() - m.min(),
        "speed": c["speed_rpm"],
    }
    if model_yaml is not None:
        from compd.commissioning.fitting import load_model, predict_log, read_fit_log

        pred = predict_log(load_model(model_yaml), read_fit_log(log_csv))[rows, 0]
        r = m - pred
        out.update(
            pred=pred,
            residual=r,
            rms=float(np.sqrt(np.mean(r * r))),
            max_res=float(np.max(np.abs(r))),
            res_range=float(r.max() - r.min()),
        )
    return out


def test_drift_and_residual_are_the_direct_computation(test_day):
    from compd.commissioning.htmlreport import thermal_from_files

    tt = thermal_from_files(test_day / "test.csv", test_day / "model.yaml", PROBE_EVERY_S)
    want = direct(test_day / "test.csv", test_day / "model.yaml")
    assert [a.axis for a in tt.axes] == ["z", "radial"] and tt.not_measured == {}
    z, radial = tt.axes
    assert z.source == "probe_z_um"  # the probe rows, not the continuous err column beside them
    # the axis the model does not predict: its err column at the same rows, its drift only
    assert (radial.source, radial.sampled, radial.residual()) == ("err_radial_um", "at the log's probe rows", None)
    assert np.array_equal(radial.rows, want["rows"]) and radial.why_no_prediction == "not an output of model.yaml"
    assert np.array_equal(z.rows, want["rows"]) and len(z.rows) == 21600 // 600 + 1
    np.testing.assert_allclose(z.drift_um, want["drift"], atol=1e-9)
    d = z.drift()
    assert d.max_abs_um == pytest.approx(want["max_abs"]) and d.at_t_s == want["at_t_s"]
    assert d.range_um == pytest.approx(want["range"])
    assert d.max_abs_um > 10.0  # the spindle's growth: a real drift, not noise
    r = z.residual()
    assert r.rms_um == pytest.approx(want["rms"]) and r.max_abs_um == pytest.approx(want["max_res"])
    assert r.range_um == pytest.approx(want["res_range"])
    np.testing.assert_allclose(z.residual_um, want["residual"], atol=1e-9)
    # the before/after of the test's figure: the model leaves a small part of the drift
    assert r.range_um < 0.3 * d.range_um and r.rms_um < 1.5


def test_idle_stretches_at_the_start_and_the_end(test_day):
    from compd.commissioning.htmlreport import thermal_from_files

    tt = thermal_from_files(test_day / "test.csv", test_day / "model.yaml", PROBE_EVERY_S)
    want = direct(test_day / "test.csv", test_day / "model.yaml")
    assert [(s.where, s.from_t_s, s.to_t_s) for s in tt.idle] == [("start", 0.0, 3600.0), ("end", 16200.0, 21600.0)]
    c = columns(test_day / "test.csv")
    for st in tt.idle:
        f = st.figures(tt.axes[0])
        inside = (
            (want["t_s"] >= st.from_t_s) & (want["t_s"] < st.to_t_s)
            if st.where == "start"
            else (want["t_s"] >= st.from_t_s)
        )
        m = c["probe_z_um"][want["rows"][inside]]
        assert f.measurements == inside.sum() >= 6
        assert f.range_um == pytest.approx(m.max() - m.min()) and f.change_um == pytest.approx(m[-1] - m[0])
        res = want["residual"][inside]
        assert f.residual_range_um == pytest.approx(res.max() - res.min())
    # at rest at the start: only the probe's noise and the air's 0.2 K/h; at the end the machine cools down
    start, end = (s.figures(tt.axes[0]) for s in tt.idle)
    assert start.range_um < 2.5 < end.range_um and end.change_um < 0


def _log(path, t, speed=None, err=None, probe=None):
    cols, data = ["t_s", "T1"], [t, 20.0 + 0.001 * t]
    for name, v in (("speed_rpm", speed), ("err_z_um", err), ("probe_z_um", probe)):
        if v is not None:
            cols.append(name)
            data.append(v)
    write_log(path, cols, np.column_stack(data))
    return read_log(path, allow_nan=True)


def test_err_is_taken_every_n_minutes_or_at_the_probe_rows(tmp_path):
    from compd.commissioning.thermaltest import every_rows, thermal_test

    # the first row at or after each 10 min from the first measurement, whatever the rows' spacing
    t = np.array([0.0, 250.0, 590.0, 610.0, 1300.0, 1790.0, 1800.0, 2500.0])
    assert every_rows(t, np.arange(len(t)), 600.0).tolist() == [0, 3, 4, 6, 7]
    assert every_rows(t, np.array([1, 2, 5, 7]), 600.0).tolist() == [1, 5, 7]  # from the first measurement at 250 s
    t = np.arange(0.0, 7200.0 + 1, 60.0)
    err = np.sin(t / 2000.0) * 10
    log = _log(tmp_path / "a.csv", t, speed=np.full(t.size, 5000.0), err=err)
    tt = thermal_test(log, every_s=1800.0)
    z = tt.axes[0]
    assert z.source == "err_z_um" and z.sampled == "every 30 min" and z.t_s.tolist() == [0, 1800, 3600, 5400, 7200]
    assert z.residual() is None and z.why_no_prediction == "no model"
    assert tt.idle == [] and "runs at the log's first and last rows" in tt.idle_why_not
    # with probe rows of another axis in the log, err_z is taken at those rows
    probe = np.where(np.mod(t, 900.0) == 0, 1.0, np.nan)
    write_log(tmp_path / "b.csv", ["t_s", "T1", "err_z_um", "probe_x_um"], np.column_stack([t, 20 + 0 * t, err, probe]))
    tt = thermal_test(read_log(tmp_path / "b.csv", allow_nan=True), ["z"], np.zeros((t.size, 1)), "m.yaml")
    z, x = tt.axes
    assert (z.axis, z.source, z.sampled) == ("z", "err_z_um", "at the log's probe rows")
    assert z.t_s.tolist() == list(np.arange(0.0, 7201.0, 900.0)) and x.source == "probe_x_um"
    assert x.why_no_prediction == "not an output of m.yaml"
    assert "idle stretches are not found without it" in tt.idle_why_not


def test_a_log_where_the_spindle_never_runs_is_one_idle_stretch(tmp_path):
    from compd.commissioning.thermaltest import thermal_test

    t = np.arange(0.0, 3 * 3600.0 + 1, 600.0)
    probe = 0.5 * np.sin(t / 5000.0)
    tt = thermal_test(_log(tmp_path / "env.csv", t, speed=0 * t, probe=probe))
    (st,) = tt.idle
    assert (st.where, st.from_t_s, st.to_t_s) == ("whole", 0.0, 3 * 3600.0)
    assert st.figures(tt.axes[0]).range_um == pytest.approx(probe.max() - probe.min())


def test_the_fit_report_keeps_the_test_figures(test_day):
    fit = json.loads((test_day / "fit.json").read_text())
    block = fit["thermal_test"]
    want = direct(test_day / "test.csv", test_day / "model.yaml")
    z = block["axes"]["z"]
    assert z["source"] == "probe_z_um" and z["measurements"] == len(want["rows"])
    assert z["drift"]["max_abs_um"] == pytest.approx(want["max_abs"]) and z["drift"]["range_um"] == pytest.approx(
        want["range"]
    )
    assert z["residual"]["rms_um"] == pytest.approx(want["rms"])  # in sample: the fit's own prediction
    assert z["t_s"] == want["t_s"].tolist() and z["speed_rpm"] == want["speed"][want["rows"]].tolist()
    assert z["residual_um"] == pytest.approx(want["residual"].tolist())
    assert [s["where"] for s in block["idle"]] == ["start", "end"] and block["log"] == "test.csv"


def test_a_fit_on_a_log_that_measures_no_axis_says_why():
    from compd.commissioning.fitting import thermal_test_block
    from compd.log import Log

    log = Log("x.csv", ["t_s", "T1", "dz"], np.zeros((3, 3)))
    assert thermal_test_block(log, type("M", (), {"outputs": ["dz"]})(), np.zeros((3, 1))) == {
        "skipped": "no probe_<axis>_um or err_<axis>_um column: not the log of a thermal test"
    }


REPORT = ["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html"]


def test_the_page_shows_the_test_and_the_json_has_it(test_day, monkeypatch, capsys):
    monkeypatch.chdir(test_day)
    assert main([*REPORT, "--test-json", "tt.json"]) == 0  # the fit report's log and model by default
    out = capsys.readouterr().out
    want = direct(test_day / "test.csv", test_day / "model.yaml")
    assert (
        f"compd report: thermal test of test.csv, axis z: {len(want['rows'])} measurements (probe_z_um),"
        f" largest drift {want['max_abs']:.2f} um at {want['at_t_s'] / 3600:.2f} h, range {want['range']:.2f} um;"
        f" residual RMS {want['rms']:.2f} um, range {want['res_range']:.2f} um"
    ) in out
    text = (test_day / "r.html").read_text()
    section = text.split("<h2>The thermal test: drift per axis (ISO 230-3)</h2>")[1].split("<h2>")[0]
    assert "the log the fit report fit.json names" in section
    summary = re.search(r"<tbody><tr><td class=\"l\">z</td>(.*?)</tr>", section)[1]
    cells = [re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", summary)]
    first = columns(test_day / "test.csv")["probe_z_um"][want["rows"][0]]
    assert cells == [
        "probe_z_um, at its probe rows",
        str(len(want["rows"])),
        f"{first:.2f}",
        f"{want['max_abs']:.2f}",
        f"{want['at_t_s'] / 3600:.2f}",
        f"{want['range']:.2f}",
        f"{want['rms']:.2f}",
        f"{want['max_res']:.2f}",
        f"{want['res_range']:.2f}",
    ]
    assert "at the start: the machine at rest, the environment alone" in section
    assert "at the end: the cool-down after the last run" in section
    assert len(re.findall(r'<img src="data:image/png;base64,', section)) == 1
    measure = re.search(r'<table class="measure">(.*?)</table>', section)[1]
    assert measure.count("<tr>") == len(want["rows"]) + 1  # the header and one row per measurement
    assert "<th>z residual / µm</th>" in measure and "<th>speed / rpm</th>" in measure
    k = len(want["rows"]) // 2  # one row in the middle, as the direct computation has it
    row = re.findall(r"<tr>(.*?)</tr>", measure)[k + 1]
    radial = columns(test_day / "test.csv")["err_radial_um"][want["rows"]]  # drift only: the model has no radial
    assert [re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)] == [
        f"{want['t_s'][k] / 3600:.2f}",
        f"{want['t_s'][k]:.1f}",
        f"{want['speed'][want['rows'][k]]:.0f}",
        f"{want['drift'][k]:.2f}",
        f"{want['pred'][k]:.2f}",
        f"{want['residual'][k]:.2f}",
        f"{radial[k] - radial[0]:.2f}",
    ]
    glance = text.split("<h2>At a glance</h2>")[1].split("</ul>")[0]
    assert f"axis z, thermal test: largest drift <b>{want['max_abs']:.2f} µm</b>" in glance
    block = json.loads((test_day / "tt.json").read_text())
    fit = json.loads((test_day / "fit.json").read_text())["thermal_test"]
    assert block["model"] == "model.yaml" and fit["model"] is None
    assert block["axes"]["z"]["drift"] == fit["axes"]["z"]["drift"]  # the page's figures are the fit report's
    assert block["axes"]["z"]["residual"] == pytest.approx(fit["axes"]["z"]["residual"])


def test_another_log_and_model_are_given_by_options(test_day, monkeypatch, capsys):
    """--test-log: a log with err_z_um only (sampled every --test-every-min), --model another model."""
    monkeypatch.chdir(test_day)
    assert (
        main(
            [
                "fit",
                "--kind",
                "mlr",
                "--log",
                "test.csv",
                "--inputs",
                "T_xi",
                "--target",
                "err_z_um",
                "--out",
                "mlr.yaml",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                *REPORT,
                "--test-log",
                "unseen.csv",
                "--model",
                "mlr.yaml",
                "--test-every-min",
                "30",
                "--test-json",
                "u.json",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    block = json.loads((test_day / "u.json").read_text())
    z = block["axes"]["z"]
    assert block["log"] == "unseen.csv" and block["model"] == "mlr.yaml" and block["every_s"] == 1800.0
    assert z["source"] == "err_z_um" and z["sampled"] == "every 30 min" and np.all(np.diff(z["t_s"]) == 1800.0)
    assert z["measurements"] == 4 * 2 + 1 and "radial" in block["axes"]  # the log's other axis: its drift only
    assert block["axes"]["radial"]["residual"] is None and block["axes"]["radial"]["why_no_residual"] == (
        "not an output of mlr.yaml"
    )
    assert "thermal test of unseen.csv, axis radial: 9 measurements (err_radial_um)" in out
    assert "no residual (not an output of mlr.yaml)" in out
    text = (test_day / "r.html").read_text()
    assert "log <code>unseen.csv</code> (--test-log)" in text and "model <code>mlr.yaml</code>" in text
    assert "data: the thermal test log" in text  # the record names the log it came from


def test_without_the_log_the_section_says_why(test_day, tmp_path, monkeypatch, capsys):
    import shutil

    for f in ("fit.json", "replay.json", "model.yaml", "unseen.csv"):
        shutil.copy(test_day / f, tmp_path / f)
    monkeypatch.chdir(tmp_path)  # test.csv is not here
    assert main(REPORT) == 0
    assert "compd: the thermal test is not shown: the log 'test.csv' that fit.json names is not found" in (
        capsys.readouterr().err
    )
    text = (tmp_path / "r.html").read_text()
    assert "Not shown: the log &#x27;test.csv&#x27; that fit.json names is not found" in text
    assert main([*REPORT, "--test-json", "t.json"]) == 2  # nothing to write: one line, nothing written
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--test-json: no thermal test to write" in err
    assert not (tmp_path / "t.json").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--test-log", "nope.csv"], ["nope.csv", "cannot read log"]),
        (["--test-log", "empty.csv"], ["empty.csv", "no probe_<axis>_um or err_<axis>_um column"]),
        (["--test-log", "bad.csv"], ["bad.csv:3", "err_z_um", "not a number"]),
        (["--test-log", "other.csv"], ["other.csv", "'T_xi', an input of model.yaml, is not in the log"]),
        (["--model", "nope.yaml"], ["nope.yaml: cannot read"]),
        (["--test-every-min", "0"], ["--test-every-min", "must be > 0"]),
        (["--test-every-min", "5000"], ["--test-every-min", "5000 min: between 0.1 and 1440 min"]),
        (["--test-every-min", "nan"], ["--test-every-min", "finite"]),
        (["--test-json", "."], [".: --test-json: is a folder"]),
    ],
)
def test_bad_test_inputs_are_one_line_exit_2(test_day, monkeypatch, capsys, argv, words):
    monkeypatch.chdir(test_day)
    write_log(test_day / "empty.csv", ["t_s", "T_xi", "speed_rpm"], np.array([[0.0, 20.0, 0.0], [60.0, 20.1, 0.0]]))
    (test_day / "bad.csv").write_text("t_s,T_xi,speed_rpm,err_z_um\n0,20,0,0\n60,20,0,x\n")
    write_log(test_day / "other.csv", ["t_s", "T1", "speed_rpm", "err_z_um"], np.array([[0.0, 20.0, 0.0, 0.0]]))
    (test_day / "r.html").unlink(missing_ok=True)
    try:  # argparse's own checks exit through SystemExit, compd's return 2
        rc = main([*REPORT, *argv])
    except SystemExit as e:
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    assert not (test_day / "r.html").exists()
