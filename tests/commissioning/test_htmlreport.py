"""`compd report`: one self-contained HTML page from a fit and a replay report; it renders in Chromium."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

from compd.cli import main
from compd.log import write_log

BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")


def day(path, seed, n=240):
    """A 2-hour day at 30 s: one temperature, the error 2 µm/K of its rise plus noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 30.0
    temp = 20.0 + 6.0 * (1 - np.exp(-t / 2400.0)) + rng.normal(0, 0.02, n)
    err = 2.0 * (temp - 20.0) + rng.normal(0, 0.2, n)
    write_log(path, ["t_s", "T1", "err_x1_um"], np.column_stack([t, temp, err]))


@pytest.fixture
def reports(tmp_path, monkeypatch):
    """fit.json and replay.json as the commands write them, run in tmp_path (relative names)."""
    monkeypatch.chdir(tmp_path)
    day(tmp_path / "train.csv", 1)
    day(tmp_path / "unseen.csv", 2)
    assert (
        main(
            [
                "fit",
                "--kind",
                "xi_spindle",
                "--log",
                "train.csv",
                "--inputs",
                "T1",
                "--out",
                "model.yaml",
                "--report",
                "fit.json",
            ]
        )
        == 0
    )
    (tmp_path / "c.yaml").write_text(
        "# <the config> & its text\n"
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources:\n  - {kind: replay, name: log, path: unseen.csv}\n"
        "model: {kind: xi_spindle, file: model.yaml}\n"
        "sink: {kind: fanuc_pmc}\n"
    )
    assert main(["replay", "c.yaml", "--log", "unseen.csv", "--report", "replay.json"]) == 0
    return tmp_path


def images(text):
    return re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)


