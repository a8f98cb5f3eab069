"""Feed axis, duty-cycle form: the slide cools with τ, no loss gives the paper's heat, τ is fitted."""

from __future__ import annotations

import numpy as np
import pytest

from compd.identify import FITS
from compd.log import Log
from compd.models.feed_axis import FeedAxis, FeedAxisParams, copper_loss_w, error_um, leaky_heat_j

R_CU = 0.8
P_40A = 3 * 40.0**2 * R_CU  # W at 40 A
PAPER = dict(
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
DUTY = FeedAxisParams(**PAPER, cooling_time_s=5400.0, ref_power_w=P_40A)


def _day(params: FeedAxisParams, seed: int = 0):
    """Heating runs of 40 min with 20 min stops, then a long stop: a working day at 10 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 12 * 3600.0, 10.0)
    on = ((t % 3600.0) < 2400.0) & (t < 8 * 3600.0)
    pos = np.where(on, 300.0 + 300.0 * np.sin(t / 60.0), 0.0)
    cur = np.where(on, 40.0, 0.0)
    q = leaky_heat_j(t, copper_loss_w(cur, R_CU, 0.0), params.cooling_time_s)
    e = error_um(t, q, pos, params) + rng.normal(0.0, 0.02, t.size)
    return Log("day.csv", ["t_s", "pos_x_mm", "current_x_a", "err_x_um"], np.column_stack([t, pos, cur, e]))


def test_without_loss_the_heat_is_the_papers_integral() -> None:
    t = np.arange(0.0, 5400.0, 10.0)
    p = np.where(t < 2700.0, P_40A, 0.0)
    np.testing.assert_allclose(leaky_heat_j(t, p, 1e12), leaky_heat_j(t, p, None), rtol=1e-6)
    # with a loss, a constant power settles at Q = P τ
    t_long = np.arange(0.0, 20 * 3600.0, 10.0)
    q = leaky_heat_j(t_long, np.full(t_long.size, P_40A), 3600.0)
    assert q[-1] == pytest.approx(P_40A * 3600.0, rel=1e-6)


def test_slide_cools_after_the_axis_stops() -> None:
    m = FeedAxis(DUTY, ["pos_x_mm", "current_x_a"], ["x"])
    out = np.zeros(1)
    x_on, x_off = np.array([450.0, 40.0]), np.array([450.0, 0.0])
    m.start(x_on, 0.0)
    for k in range(1, 541):  # 90 min of work
        m.evaluate(x_on, 10.0 * k, out)
    e_stop = out[0]
    for k in range(541, 541 + 8 * 540):  # then 8 τ at rest
        m.evaluate(x_off, 10.0 * k, out)
    assert abs(e_stop) > 0.5
    assert abs(out[0]) < 0.01 * abs(e_stop)
    # the paper's form has no loss: its error never comes back
    p = FeedAxis(FeedAxisParams(**PAPER), m.inputs, m.outputs)
    p.start(x_on, 0.0)
    for k in range(1, 541):
        p.evaluate(x_on, 10.0 * k, out)
    for k in range(541, 541 + 8 * 540):
        p.evaluate(x_off, 10.0 * k, out)
    assert abs(out[0]) > 0.5 * abs(e_stop)


def test_evaluate_matches_predict() -> None:
    log = _day(DUTY)
    X, t = log.matrix(["pos_x_mm", "current_x_a"]), log.t_s
    P = FeedAxis(DUTY, ["pos_x_mm", "current_x_a"], ["x"]).predict(X, t)[:, 0]
    m = FeedAxis(DUTY, ["pos_x_mm", "current_x_a"], ["x"])
    m.start(X[0], t[0])
    out = np.zeros(1)
    got = np.empty(t.size)
    for i in range(t.size):
        m.evaluate(X[i], t[i], out)
        got[i] = out[0]
    np.testing.assert_allclose(got, P, atol=1e-6)


def test_outage_cools_the_saved_heat() -> None:
    m = FeedAxis(DUTY, ["pos_x_mm", "current_x_a"], ["x"])
    m2 = FeedAxis(DUTY, m.inputs, m.outputs)
    m2.set_state({"heating_s": 3600.0, "heat_j": 1.0e6}, elapsed_s=5400.0)
    m2.start(np.array([0.0, 0.0]), 0.0)
    assert m2.heat_j == pytest.approx(1.0e6 * np.exp(-1.0), rel=1e-9)


def test_fit_recovers_cooling_time() -> None:
    res = FITS.get(FeedAxis.kind)(_day(DUTY, seed=1), None, None, r_cu_ohm=R_CU, length_mm=600, duty_cycle=True)
    p = res.model.params
    assert p.cooling_time_s == pytest.approx(5400.0, rel=0.05)
    assert p.ref_power_w == pytest.approx(P_40A)
    paper = FITS.get(FeedAxis.kind)(_day(DUTY, seed=1), None, None, r_cu_ohm=R_CU, length_mm=600).model
    log = _day(DUTY, seed=1)
    e = log.col("err_x_um")
    rms = {
        name: float(np.sqrt(np.mean((mm.predict(log.matrix(mm.inputs), log.t_s)[:, 0] - e) ** 2)))
        for name, mm in (("duty", res.model), ("paper", paper))
    }
    assert rms["duty"] < 0.05 < rms["paper"]


def test_cooling_time_needs_a_reference_power() -> None:
    with pytest.raises(ValueError, match="ref_power_w"):
        FeedAxisParams(**PAPER, cooling_time_s=3600.0)
