"""A model file with a NaN, an infinity, a number out of its physical range or an array of the
wrong shape is bad input (exit 2) wherever it is loaded, naming the file, the line and the key."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from compd.cli import main
from compd.core.config import load_yaml
from compd.core.errors import format_path
from compd.log import write_log
from tests.conftest import ROOT

NAN, INF = math.nan, math.inf

# (kind, fit arguments) — each kind fitted on the same small synthetic log
FITS = {
    "lvr": [],
    "mlr": [],
    "ar1": ["--target", "err_x1_um", "--inputs", "T1"],
    "feed_axis": ["--target", "err_x1_um", "--option", "form=analytic"],  # the paper form's keys below
    "xi_spindle": ["--target", "err_x1_um", "--inputs", "T1"],
}


def _set(path, value):
    def corrupt(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return corrupt


def _append(path, value):
    def corrupt(doc):
        node = doc
        for k in path:
            node = node[k]
        node.append(value)

    return corrupt


def _pop(path):
    def corrupt(doc):
        node = doc
        for k in path:
            node = node[k]
        node.pop()

    return corrupt


P = "params"
# (kind, what, corruption, the key path the message must name, words it must contain)
CASES = [
    ("lvr", "nan", _set((P, "coef_um_per_k", 1, 0), NAN), (P, "coef_um_per_k", 1, 0), "finite"),
    ("lvr", "inf", _set((P, "intercept_um", 1), INF), (P, "intercept_um", 1), "finite"),
    (
        "lvr",
        "shape",
        _append((P, "coef_um_per_k", 2), 1.0),
        (P, "coef_um_per_k", 2),
        "row 2 has 3 values, expected 2 (one per output)",
    ),
    ("lvr", "cov shape", _pop((P, "rise_cov_k2")), (P, "rise_cov_k2"), "expected 3 (one per input)"),
    ("lvr", "components", _set((P, "n_components"), 7), (P, "n_components"), "7 components from 3 inputs"),
    ("mlr", "nan", _set((P, "rise_mean_k", 0), NAN), (P, "rise_mean_k", 0), "finite"),
    ("mlr", "inf", _set((P, "coef_um_per_k", 0, 1), -INF), (P, "coef_um_per_k", 0, 1), "finite"),
    ("mlr", "shape", _set((P, "t0_c"), [20.0, 20.0]), (P, "t0_c"), "has 2 values, expected 3 (one per input)"),
    ("mlr", "range", _set((P, "coef_um_per_k", 2, 0), 1e6), (P, "coef_um_per_k", 2, 0), "less than or equal"),
    ("ar1", "nan", _set((P, "c1"), NAN), (P, "c1"), "finite"),
    ("ar1", "inf", _set((P, "bed_gain_um_per_k", 0), -INF), (P, "bed_gain_um_per_k", 0), "finite"),
    ("ar1", "shape", _set((P, "c2_table", 0), [1000.0]), (P, "c2_table", 0, 1), "missing"),
    ("ar1", "inputs", _set(("inputs",), ["speed_rpm"]), ("inputs",), "ar1 takes 2 inputs"),
    ("ar1", "C1 = 1", _set((P, "c1"), 1.0), (P, "c1"), "less than 1"),
    ("ar1", "dt 0", _set((P, "dt_s"), 0.0), (P, "dt_s"), "greater than 0"),
    ("feed_axis", "nan", _set((P, "chi_per_m"), NAN), (P, "chi_per_m"), "finite"),
    ("feed_axis", "inf", _set((P, "u1_k"), INF), (P, "u1_k"), "finite"),
    (
        "feed_axis",
        "shape",
        _set((P, "input_roles"), ["position", "current", "ambient"]),
        (P, "input_roles"),
        "3 roles (position, current, ambient) but the model has 2 inputs",
    ),
    ("feed_axis", "length", _set((P, "length_mm"), -900.0), (P, "length_mm"), "greater than 0"),
    ("feed_axis", "e^(χL)", _set((P, "chi_per_m"), 5000.0), (P, "chi_per_m"), "overflows"),
    ("xi_spindle", "nan", _set((P, "alpha_per_k"), NAN), (P, "alpha_per_k"), "finite"),
    ("xi_spindle", "inf", _set((P, "length_mm"), INF), (P, "length_mm"), "finite"),
    ("xi_spindle", "shape", _set(("outputs",), ["x1", "x2"]), ("outputs",), "1 output axes (axial), got 2"),
    ("xi_spindle", "radial nan", _set((P, "radial"), {"r_a_mm": NAN}), (P, "radial", "r_a_mm"), "finite"),
    ("xi_spindle", "alpha", _set((P, "alpha_per_k"), 0.5), (P, "alpha_per_k"), "less than 0.001"),
]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A synthetic log and one fitted model file per kind."""
    d = tmp_path_factory.mktemp("fitted")
    rng = np.random.default_rng(0)
    n = 300
    t = np.arange(n) * 30.0
    T = 20 + np.outer(1 - np.exp(-t / 3000), [3.0, 2.0, 1.0]) + rng.normal(0, 0.03, (n, 3))
    E = (T - T[0]) @ np.array([[2.0, 1.5], [1.0, -1.0], [0.5, 3.0]]) + rng.normal(0, 0.2, (n, 2))
    speed = np.where((t // 1800) % 2 == 0, 2000.0, 0.0)
    pos = 500 + 400 * np.sin(t / 200)
    cur = np.where(speed > 0, 10.0, 2.0)
    cols = ["t_s", "T1", "T2", "T3", "speed_rpm", "err_x1_um", "err_x2_um", "pos_x1_mm", "current_x1_a"]
    log = d / "log.csv"
    write_log(log, cols, np.column_stack([t, T, speed, E, pos, cur]))
    for kind, extra in FITS.items():
        assert main(["fit", "--kind", kind, "--log", str(log), "--out", str(d / f"{kind}.yaml"), *extra]) == 0
    return d


def _corrupt(fitted, tmp_path, kind, corrupt):
    doc = yaml.safe_load((fitted / f"{kind}.yaml").read_text())
    corrupt(doc)
    bad = tmp_path / "model.yaml"
    bad.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return bad


def _config(tmp_path, kind, model_file):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "loop: {clock: sim, period_s: 1.0}\n"
        "sources: [{kind: replay, name: log, path: log.csv}]\n"
        f"model: {{kind: {kind}, file: {model_file.name}}}\n"
        "sink: {kind: pci1756}\n",
        encoding="utf-8",
    )
    return cfg


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err
    return lines[0]


@pytest.mark.parametrize(("kind", "what", "corrupt", "key", "words"), CASES, ids=[f"{c[0]}-{c[1]}" for c in CASES])
def test_bad_model_file_is_exit_2_naming_file_line_key(fitted, tmp_path, capsys, kind, what, corrupt, key, words):
    bad = _corrupt(fitted, tmp_path, kind, corrupt)
    line = load_yaml(bad).line_of(key)
    where = f"{bad}:{line}: {format_path(key)}: "
    log = str(fitted / "log.csv")
    pred = tmp_path / "pred.csv"
    (tmp_path / "log.csv").write_bytes((fitted / "log.csv").read_bytes())
    cfg = _config(tmp_path, kind, bad)
    for argv in (
        ["predict", str(bad), "--log", log, "--out", str(pred)],
        ["replay", "--model", str(bad), "--log", log],
        ["replay", str(cfg), "--log", log],
        ["check-config", str(cfg)],
    ):
        rc = main(argv)
        err = _one_line(capsys.readouterr().err)
        assert rc == 2, (argv, err)
        assert where in err and words in err, (argv, err)
    assert not pred.exists()


def test_fitted_models_load_unchanged(fitted, tmp_path, capsys):
    """The ranges refuse no model that `compd fit` writes."""
    log = str(fitted / "log.csv")
    for kind in FITS:
        assert main(["predict", str(fitted / f"{kind}.yaml"), "--log", log, "--out", str(tmp_path / "p.csv")]) == 0


def test_nan_model_through_the_real_cli(fitted, tmp_path):
    """The case the audit found: a NaN coefficient, `compd predict` as a user runs it."""
    bad = _corrupt(fitted, tmp_path, "lvr", _set((P, "coef_um_per_k", 1, 0), NAN))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "compd",
            "predict",
            str(bad),
            "--log",
            str(fitted / "log.csv"),
            "--out",
            str(tmp_path / "pred.csv"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 2, proc.stderr
    line = _one_line(proc.stderr)
    assert f"model.yaml:{load_yaml(bad).line_of((P, 'coef_um_per_k', 1, 0))}: params.coef_um_per_k[1][0]:" in line
