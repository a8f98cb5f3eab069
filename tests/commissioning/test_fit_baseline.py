"""The "worse than MLR" check compares held-out scores: folds of the log, each hidden from its fit, the same inputs."""

from __future__ import annotations

import numpy as np
import pytest

import compd.commissioning.fitting as fitting
import compd.identify as identify_pkg
from compd.identify import holdout
from compd.log import Log

N = 300


def _log(err: np.ndarray, temp: np.ndarray) -> Log:
    t = np.arange(N, dtype=float) * 10.0
    other = 20.0 + 0.5 * np.sin(t / 500.0)
    return Log("day.csv", ["t_s", "T1", "T2", "err_x_um"], np.column_stack([t, temp, other, err]))


def test_each_fold_is_predicted_by_a_fit_that_never_saw_its_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    log = _log(2.0 * (temp - 20.0), temp)
    hidden: list[tuple[int, int]] = []
    real = fitting.FITS.get("mlr")

    class Spy:
        def get(self, kind: str, path: object = None):  # noqa: ANN201
            def fit(train: Log, *a, **kw):  # noqa: ANN002, ANN003, ANN202
                gone = np.flatnonzero(np.isnan(train.col("err_x_um")))
                hidden.append((int(gone[0]), int(gone[-1]) + 1))
                # every row's inputs stay (a model with memory runs through the fold); only its errors go
                assert np.array_equal(train.data[:, :3], log.data[:, :3])
                assert np.array_equal(np.delete(train.data, gone, axis=0), np.delete(log.data, gone, axis=0))
                return real(train, *a, **kw)

            return fit

    monkeypatch.setattr(identify_pkg, "FITS", Spy())
    rmse = fitting.held_out_rmse("mlr", log, ["T1"], ["err_x_um"], {})
    # no duty columns, no gaps: four stretches of equal length that cover the log
    assert hidden == [(0, 75), (75, 150), (150, 225), (225, 300)]
    assert rmse[0] < 1e-9  # an exact linear law predicts every fold exactly


def test_a_law_that_changes_in_one_fold_shows_in_the_held_out_score() -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    err = 2.0 * (temp - 20.0)
    err[225:] += 3.0  # the last fold: an offset the others never showed
    rmse = fitting.held_out_rmse("mlr", _log(err, temp), ["T1"], ["err_x_um"], {})
    # the same definition computed here: each quarter predicted by least squares on the other three
    sq = 0.0
    for lo in range(0, N, 75):
        keep = np.r_[0:lo, lo + 75 : N]
        A = np.column_stack([np.ones(N), temp - temp[0]])
        coef, *_ = np.linalg.lstsq(A[keep], err[keep], rcond=None)
        sq += float(np.sum((err[lo : lo + 75] - A[lo : lo + 75] @ coef) ** 2))
    assert rmse[0] == pytest.approx(np.sqrt(sq / N), rel=1e-9)
    assert rmse[0] > 1.0  # the change is seen, where an in-sample fit would smear it


def test_folds_follow_the_duty_and_the_days() -> None:
    t = np.arange(0.0, 24 * 3600, 60.0)
    speed = np.where((t >= 5 * 3600) & (t < 14 * 3600), 2000.0, 0.0)
    log = Log("d.csv", ["t_s", "speed_rpm", "T1", "err_z_um"], np.column_stack([t, speed, t * 0 + 20, t * 0]))
    cut, how = holdout.folds(log)  # one speed: stretches of time
    assert how == "duty" and cut[0][0][0] == 0 and cut[-1][-1][1] == len(t)
    edges = [f[0][0] for f in cut[1:]]
    # the equal-length edge at 6 h moves to the start of the run at 5 h; 12 h stays (no change near it)
    assert 300 in edges and 720 in edges
    two = Log("2d.csv", log.columns, np.vstack([log.data, log.data + [86400 + 7200, 0, 0, 0]]))
    cut, how = holdout.folds(two)
    assert how == "days" and cut == [[(0, len(t))], [(len(t), 2 * len(t))]]


def test_two_speeds_are_held_out_level_by_level() -> None:
    """A day at two speeds: each speed's runs, with the pauses after them, form one fold, so each
    speed is predicted by a fit that never saw it (as an unseen day's speeds are)."""
    t = np.arange(0.0, 24 * 3600, 60.0)
    h = t / 3600
    speed = np.select([(h >= 1) & (h < 4), (h >= 6) & (h < 9), (h >= 11) & (h < 14)], [2000.0, 3000.0, 2000.0], 0.0)
    log = Log("d.csv", ["t_s", "speed_rpm", "T1", "err_z_um"], np.column_stack([t, speed, t * 0 + 20, t * 0]))
    cut, how = holdout.folds(log)
    assert how == "levels"
    assert cut == [[(60, 360), (660, 1440)], [(360, 660)]]  # 2000 rpm: two runs to the next run or the end


def test_the_report_names_method_and_inputs_and_warns_only_where_mlr_wins() -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    log = _log(2.0 * (temp - 20.0) + 0.3 * np.sin(np.arange(N) / 3.0), temp)
    oc = fitting.fit_model("lvr", log, ["T1", "T2"], None, {})
    base = oc.report["baseline_mlr"]
    assert base["inputs"] == ["T1", "T2"] and "folds" in base["method"]
    ours, mlr = base["axes"]["x"]["held_out_rmse_um"], base["axes"]["x"]["mlr_held_out_rmse_um"]
    worse = [w for w in oc.warnings if "worse than MLR" in w]
    assert bool(worse) == (ours > mlr)
    if worse:
        assert "(T1, T2)" in worse[0]
