"""Feed axis (paper 000): coefficients recovered, end-of-stroke reversal, evaluate = predict, Siemens reduction."""

from __future__ import annotations

import numpy as np
import pytest

from compd.identify import FITS
from compd.log import Log
from compd.models.feed_axis import (
    FeedAxis,
    FeedAxisParams,
    copper_loss_w,
    error_profile_um,
    error_um,
    heat_j,
    linear_reduction,
)

R_CU = 0.8
# A slide whose far support reverses the error near the end of the stroke.
TRUE = FeedAxisParams(
    length_mm=600,
    segments=30,
    chi_per_m=8.0,
    eta=0.2,
    u1_k=2.0,
    u2_k=-0.3,
    xi=1.0,
    r_cu_ohm=R_CU,
    input_roles=["position", "current"],
)


def _paper_runs(noise_um=0.0, seed=0):
    """Paper 000's procedure: five 15-min heating runs at 40 A, then a 0–600 mm sweep in 20 mm steps."""
    rows, t = [], 0.0
    for _ in range(5):
        for _ in range(90):
            rows.append([t, 300.0, 40.0])
            t += 10.0
        for y in np.arange(0.0, 601.0, 20.0):
            rows.append([t, y, 0.0])
            t += 1.0
    rows = np.asarray(rows)
    q = heat_j(rows[:, 0], copper_loss_w(rows[:, 2], R_CU, 0.0))
    e = error_um(rows[:, 0], q, rows[:, 1], TRUE)
    e = e + np.random.default_rng(seed).normal(0, noise_um, e.size)
    return Log("feed.csv", ["t_s", "pos_x_mm", "current_x_a", "err_x_um"], np.column_stack([rows, e])), e


def test_profile_shows_end_of_stroke_reversal():
    y, e = error_profile_um(4500.0, 3 * 40.0**2 * R_CU * 4500.0, TRUE)
    i = int(np.argmax(e))
    assert 0 < y[i] < 400 and e[i] - e[-1] > 2.0


def test_fit_recovers_known_coefficients():
    log, _ = _paper_runs()
    res = FITS.get(FeedAxis.kind)(log, None, None, r_cu_ohm=R_CU, length_mm=600)
    p = res.model.params
    assert res.report["converged"]
    assert p.eta == pytest.approx(0.2, rel=1e-3)
    assert p.u1_k == pytest.approx(2.0, rel=1e-3)
    assert p.u2_k == pytest.approx(-0.3, rel=1e-3)
    assert p.chi_per_m == pytest.approx(8.0, rel=1e-3)
    assert res.model.inputs == ["pos_x_mm", "current_x_a"]


def test_noisy_fit_follows_reversal_within_half_micron():
    log, e_true = _paper_runs(noise_um=0.1, seed=3)
    m = FITS.get(FeedAxis.kind)(log, None, None, r_cu_ohm=R_CU, length_mm=600).model
    pred = m.predict(log.matrix(m.inputs), log.t_s)[:, 0]
    rmse = float(np.sqrt(np.mean((pred - log.col("err_x_um")) ** 2)))
    assert rmse < 0.5
    q_end = 3 * 40.0**2 * R_CU * 4500.0
    y, fitted = error_profile_um(4500.0 + 31.0, q_end, m.params)
    _, true = error_profile_um(4500.0 + 31.0, q_end, TRUE)
    assert np.argmax(fitted) == np.argmax(true)
    assert np.max(np.abs(fitted - true)) < 0.5


def test_evaluate_matches_predict_and_resumes():
    log, _ = _paper_runs()
    X, t = log.matrix(["pos_x_mm", "current_x_a"]), log.t_s
    m = FeedAxis(TRUE, ["pos_x_mm", "current_x_a"], ["x"])
    P = FeedAxis(TRUE, m.inputs, m.outputs).predict(X, t)
    m.start(X[0], t[0])
    out = np.zeros(1)
    got = []
    for i in range(len(t)):
        m.evaluate(X[i], t[i], out)
        got.append(out[0])
    np.testing.assert_allclose(got, P[:, 0], atol=1e-9)
    m2 = FeedAxis(TRUE, m.inputs, m.outputs)
    m2.set_state(m.get_state(), elapsed_s=0.0)
    m2.start(X[-1], 10_000.0)
    m2.evaluate(X[-1], 10_000.0, out)
    assert out[0] == pytest.approx(got[-1], abs=1e-9)


def test_linear_reduction_is_least_squares_line():
    q = 3 * 40.0**2 * R_CU * 2700.0
    k0, tan_b, p0 = linear_reduction(2700.0, q, TRUE, p0_mm=300.0)
    y, e = error_profile_um(2700.0, q, TRUE)
    r = e - (k0 + tan_b * (y - p0))
    assert abs(r.sum()) < 1e-8 and abs((r * (y - p0)).sum()) < 1e-6


def test_copper_loss():
    assert copper_loss_w(10.0, 0.5, 0.004, 40.0, 20.0) == pytest.approx(3 * 100 * 0.5 * 1.08)
    assert copper_loss_w(10.0, 0.5, 0.004) == pytest.approx(150.0)


def test_needs_a_motor_loss():
    log, _ = _paper_runs()
    no_current = Log("f.csv", ["t_s", "pos_x_mm", "err_x_um"], log.data[:, [0, 1, 3]])
    from compd.core.errors import BadInput

    with pytest.raises(BadInput, match="power_w"):
        FITS.get(FeedAxis.kind)(no_current, None, None)
