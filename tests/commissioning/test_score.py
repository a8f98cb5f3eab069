"""`compd score`: a fitted model on a day it has not seen, before/after per axis and the MLR baseline."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from compd.cli import main
from compd.log import write_log
from tests.conftest import ROOT

MODEL = """\
kind: mlr
inputs: [T1]
outputs: [x1]
params: {coef_um_per_k: [[2.0]], intercept_um: [0.0]}
"""


@pytest.fixture()
def day(tmp_path):
    """An unseen day: err = 2.1 (T1 − 20) µm, a model that says 2.0 (T1 − 20), blanks between probes."""
    t = np.arange(300) * 30.0
    T1 = 20 + 5 * (1 - np.exp(-t / 3000.0))
    T2 = 20 + 0.1 * np.sin(t / 900.0)
    err = 2.1 * (T1 - 20)
    err[1::7] = np.nan  # rows without a measurement are left out
    write_log(tmp_path / "day.csv", ["t_s", "T1", "T2", "err_x1_um"], np.column_stack([t, T1, T2, err]))
    (tmp_path / "model.yaml").write_text(MODEL)
    return tmp_path, T1, err


def test_score_prints_and_writes_before_after_and_baseline(day, capsys):
    d, T1, err = day
    rc = main(["score", str(d / "model.yaml"), "--log", str(d / "day.csv"), "--json", str(d / "s.json")])
    out, errout = capsys.readouterr()
    assert rc == 0, errout
    rep = json.loads((d / "s.json").read_text())
    ok = np.isfinite(err)
    e = err[ok]
    resid = e - 2.0 * (T1[ok] - 20)
    z = rep["axes"]["x1"]
    assert z["rows"] == int(ok.sum())
    assert z["rms_before_um"] == pytest.approx(math.sqrt(np.mean(e * e)), rel=1e-3)
    assert z["rms_after_um"] == pytest.approx(math.sqrt(np.mean(resid * resid)), rel=1e-3)  # the CSV keeps 6 digits
    assert z["max_abs_after_um"] == pytest.approx(np.max(np.abs(resid)), rel=1e-3)
    assert z["reduction_pct"] == pytest.approx(100 * (1 - z["rms_after_um"] / z["rms_before_um"]))
    base = rep["baseline_mlr"]
    assert base["inputs"] == ["T1"]  # the model's temperature inputs
    # err is exactly linear in T1: MLR fitted on the earlier blocks predicts the rest ~exactly,
    # better than a model with the wrong gain, and the command says so
    assert base["axes"]["x1"]["mlr_held_out_rmse_um"] < 1e-3
    assert base["axes"]["x1"]["model_rmse_um"] > 0.1
    assert "MLR baseline predicts this log better" in errout
    line = next(ln for ln in out.splitlines() if ln.startswith("axis x1: RMS"))
    assert f"{z['rms_before_um']:.2f} -> {z['rms_after_um']:.2f} um" in line
    assert f"reduction {z['reduction_pct']:.1f} %" in line


def _cli(*argv: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "compd", *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )


def test_score_bad_inputs_are_one_line_exit_2(day):
    d, _, _ = day
    write_log(d / "noerr.csv", ["t_s", "T1"], np.column_stack([np.arange(5.0), np.full(5, 20.0)]))
    (d / "broken.yaml").write_text("kind: mlr\ninputs: [T1\n")
    cases = {
        ("model.yaml", "--log", "noerr.csv"): ("noerr.csv", "err_x1_um"),
        ("broken.yaml", "--log", "day.csv"): ("broken.yaml",),
        ("nothere.yaml", "--log", "day.csv"): ("nothere.yaml",),
        ("model.yaml", "--log", "day.csv", "--json", "nope/s.json"): ("nope/s.json", "--json"),
    }
    for argv, names in cases.items():
        r = _cli("score", *argv, cwd=d)
        assert r.returncode == 2, (argv, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
        for name in names:
            assert name in r.stderr, (argv, r.stderr)
    assert not (d / "nope").exists()