def test_report_is_one_self_contained_page(reports, capsys):
    fit = json.loads((reports / "fit.json").read_text())
    rep = json.loads((reports / "replay.json").read_text())
    assert fit["model"] == "model.yaml" and rep["log"] == "unseen.csv" and rep["config"] == "c.yaml"
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "report.html"]) == 0
    assert "replay of x1, 2 plots -> report.html" in capsys.readouterr().out
    text = (reports / "report.html").read_text()
    assert text.startswith("<!DOCTYPE html>")
    # nothing fetched from anywhere: no scripts, no links, no external sources
    assert not re.search(r'(src|href)="(?!data:)', text) and "<script" not in text and "<link" not in text
    pngs = images(text)
    assert len(pngs) == 3  # the fit's, the replay's and the thermal test's (from the fit's log)
    import base64

    assert all(base64.b64decode(p)[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    # the figures of both reports, as the JSON has them
    assert f"{fit['axes']['x1']['rmse_um']:.2f}" in text
    held = fit["baseline_mlr"]["axes"]["x1"]
    assert f"{held['held_out_rmse_um']:.2f}" in text and f"{held['mlr_held_out_rmse_um']:.2f}" in text
    for k in ("rms_before_um", "rms_after_um", "max_abs_after_um"):
        assert f"{rep['axes']['x1'][k]:.2f}" in text
    assert f"{rep['axes']['x1']['reduction_pct']:.1f} %" in text
    # the coefficients of the model file, and the config's text escaped
    assert "length_mm" in text and "alpha_per_k" in text
    assert "# &lt;the config&gt; &amp; its text" in text


def test_report_embeds_given_pngs(reports):
    from compd.commissioning.plots import Trend, write_trend

    png = reports / "mine.png"
    t = np.arange(10.0)
    write_trend(Trend(t, ["x1"], {"T1": 20 + t}, np.zeros(10, int), ["x1"], 1.0, np.zeros((10, 1))), png)
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html", "--png", str(png)]) == 0
    text = (reports / "r.html").read_text()
    assert len(images(text)) == 2 and "mine.png" in text  # the one given, and the thermal test's


def test_report_without_the_data_says_what_is_missing(reports, capsys):
    (reports / "unseen.csv").unlink()
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html"]) == 0
    captured = capsys.readouterr()
    assert "1 plots" in captured.out and "'unseen.csv' is not found" in captured.err
    assert len(images((reports / "r.html").read_text())) == 2  # the fit's and the thermal test's


@pytest.mark.parametrize(
    "which, content, words",
    [
        ("fit", '{\n  "kind": "mlr",\n  oops\n}\n', ["bad.json:3", "--fit", "not JSON"]),
        ("fit", "[1, 2]", ["bad.json", "--fit", "JSON object"]),
        ("fit", json.dumps({"axes": {"x1": {"rmse_um": 1.0}}}), ["bad.json", "kind"]),
        ("fit", json.dumps({"kind": "mlr", "axes": {"x1": {"rmse_um": "big"}}}), ["bad.json", "axes.x1.rmse_um"]),
        ("fit", json.dumps({"mlr": {"kind": "mlr"}, "ar1": {"kind": "ar1"}}), ["bad.json", "--kind all"]),
        (
            "fit",
            json.dumps(
                {
                    "kind": "mlr",
                    "axes": {"x1": {"rmse_um": 1.0}},
                    "baseline_mlr": {"axes": {"x1": {"held_out_rmse_um": None}}},
                }
            ),
            ["bad.json", "baseline_mlr.axes.x1.held_out_rmse_um"],
        ),
        ("replay", json.dumps({"rows": 3}), ["bad.json", "axes", "compd replay --report"]),
        (
            "replay",
            json.dumps({"axes": {"z": {"rms_before_um": 1, "rms_after_um": 1, "reduction_pct": 0}}}),
            ["bad.json", "axes.z.max_abs_after_um", "missing"],
        ),
        ("replay", "\xff\xfe", ["bad.json", "--replay"]),
    ],
)
def test_bad_report_json_is_exit_2(reports, capsys, which, content, words):
    bad = reports / "bad.json"
    bad.write_bytes(content.encode("latin-1") if which == "replay" and content.startswith("\xff") else content.encode())
    args = {"fit": "fit.json", "replay": "replay.json", which: "bad.json"}
    assert main(["report", "--fit", args["fit"], "--replay", args["replay"], "--out", "r.html"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    for w in words:
        assert w in err
    assert not (reports / "r.html").exists()


def test_missing_report_files_are_exit_2(reports, capsys):
    assert main(["report", "--fit", "nope.json", "--replay", "replay.json", "--out", "r.html"]) == 2
    assert "nope.json: --fit: cannot read" in capsys.readouterr().err
    assert (
        main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html", "--config", "nope.yaml"])
        == 2
    )
    assert "nope.yaml: --config" in capsys.readouterr().err
    (reports / "x.png").write_text("not a png")
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html", "--png", "x.png"]) == 2
    assert "x.png: --png: not a PNG" in capsys.readouterr().err


def browser() -> str | None:
    found = next((b for b in map(shutil.which, BROWSERS) if b), None)
    if found is None and os.environ.get("CI"):  # make test installs it (Makefile APT_PACKAGES)
        pytest.fail(f"no headless Chromium ({', '.join(BROWSERS)}) on PATH: make sysdeps installs it")
    return found


def chromium(exe: str, *args: str) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run(
        [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            "--disable-extensions",
            "--user-data-dir=" + str(args[-1]) + ".profile",
            *args[:-1],
            "file://" + str(args[-1]),
        ],
        capture_output=True,
        timeout=120,
        check=False,
    )


def test_report_renders_in_headless_chromium(reports):
    exe = browser()
    if exe is None:
        pytest.skip("no headless Chromium here (Debian package chromium-headless-shell)")
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "report.html", *RECORD]) == 0
    page = reports / "report.html"
    dom = chromium(exe, "--dump-dom", page)
    assert dom.returncode == 0, dom.stderr.decode(errors="replace")[-2000:]
    html = dom.stdout.decode()
    assert "compd commissioning report" in html and html.count("<img") == 3 and "<table" in html
    assert "The thermal test: drift per axis (ISO 230-3)" in html and '<table class="measure">' in html
    assert '<table class="record">' in html and '<section class="signoff">' in html
    # printed, it is laid out on A4 (595 x 842 pt), on a few pages: the print stylesheet took
    pdf = reports / "report.pdf"
    printed = chromium(exe, f"--print-to-pdf={pdf}", "--no-pdf-header-footer", page)
    assert printed.returncode == 0 and pdf.exists(), printed.stderr.decode(errors="replace")[-2000:]
    data = pdf.read_bytes()
    boxes = {tuple(round(float(v)) for v in m.split()) for m in re.findall(rb"/MediaBox\s*\[([^\]]*)\]", data)}
    assert boxes == {(0, 0, 595, 842)}, boxes
    assert 1 <= len(re.findall(rb"/Type\s*/Page[^s]", data)) <= 8
    shot = reports / "shot.png"
    run = chromium(exe, "--window-size=1200,4000", f"--screenshot={shot}", page)  # down to the plots
    assert run.returncode == 0 and shot.exists(), run.stderr.decode(errors="replace")[-2000:]
    import matplotlib.image

    img = matplotlib.image.imread(shot)[..., :3]
    assert img.shape[:2] == (4000, 1200)
    # the page is not blank, and the plots were decoded and drawn: pixels of their line colours
    assert (img.min(axis=2) < 0.5).mean() > 0.005
    saturated = (img.max(axis=2) - img.min(axis=2)) > 0.35
    assert saturated.sum() > 2000


def test_report_says_when_the_mlr_comparison_was_skipped(reports):
    fit = json.loads((reports / "fit.json").read_text())
    fit["baseline_mlr"] = {"skipped": "the held-out comparison could not fit a block: <too few rows>"}
    (reports / "fit2.json").write_text(json.dumps(fit))
    assert main(["report", "--fit", "fit2.json", "--replay", "replay.json", "--out", "r.html"]) == 0
    text = (reports / "r.html").read_text()
    assert (
        "No held-out comparison with MLR: the held-out comparison could not fit a block: &lt;too few rows&gt;" in text
    )
    assert "MLR baseline held-out RMSE" not in text


RECORD = [
    "--machine",
    "DMU 50 s/n 1234 <hall 2>",
    "--operator",
    "A. Meier",
    "--ambient-c",
    "22.0",
    "20.5",
    "--instrument",
    "Renishaw XL-80 s/n 9876, 0.001 µm",
]


def cells(text):
    """The page's table cells before the sign-off, as text (tags stripped)."""
    head = text.split('<section class="signoff">')[0]
    return [re.sub(r"<[^>]+>", "", c).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", head, re.S)]


def record_rows(text):
    """The record table as {label: text}."""
    table = re.search(r'<table class="record">(.*?)</table>', text, re.S)[1]
    return {
        re.sub(r"<[^>]+>", "", k): re.sub(r"<[^>]+>", "", v)
        for k, v in re.findall(r'<th class="l">(.*?)</th><td class="l">(.*?)</td>', table, re.S)
    }


def test_the_record_shows_what_the_options_give(reports, capsys):
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html", *RECORD]) == 0
    assert capsys.readouterr().err == ""  # every record field given: nothing to say
    text = (reports / "r.html").read_text()
    rec = record_rows(text)
    assert rec["machine"] == "DMU 50 s/n 1234 &lt;hall 2&gt;"  # escaped, as given
    assert rec["operator (ran the test)"] == "A. Meier"
    assert rec["measuring instrument"] == "Renishaw XL-80 s/n 9876, 0.001 µm"
    # the lowest first, whatever the order given; the logs have no column named for the air, and say so
    assert rec["ambient temperature during the test"] == (
        "20.5 to 22.0 °C (as stated, --ambient-c)the logs have no column named for the air (amb, room, air)"
    )
    # what the data covers: rows, first and last t_s (the test logs run 240 rows at 30 s)
    assert rec["data: the fit log"].startswith(
        "train.csv, 240 rows, t_s 0.0 s to 7170.0 s (1.99 h) on the log's own clock"
    )
    assert rec["data: the unseen day log"].startswith("unseen.csv, 240 rows, t_s 0.0 s to 7170.0 s (1.99 h)")
    assert "the file was last written 20" in rec["data: the fit log"]
    fitted = __import__("yaml").safe_load((reports / "model.yaml").read_text())["fit"]["fitted_at"]
    assert rec["model"].startswith(f"model.yaml, fitted {fitted[:10]} {fitted[11:19]} UTC by compd ")
    assert re.fullmatch(
        r"made \d{4}-\d\d-\d\d \d\d:\d\d UTC\S* by compd \S+ from fit\.json and replay\.json", rec["this report"]
    ), rec["this report"]
    assert "<title>compd commissioning report: DMU 50 s/n 1234 &lt;hall 2&gt;, xi_spindle on x1</title>" in text
    # the sign-off: both roles, name, date and signature left blank to sign on paper, and it says so
    sign = text.split('<section class="signoff">')[1]
    for role in ("Commissioning engineer", "Plant owner"):
        assert re.search(
            rf'<td class="role">{role}</td><td class="name"></td><td class="date"></td>'
            r'<td class="signature"></td>',
            sign,
        )
    assert "filled in by hand on the printed page" in sign
    assert "@page{size:A4" in text and "@media print" in text


def test_record_fields_not_given_are_explained_never_blank(reports, capsys):
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html"]) == 0
    err = capsys.readouterr().err
    assert err == (
        'compd: the record says "not given" for machine, operator, instrument, ambient-c'
        " (give --machine, --operator, --instrument, --ambient-c)\n"
    )
    text = (reports / "r.html").read_text()
    rec = record_rows(text)
    assert rec["machine"] == "not given (use --machine)"
    assert rec["operator (ran the test)"] == "not given (use --operator)"
    assert rec["measuring instrument"] == "not given (use --instrument)"
    assert rec["ambient temperature during the test"].startswith("not given (use --ambient-c)")
    # no cell blank, and no bare null, None, nan or inf anywhere before the sign-off
    assert all(c and c not in ("null", "None", "nan", "inf", "-") for c in cells(text))
    assert not re.search(r"\b(null|None)\b", text.split('<section class="signoff">')[0])


def test_empty_coefficients_and_figures_say_why(reports):
    """The fixture's ξ model has no speed input, so no lift and no radial output; its t0_c and xi_mm are
    empty too. A fit report figure that is not finite, or absent, says so."""
    model = __import__("yaml").safe_load((reports / "model.yaml").read_text())
    assert {k for k, v in model["params"].items() if v is None} >= {"t0_c", "xi_mm", "lift", "radial"}
    fit = json.loads((reports / "fit.json").read_text())
    fit["details"] = {"lag": {"held_out_rmse_um": {"0": 0.5, "60": float("inf")}, "kept": False}, "library_span": None}
    del fit["axes"]["x1"]["max_abs_err_um"]
    (reports / "fit2.json").write_text(json.dumps(fit))
    assert main(["report", "--fit", "fit2.json", "--replay", "replay.json", "--out", "r.html"]) == 0
    text = (reports / "r.html").read_text()
    rows = dict(re.findall(r'<tr><td class="l">([^<]*)</td><td class="l">(.*?)</td></tr>', text))

    def shown(name):
        return re.sub(r"<[^>]+>", "", rows[name])

    assert shown("t0_c").startswith("set when the daemon starts: the readings at start are the reference")
    assert shown("xi_mm").startswith("not recorded: where the ξ sensor sits is documentation only")
    assert shown("lift").startswith("not used: no centrifugal lift, the fit had no speed input")
    assert shown("radial").startswith("not used: no radial output")
    assert shown("lag.held_out_rmse_um.60") == "not computed: a fit of this choice failed on a held-out fold"
    assert shown("lag.held_out_rmse_um.0") == "0.5" and shown("lag.kept") == "no"
    assert shown("library_span").startswith("not used: the whole log is the sample library")
    assert "not in the fit report (written by an older compd)" in text  # the max |error| it lacks
    assert all(c and c not in ("null", "None", "nan", "inf", "-") for c in cells(text))


@pytest.mark.parametrize(
    "kind, params, nulls",
    [
        (
            "ar1",
            {"dt_s": 60.0, "c1": 0.98, "c2_exponent": None, "c3_um_per_k": None, "t0_c": None},
            {
                "c2_exponent": "not set: outside the C2 table",
                "c3_um_per_k": "not used by this ar1 model: no ambient input",
                "t0_c": "set when the daemon starts",
            },
        ),
        (
            "feed_axis",
            {
                "length_mm": 600.0,
                "chi_per_m": None,
                "eta": None,
                "u1_k": None,
                "u2_k": None,
                "slide_volume_m3": None,
                "field": {"slide_mm": [0.0, 600.0]},
                "position_poly": None,
                "power_w": None,
                "r_cu_ohm": None,
                "cooling_time_s": None,
                "ref_power_w": None,
                "linear_p0_mm": None,
            },
            {
                **dict.fromkeys(
                    (
                        "chi_per_m",
                        "eta",
                        "u1_k",
                        "u2_k",
                        "slide_volume_m3",
                        "power_w",
                        "r_cu_ohm",
                        "cooling_time_s",
                        "ref_power_w",
                    ),
                    "not used by the field form",
                ),
                "position_poly": "not used: the model is in the field form",
                "linear_p0_mm": "not used: the output is E",
            },
        ),
        (
            "feed_axis",
            {
                "length_mm": 600.0,
                "chi_per_m": 3.0,
                "slide_volume_m3": None,
                "field": None,
                "position_poly": None,
                "power_w": None,
                "r_cu_ohm": 0.5,
                "cooling_time_s": None,
                "ref_power_w": None,
            },
            {
                "slide_volume_m3": "not given: η is per m³",
                "field": "not used: the model is in the analytic form",
                "position_poly": "not used: the model is in the analytic form",
                "power_w": "not fixed: the motor loss comes from the current input",
                "cooling_time_s": "not used: no duty-cycle form",
                "ref_power_w": "not used: no duty-cycle form",
            },
        ),
        (
            "feed_axis",
            {"length_mm": 600.0, "field": None, "position_poly": {"degree": 2}, "eta": None},
            {
                "field": "not used: the model is in the position-regression form",
                "eta": "not used by the position-regression form",
            },
        ),
        (
            "mlr",
            {"t0_c": None, "rise_mean_k": None, "rise_cov_k2": None},
            {
                "t0_c": "set when the daemon starts",
                "rise_mean_k": "not recorded in the model file",
                "rise_cov_k2": "not recorded in the model file",
            },
        ),
        (
            "xi_spindle",
            {"radial": {"k_um_per_rpm2": None}},
            {"radial.k_um_per_rpm2": "not used: the lift is the model's `lift`"},
        ),
    ],
)
def test_every_empty_parameter_of_each_kind_is_explained_in_its_own_words(kind, params, nulls):
    from compd.commissioning.htmlreport import why_param_empty

    for name, words in nulls.items():
        assert why_param_empty(kind, name, params).startswith(words), (kind, name, why_param_empty(kind, name, params))
    # a key no rule knows still says what an empty value means, and where to read about it
    assert "docs/configuration.md, model: kind lvr, params" in why_param_empty("lvr", "something_new", {})


def test_a_log_on_unix_time_is_shown_as_dates_and_its_air_column_read(tmp_path):
    from datetime import UTC, datetime, timedelta, timezone

    from compd.commissioning.htmlreport import (
        LogFacts,
        Page,
        log_facts,
        make_record,
        record_section,
    )

    t = 1_767_225_600.0 + np.arange(3) * 3600.0  # 2026-01-01 00:00 UTC, hourly
    write_log(
        tmp_path / "day.csv",
        ["t_s", "T_room", "T1", "err_x_um"],
        np.column_stack([t, [19.5, 20.25, 21.0], [20, 21, 22], [0, 1, 2]]),
    )
    lf = log_facts("unseen day", {"log": "day.csv"}, str(tmp_path / "r.json"), "--replay")
    assert lf.rows == 3 and lf.ambient_c == {"T_room": (19.5, 21.0)} and not lf.why_not
    made = datetime(2026, 1, 2, 9, 30, tzinfo=timezone(timedelta(hours=1)))
    page = Page(
        {"kind": "mlr", "axes": {}},
        "fit.json",
        {"axes": {}},
        "r.json",
        model_why_not="no model here",
        record=make_record(ambient_c=[20.0], made_at=made),
        logs=[lf, LogFacts("fit", "gone.csv", why_not="not found (looked up as written)")],
    )
    text = record_section(page, made)
    assert "t_s 1767225600.0 s to 1767232800.0 s (2.00 h): 2026-01-01 00:00 UTC to 2026-01-01 02:00 UTC" in text
    assert "T_room read 19.5 to 21.0 °C in <code>day.csv</code> (unseen day)" in text
    assert "20.0 °C (as stated, --ambient-c)" in text
    assert '<code>gone.csv</code>: <span class="none">not found (looked up as written)</span>' in text
    assert "made 2026-01-02 09:30 UTC+01:00 by compd" in text
    assert '<span class="none">no model here</span>' in text
    assert datetime.fromtimestamp(t[0], UTC).year == 2026


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--operator", "  "], ["--operator", "empty"]),
        (["--machine", "DMU 50\nhall 2"], ["--machine", "one line"]),
        (["--instrument", "x" * 201], ["--instrument", "201 characters: at most 200"]),
        (["--ambient-c", "20", "21", "22"], ["--ambient-c", "3 values given"]),
        (["--ambient-c", "72"], ["--ambient-c", "72 °C is not the air of a shop"]),
        (["--ambient-c", "nan"], ["--ambient-c", "finite"]),
        (["--ambient-c"], ["--ambient-c", "expected at least one argument"]),
    ],
)
def test_bad_record_options_are_one_line_exit_2(reports, capsys, argv, words):
    try:  # argparse's own checks (a number, at least one) exit through SystemExit, compd's return 2
        rc = main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html", *argv])
    except SystemExit as e:
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    assert not (reports / "r.html").exists()
