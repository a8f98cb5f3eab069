"""The "worse than MLR" check compares held-out scores: forward-chained time blocks, the same inputs."""

from __future__ import annotations

import numpy as np
import pytest

import compd.fitting as fitting
from compd.log import Log

N = 300


def _log(err: np.ndarray, temp: np.ndarray) -> Log:
    t = np.arange(N, dtype=float) * 10.0
    other = 20.0 + 0.5 * np.sin(t / 500.0)
    return Log("day.csv", ["t_s", "T1", "T2", "err_x_um"], np.column_stack([t, temp, other, err]))


def test_a_fit_is_scored_on_blocks_after_its_training_rows(monkeypatch: pytest.MonkeyPatch) -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    log = _log(2.0 * (temp - 20.0), temp)
    seen: list[int] = []
    real = fitting.FITS.get("mlr")

    class Spy:
        def get(self, kind: str):  # noqa: ANN201
            def fit(train: Log, *a, **kw):  # noqa: ANN002, ANN003, ANN202
                seen.append(len(train))
                assert np.array_equal(train.data, log.data[: len(train)])  # a prefix, in time order
                return real(train, *a, **kw)

            return fit

    monkeypatch.setattr(fitting, "FITS", Spy())
    rmse = fitting.held_out_rmse("mlr", log, ["T1"], ["err_x_um"], {})
    assert seen == [100, 200]
    assert rmse[0] < 1e-9  # an exact linear law extrapolates exactly


def test_a_law_that_changes_later_shows_in_the_held_out_score() -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    err = 2.0 * (temp - 20.0)
    err[200:] += 3.0  # the last block: an offset the first two never showed
    rmse = fitting.held_out_rmse("mlr", _log(err, temp), ["T1"], ["err_x_um"], {})
    # blocks 2 and 3 are scored (200 rows), only block 3 (100 rows) is off by 3 um
    assert rmse[0] == pytest.approx(np.sqrt(100 * 9.0 / 200), rel=1e-6)


def test_the_report_names_method_and_inputs_and_warns_only_where_mlr_wins() -> None:
    temp = 20.0 + np.linspace(0.0, 8.0, N)
    log = _log(2.0 * (temp - 20.0) + 0.3 * np.sin(np.arange(N) / 3.0), temp)
    oc = fitting.fit_model("lvr", log, ["T1", "T2"], None, {})
    base = oc.report["baseline_mlr"]
    assert base["inputs"] == ["T1", "T2"] and "blocks" in base["method"]
    ours, mlr = base["axes"]["x"]["held_out_rmse_um"], base["axes"]["x"]["mlr_held_out_rmse_um"]
    worse = [w for w in oc.warnings if "worse than MLR" in w]
    assert bool(worse) == (ours > mlr)
    if worse:
        assert "(T1, T2)" in worse[0]
