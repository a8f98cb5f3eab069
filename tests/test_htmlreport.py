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
    assert main(["fit", "--kind", "xi_spindle", "--log", "train.csv", "--inputs", "T1", "--out", "model.yaml",
                 "--report", "fit.json"]) == 0
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
    assert len(pngs) == 2
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
    assert len(images(text)) == 1 and "mine.png" in text


def test_report_without_the_data_says_what_is_missing(reports, capsys):
    (reports / "unseen.csv").unlink()
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html"]) == 0
    captured = capsys.readouterr()
    assert "1 plots" in captured.out and "'unseen.csv' is not found" in captured.err
    assert len(images((reports / "r.html").read_text())) == 1


@pytest.mark.parametrize("which, content, words", [
    ("fit", "{\n  \"kind\": \"mlr\",\n  oops\n}\n", ["bad.json:3", "--fit", "not JSON"]),
    ("fit", "[1, 2]", ["bad.json", "--fit", "JSON object"]),
    ("fit", json.dumps({"axes": {"x1": {"rmse_um": 1.0}}}), ["bad.json", "kind"]),
    ("fit", json.dumps({"kind": "mlr", "axes": {"x1": {"rmse_um": "big"}}}), ["bad.json", "axes.x1.rmse_um"]),
    ("fit", json.dumps({"mlr": {"kind": "mlr"}, "ar1": {"kind": "ar1"}}), ["bad.json", "--kind all"]),
    ("fit", json.dumps({"kind": "mlr", "axes": {"x1": {"rmse_um": 1.0}},
                        "baseline_mlr": {"axes": {"x1": {"held_out_rmse_um": None}}}}),
     ["bad.json", "baseline_mlr.axes.x1.held_out_rmse_um"]),
    ("replay", json.dumps({"rows": 3}), ["bad.json", "axes", "compd replay --report"]),
    ("replay", json.dumps({"axes": {"z": {"rms_before_um": 1, "rms_after_um": 1, "reduction_pct": 0}}}),
     ["bad.json", "axes.z.max_abs_after_um", "missing"]),
    ("replay", "\xff\xfe", ["bad.json", "--replay"]),
])
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
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "r.html",
                 "--config", "nope.yaml"]) == 2
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
        [exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
         "--disable-extensions", "--user-data-dir=" + str(args[-1]) + ".profile", *args[:-1],
         "file://" + str(args[-1])],
        capture_output=True, timeout=120, check=False,
    )


def test_report_renders_in_headless_chromium(reports):
    exe = browser()
    if exe is None:
        pytest.skip("no headless Chromium here (Debian package chromium-headless-shell)")
    assert main(["report", "--fit", "fit.json", "--replay", "replay.json", "--out", "report.html"]) == 0
    page = reports / "report.html"
    dom = chromium(exe, "--dump-dom", page)
    assert dom.returncode == 0, dom.stderr.decode(errors="replace")[-2000:]
    html = dom.stdout.decode()
    assert "compd commissioning report" in html and html.count("<img") == 2 and "<table" in html
    shot = reports / "shot.png"
    run = chromium(exe, "--window-size=1200,2400", f"--screenshot={shot}", page)
    assert run.returncode == 0 and shot.exists(), run.stderr.decode(errors="replace")[-2000:]
    import matplotlib.image

    img = matplotlib.image.imread(shot)[..., :3]
    assert img.shape[:2] == (2400, 1200)
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
    assert "No held-out comparison with MLR: the held-out comparison could not fit a block: &lt;too few rows&gt;" in text
    assert "MLR baseline held-out RMSE" not in text
