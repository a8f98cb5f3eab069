"""ξ-point spindle (paper 003): Table 1, ξ from a profile, radial rings, clearance, fit."""

from __future__ import annotations

import numpy as np
import pytest

from compd.core.errors import BadInput
from compd.identify import FITS
from compd.identify.xi_spindle import find_xi
from compd.log import Log
from compd.models.xi_spindle import (
    LiftParams,
    RadialParams,
    XiSpindle,
    XiSpindleParams,
    axial_clearance_um,
    axial_growth_um,
    clearance_um,
    inner_ring_um,
    lift_um,
    outer_ring_um,
    ring_displacement_um,
)


@pytest.mark.parametrize(
    "t_c, dl_um", [(23.2, 1.57), (26.8, 9.65), (28.5, 13.46), (29.9, 16.61), (30.7, 18.40), (31.5, 20.20)]
)
def test_table1_rows(t_c, dl_um):
    # paper 003 Table 1 (its 30.7 °C row prints 18.50, a typo for 18.40)
    assert round(float(axial_growth_um(t_c, 22.5, 13.6e-6, 165.0)), 2) == pytest.approx(dl_um, abs=0.006)


def test_find_xi_is_mean_value_point():
    x = np.linspace(0, 165, 34)
    t = 30 - 8 * x / 165
    xi = find_xi(x, t)
    assert xi == pytest.approx(82.5, abs=1e-9)
    with pytest.raises(BadInput):
        find_xi(x, np.full_like(x, 20.0))


def test_uniform_ring_reduces_to_alpha_r_dt():
    a, dt = 12e-6, 5.0
    nodes = np.linspace(25, 35, 11)
    for r in (25.0, 28.0, 35.0):
        assert ring_displacement_um(r, 25, 35, nodes, np.full(11, dt), a, 0.26) == pytest.approx(a * r * dt * 1e3)
    assert inner_ring_um(dt, dt, 25, 27.34, a, 0.26) == pytest.approx(a * 27.34 * dt * 1e3)
    assert outer_ring_um(dt, dt, 37.66, 40, a) == pytest.approx(a * 37.66 * dt * 1e3)


def test_linear_profile_closed_form_matches_numeric():
    nodes = np.linspace(25, 27.34, 201)
    dts = 3 + 2 * (nodes - 25) / 2.34
    num = ring_displacement_um(27.34, 25, 27.34, nodes, dts, 11.5e-6, 0.26)
    assert inner_ring_um(3, 5, 25, 27.34, 11.5e-6, 0.26) == pytest.approx(num, rel=1e-5)


def test_clearance():
    assert clearance_um(0.0, 10.319, 0.53) == 0.0
    c1, c2 = clearance_um(5.0, 10.319, 0.53), clearance_um(10.0, 10.319, 0.53)
    assert 0 < c1 < c2


def test_radial_evaluate_legacy_lift_on_the_radial_output():
    """radial.k_um_per_rpm2 (files written before the `lift` section) keeps its meaning: k n² uncapped on radial."""
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, radial=RadialParams(k_um_per_rpm2=1e-7))
    assert params.lift is None
    m = XiSpindle(params, ["T_xi", "T_in", "T_out", "speed_rpm"], ["z", "x"])
    m.start(np.array([22.5, 22.5, 22.5, 0.0]), 0.0)
    out = np.zeros(2)
    m.evaluate(np.array([26.8, 27.0, 25.0, 6000.0]), 1.0, out)
    rad = params.radial
    expect = (
        outer_ring_um(2.5, 2.5, rad.r_c_mm, rad.r_d_mm, rad.alpha_per_k)
        - inner_ring_um(4.5, 4.5, rad.r_a_mm, rad.r_b_mm, rad.alpha_per_k, rad.mu)
        + clearance_um(out[0], rad.d_w_mm, rad.f)
        + 1e-7 * 6000.0**2
    )
    assert out[0] == pytest.approx(9.6492, abs=1e-3)
    assert out[1] == pytest.approx(expect)
    with pytest.raises(BadInput):
        XiSpindle(params, ["T_xi"], ["z"])


def test_fit_axial_length():
    t = np.arange(100.0)
    T = 22.5 + 8 * (1 - np.exp(-t / 30))
    e = 13.6e-6 * 165e3 * (T - T[0])
    log = Log("x.csv", ["t_s", "T_xi", "err_z_um"], np.column_stack([t, T, e]))
    m = FITS.get(XiSpindle.kind)(log, None, None).model
    assert m.params.length_mm == pytest.approx(165.0)


def test_a_spindle_growing_toward_the_axis_minus_is_fitted_with_its_sign() -> None:
    """A vertical spindle growing down toward the table, logged in machine coordinates (Z+ away from
    the workpiece: the error is negative): fitted with axial_sign −1 and the same length, the lift
    on the same side; it was refused ("the error falls as T_xi rises")."""
    t = np.arange(200.0)
    T = 22.5 + 8 * (1 - np.exp(-t / 30))
    n = np.where(t < 100, 6000.0, 9000.0)
    growth = 13.6e-6 * 165e3 * (T - T[0])
    lift = np.minimum(2e-8 * n * n, 0.8 * growth)
    for sign in (1, -1):
        log = Log("x.csv", ["t_s", "T_xi", "speed_rpm", "err_z_um"], np.column_stack([t, T, n, sign * (growth + lift)]))
        res = FITS.get(XiSpindle.kind)(log, ["T_xi", "speed_rpm"], None)
        m = res.model
        assert m.params.axial_sign == sign and res.report["axial_sign"] == sign
        assert m.params.length_mm == pytest.approx(165.0, rel=1e-3)
        assert m.params.lift.k_um_per_rpm2 == pytest.approx(2e-8, rel=1e-3)
        np.testing.assert_allclose(
            m.predict(log.matrix(["T_xi", "speed_rpm"]), t)[:, 0], sign * (growth + lift), atol=1e-6
        )


def test_the_xi_sensor_is_chosen_once_and_held_while_the_lag_is_searched(monkeypatch) -> None:
    """--inputs naming none: the ξ sensor is the column that predicts the held-out folds best, chosen
    once; the lag search refits with it held (it chose it again in every fold of every lag tried:
    35 s on an 8-hour day), and --option xi_sensor=COL names it."""
    from compd.identify import identify
    from compd.identify import xi_spindle as xs

    rng = np.random.default_rng(5)
    t = np.arange(0.0, 8 * 3600, 60.0)
    n = np.repeat([0.0, 6000, 0, 12000, 3000, 9000, 0, 15000], t.size // 8)
    heat = np.zeros(t.size)
    for k in range(1, t.size):
        heat[k] = heat[k - 1] + (2e-8 * n[k] ** 2 - heat[k - 1]) * 60 / 1500
    T_xi = 22 + heat + rng.normal(0, 0.02, t.size)
    T_amb = 20 + 0.3 * np.sin(t / 5000)
    err = 13.6e-6 * 165e3 * (T_xi - T_xi[0])
    log = Log("x.csv", ["t_s", "T_amb", "T_xi", "speed_rpm", "err_z_um"], np.column_stack([t, T_amb, T_xi, n, err]))
    calls = []
    real = xs._xi_sensor
    monkeypatch.setattr(xs, "_xi_sensor", lambda *a: calls.append(1) or real(*a))
    res = identify("xi_spindle", log, None, ["err_z_um"])
    assert res.model.inputs == ["T_xi", "speed_rpm"] and res.report["inputs_chosen"]["inputs"][0] == "T_xi"
    assert len(calls) == 1
    named = identify("xi_spindle", log, None, ["err_z_um"], xi_sensor="T_amb", lag="off")
    assert named.model.inputs == ["T_amb", "speed_rpm"] and len(calls) == 1
    with pytest.raises(BadInput, match="T_nope is not a column"):
        identify("xi_spindle", log, None, ["err_z_um"], xi_sensor="T_nope", lag="off")


# paper 003, Table 1: T(ξ) °C → modelled ΔL µm (α = 13.6e-6 /K, L = 165 mm, T0 = 22.5 °C).
# The paper prints 18.50 for 30.7 °C; α L ΔT gives 18.40.
TABLE_1 = [
    (22.5, 0.0),
    (23.2, 1.57),
    (26.8, 9.65),
    (28.5, 13.46),
    (28.9, 14.36),
    (29.2, 15.03),
    (29.5, 15.71),
    (29.7, 16.16),
    (29.9, 16.61),
    (30.7, 18.40),
    (30.8, 18.63),
    (31.0, 19.07),
    (31.1, 19.30),
    (31.2, 19.52),
    (31.3, 19.75),
    (31.4, 19.97),
    (31.5, 20.20),
]


def test_table_1_all_rows() -> None:
    assert len(TABLE_1) == 17
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165.0, t0_c=22.5)
    model = XiSpindle(params, ["T_xi"], ["z"])
    out = np.zeros(1)
    for t_c, dl_um in TABLE_1:
        model.evaluate(np.array([t_c]), 0.0, out)
        assert out[0] == pytest.approx(dl_um, abs=0.01)
        assert axial_growth_um(t_c, 22.5, 13.6e-6, 165.0) == pytest.approx(dl_um, abs=0.01)


def test_t0_taken_at_start_and_restored() -> None:
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165.0)
    model = XiSpindle(params, ["T_xi"], ["z"])
    out = np.zeros(1)
    model.start(np.array([22.5]), 0.0)
    model.evaluate(np.array([31.5]), 1.0, out)
    assert out[0] == pytest.approx(20.20, abs=0.01)
    again = XiSpindle(params, ["T_xi"], ["z"])
    again.set_state(model.get_state())
    again.start(np.array([25.0]), 0.0)  # restored T0 wins over the new first reading
    again.evaluate(np.array([31.5]), 1.0, out)
    assert out[0] == pytest.approx(20.20, abs=0.01)


def test_wiring_checked() -> None:
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165.0)
    with pytest.raises(BadInput, match="takes 1 inputs"):
        XiSpindle(params, ["a", "b"], ["z"])


def test_find_xi_linear_profile_is_the_middle() -> None:
    x = np.linspace(0, 165, 34)
    assert find_xi(x, 20 + 0.05 * x) == pytest.approx(82.5, abs=1e-9)


def test_find_xi_exponential_profile() -> None:
    x = np.linspace(0.0, 1.0, 2001)
    t = np.exp(-3 * x)
    xi = find_xi(x, t)
    mean = (1 - np.exp(-3)) / 3
    assert xi == pytest.approx(-np.log(mean) / 3, abs=1e-4)


def test_find_xi_rejects_constant_profile() -> None:
    with pytest.raises(BadInput, match="constant"):
        find_xi(np.array([0.0, 1.0, 2.0]), np.array([20.0, 20.0, 20.0]))


def _radial_log(k_um_per_rpm2: float | None, outer_gain: float = 1.0, inner_gain: float = 1.0) -> tuple[Log, XiSpindle]:
    """A synthetic spindle day whose errors are exactly the model's: the axial lift k, the ring gains."""
    t = np.arange(0.0, 4 * 3600.0, 60.0)
    speed = np.where((t // 1800) % 2 == 0, 9000.0, 3000.0)
    t_xi = 20.0 + 9.0 * (1 - np.exp(-t / 2400.0))
    t_out = 20.0 + 4.0 * (1 - np.exp(-t / 3000.0)) + 0.8 * np.sin(t / 2000.0) ** 2
    lift = None if k_um_per_rpm2 is None else LiftParams(k_um_per_rpm2=k_um_per_rpm2)
    truth = XiSpindle(
        XiSpindleParams(
            alpha_per_k=13.6e-6,
            length_mm=160.0,
            lift=lift,
            radial=RadialParams(inner_sensors=0, outer_gain=outer_gain, inner_gain=inner_gain),
        ),
        ["T_xi", "T_brg_front"] + ([] if lift is None else ["speed_rpm"]),
        ["z", "radial"],
    )
    X = np.column_stack([t_xi, t_out, speed])
    E = truth.predict(X[:, : len(truth.inputs)], t)
    cols = ["t_s", "T_xi", "T_brg_front", "speed_rpm", "err_z_um", "err_radial_um"]
    return Log("spindle.csv", cols, np.column_stack([t, X, E])), truth


def test_inner_ring_at_the_xi_sensor() -> None:
    """inner_sensors = 0: the inner ring takes the ξ sensor's rise (paper 003: ≈ the rotor journal)."""
    rad0 = RadialParams(inner_sensors=0, clearance=False)
    rad1 = RadialParams(inner_sensors=1, clearance=False)
    m0 = XiSpindle(XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, radial=rad0), ["T_xi", "T_o"], ["z", "r"])
    m1 = XiSpindle(XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, radial=rad1), ["T_xi", "T_i", "T_o"], ["z", "r"])
    out0, out1 = np.zeros(2), np.zeros(2)
    m0.start(np.array([20.0, 20.0]), 0.0)
    m1.start(np.array([20.0, 20.0, 20.0]), 0.0)
    m0.evaluate(np.array([26.0, 23.0]), 1.0, out0)
    m1.evaluate(np.array([26.0, 26.0, 23.0]), 1.0, out1)
    assert out0[1] == pytest.approx(out1[1])
    # a warmer inner ring closes the gap: the radial error falls below the outer ring's growth
    assert out0[1] < outer_ring_um(3.0, 3.0, rad0.r_c_mm, rad0.r_d_mm, rad0.alpha_per_k)


def test_fit_radial_recovers_the_lift() -> None:
    log, truth = _radial_log(8e-9)
    fit = FITS.get(XiSpindle.kind)(log, ["T_xi", "T_brg_front", "speed_rpm"], ["err_z_um", "err_radial_um"])
    m = fit.model
    assert m.outputs == ["z", "radial"]
    assert m.inputs == ["T_xi", "T_brg_front", "speed_rpm"]
    assert m.params.length_mm == pytest.approx(160.0)
    assert m.params.radial.inner_sensors == 0
    assert fit.report["k_um_per_rpm2"] == pytest.approx(8e-9, rel=1e-6)
    assert m.params.lift.k_um_per_rpm2 == pytest.approx(8e-9, rel=1e-6)
    assert m.params.lift.speed_input == "speed_rpm"
    assert m.params.radial.k_um_per_rpm2 is None  # the radial output carries no lift
    # the truth's rings are the paper's (gains 1): the fitted gains find that
    assert m.params.radial.outer_gain == pytest.approx(1.0, abs=1e-6)
    assert m.params.radial.inner_gain == pytest.approx(1.0, abs=1e-6)
    t = log.t_s
    X = log.data[:, 1:4]
    np.testing.assert_allclose(m.predict(X, t), truth.predict(X, t), atol=1e-6)


def test_fit_radial_without_speed_has_no_lift() -> None:
    log, _ = _radial_log(None)
    m = FITS.get(XiSpindle.kind)(log, ["T_xi", "T_brg_front"], ["err_z_um", "err_radial_um"]).model
    assert m.params.lift is None
    assert m.params.radial.k_um_per_rpm2 is None
    assert m.inputs == ["T_xi", "T_brg_front"]


def test_fit_radial_checks_its_inputs() -> None:
    log, _ = _radial_log(8e-9)
    with pytest.raises(BadInput, match="a radial fit takes"):
        FITS.get(XiSpindle.kind)(log, ["T_xi"], ["err_z_um", "err_radial_um"])
    with pytest.raises(BadInput, match="a radial fit takes"):
        FITS.get(XiSpindle.kind)(log, ["T_xi", "speed_rpm"], ["err_z_um", "err_radial_um"])
    with pytest.raises(BadInput, match="ring sensors"):
        FITS.get(XiSpindle.kind)(log, None, ["err_z_um", "err_radial_um"])
    with pytest.raises(BadInput, match="axial and radial"):
        FITS.get(XiSpindle.kind)(log, ["T_xi"], ["err_z_um", "err_radial_um", "err_z_um"])
    with pytest.raises(BadInput, match="name the ξ sensor first"):
        FITS.get(XiSpindle.kind)(log, ["speed_rpm"], ["err_z_um"])


# --- the ring gains: compd's form of the radial output (the paper's: both 1) ---


def test_ring_gains_scale_each_ring_term() -> None:
    paper = RadialParams(inner_sensors=0)
    gained = RadialParams(inner_sensors=0, outer_gain=0.7, inner_gain=0.6)
    assert (paper.outer_gain, paper.inner_gain) == (1.0, 1.0)  # files without the keys: the paper's form
    outs = []
    for rad in (paper, gained):
        m = XiSpindle(XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, radial=rad), ["T_xi", "T_o"], ["z", "r"])
        m.start(np.array([22.5, 22.5]), 0.0)
        out = np.zeros(2)
        m.evaluate(np.array([26.8, 25.0]), 1.0, out)
        outs.append(out)
    u_c = outer_ring_um(2.5, 2.5, 37.66, 40.0, 11.5e-6)
    u_b = inner_ring_um(4.3, 4.3, 25.0, 27.34, 11.5e-6, 0.26)
    c = clearance_um(outs[0][0], 10.319, 0.53)
    assert outs[0][1] == pytest.approx(u_c - u_b + c)
    assert outs[1][1] == pytest.approx(0.7 * u_c - 0.6 * u_b + c)
    assert outs[1][0] == outs[0][0]  # the axial output does not change


def test_fit_recovers_the_ring_gains_and_the_paper_form_fits_none() -> None:
    log, truth = _radial_log(8e-9, outer_gain=0.72, inner_gain=0.61)
    inputs, targets = ["T_xi", "T_brg_front", "speed_rpm"], ["err_z_um", "err_radial_um"]
    fit = FITS.get(XiSpindle.kind)(log, inputs, targets)
    rad = fit.model.params.radial
    assert rad.outer_gain == pytest.approx(0.72, abs=1e-6)
    assert rad.inner_gain == pytest.approx(0.61, abs=1e-6)
    assert fit.report["radial_form"] == "ring_gains"
    X, t = log.data[:, 1:4], log.t_s
    np.testing.assert_allclose(fit.model.predict(X, t)[:, 1], truth.predict(X, t)[:, 1], atol=1e-6)
    paper = FITS.get(XiSpindle.kind)(log, inputs, targets, ring_gains=False)
    assert (paper.model.params.radial.outer_gain, paper.model.params.radial.inner_gain) == (1.0, 1.0)
    assert paper.report["radial_form"] == "paper"
    # the truth is not the paper's form, so the unfitted rings miss by what the gains say
    miss = paper.model.predict(X, t)[:, 1] - log.data[:, 5]
    assert np.sqrt(np.mean(miss**2)) > 0.1


def test_ring_gains_are_never_negative() -> None:
    """A radial error that falls as the outer ring warms gives g_C = 0, not a negative gain."""
    log, _ = _radial_log(None, outer_gain=0.0, inner_gain=0.5)
    data = log.data.copy()
    data[:, 5] -= 0.3 * (data[:, 2] - data[0, 2])  # the radial error falls with T_brg_front
    bent = Log(log.file, log.columns, data)
    rad = FITS.get(XiSpindle.kind)(bent, ["T_xi", "T_brg_front"], ["err_z_um", "err_radial_um"]).model.params.radial
    assert rad.outer_gain == 0.0
    assert rad.inner_gain > 0.0


# --- centrifugal lift on the axial output, capped by the axial clearance (paper 003 §3.4) ---


def test_axial_clearance_is_the_share_of_growth_and_zero_when_shrinking() -> None:
    assert axial_clearance_um(10.0) == pytest.approx(8.0)
    assert axial_clearance_um(10.0, 0.5) == pytest.approx(5.0)
    assert axial_clearance_um(0.0) == 0.0
    assert axial_clearance_um(-4.0) == 0.0


@pytest.mark.parametrize("dl_um", [-3.0, 0.0, 0.5, 2.0, 10.0, 25.0])
@pytest.mark.parametrize("speed_rpm", [0.0, 3000.0, 9000.0, 20000.0])
def test_lift_never_exceeds_the_clearance(dl_um, speed_rpm) -> None:
    lift = lift_um(1e-7, speed_rpm, dl_um)
    assert 0.0 <= lift <= axial_clearance_um(dl_um) + 1e-15
    assert lift == pytest.approx(min(1e-7 * speed_rpm**2, 0.8 * max(dl_um, 0.0)))


def test_no_lift_while_no_clearance_is_open() -> None:
    assert lift_um(1e-7, 15000.0, 0.0) == 0.0
    assert lift_um(1e-7, 15000.0, -2.0) == 0.0


def _axial_lift_model(inputs: tuple[str, ...] = ("T_xi", "speed_rpm")) -> XiSpindle:
    """The axial-only model with the lift (what the demo runs): no radial output needed."""
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, lift=LiftParams(k_um_per_rpm2=1e-7))
    m = XiSpindle(params, list(inputs), ["z"])
    m.start(np.array([22.5 if n == "T_xi" else 0.0 for n in inputs]), 0.0)
    return m


def test_axial_only_model_carries_the_lift() -> None:
    m = _axial_lift_model()
    still, turning = np.zeros(1), np.zeros(1)
    m.evaluate(np.array([26.8, 0.0]), 1.0, still)
    m.evaluate(np.array([26.8, 6000.0]), 1.0, turning)
    dl = 9.6492  # Table 1 row 26.8 °C
    assert still[0] == pytest.approx(dl, abs=1e-3)
    assert turning[0] == pytest.approx(dl + 1e-7 * 6000.0**2, abs=1e-3)  # 3.6 µm < 0.8 ΔL = 7.7 µm
    # the speed input is found by its name, wherever it stands
    swapped = _axial_lift_model(("speed_rpm", "T_xi"))
    again = np.zeros(1)
    swapped.evaluate(np.array([6000.0, 26.8]), 1.0, again)
    assert again[0] == turning[0]
    assert swapped.t0_c == 22.5


def test_axial_lift_is_capped_by_the_clearance_the_growth_opened() -> None:
    m = _axial_lift_model()
    out = np.zeros(1)
    m.evaluate(np.array([23.2, 20000.0]), 1.0, out)  # k n² = 40 µm, ΔL = 1.57 µm
    dl = float(axial_growth_um(23.2, 22.5, 13.6e-6, 165.0))
    assert out[0] == pytest.approx(dl * 1.8)
    m.evaluate(np.array([22.5, 20000.0]), 1.0, out)  # cold: nothing open, nothing lifts
    assert out[0] == 0.0
    m.evaluate(np.array([22.0, 20000.0]), 1.0, out)  # shrunk: preload up, no lift
    assert out[0] == pytest.approx(float(axial_growth_um(22.0, 22.5, 13.6e-6, 165.0)))


def test_lift_goes_on_the_axial_output_not_the_radial() -> None:
    rad = RadialParams(inner_sensors=0)
    lifted = XiSpindle(
        XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, lift=LiftParams(k_um_per_rpm2=1e-7), radial=rad),
        ["T_xi", "T_o", "speed_rpm"],
        ["z", "r"],
    )
    plain = XiSpindle(XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, radial=rad), ["T_xi", "T_o"], ["z", "r"])
    lifted.start(np.array([22.5, 22.5, 0.0]), 0.0)
    plain.start(np.array([22.5, 22.5]), 0.0)
    a, b = np.zeros(2), np.zeros(2)
    lifted.evaluate(np.array([26.8, 24.0, 6000.0]), 1.0, a)
    plain.evaluate(np.array([26.8, 24.0]), 1.0, b)
    assert a[0] == pytest.approx(b[0] + 3.6)
    assert a[1] == b[1]


def test_lift_wiring_and_params_are_checked() -> None:
    params = XiSpindleParams(alpha_per_k=13.6e-6, length_mm=165, lift=LiftParams(k_um_per_rpm2=1e-7))
    with pytest.raises(BadInput, match="not among the model's inputs") as e:
        XiSpindle(params, ["T_xi", "n"], ["z"])
    assert e.value.path == "params.lift.speed_input"
    with pytest.raises(BadInput, match="takes 2 inputs"):
        XiSpindle(params, ["T_xi", "T_o", "speed_rpm"], ["z"])
    named = params.model_copy(update={"lift": LiftParams(k_um_per_rpm2=1e-7, speed_input="S1")})
    assert XiSpindle(named, ["T_xi", "S1"], ["z"]).inputs == ["T_xi", "S1"]
    with pytest.raises(ValueError, match="cannot both be set"):
        XiSpindleParams(
            alpha_per_k=13.6e-6,
            length_mm=165,
            lift=LiftParams(k_um_per_rpm2=1e-7),
            radial=RadialParams(k_um_per_rpm2=1e-7),
        )
    with pytest.raises(ValueError, match="same bearings"):
        XiSpindleParams(
            alpha_per_k=13.6e-6,
            length_mm=165,
            lift=LiftParams(k_um_per_rpm2=1e-7, preload_share=0.7),
            radial=RadialParams(),
        )
    with pytest.raises(ValueError):
        LiftParams(k_um_per_rpm2=-1e-9)


def test_older_model_file_keeps_its_radial_lift(tmp_path) -> None:
    """A model file as `compd fit` wrote it before the `lift` section: k under radial, no gains,
    the speed last. It loads, means k n² uncapped on the radial output, and writes back as it was."""
    from compd.commissioning.fitting import load_model

    f = tmp_path / "old.yaml"
    f.write_text(
        "kind: xi_spindle\ninputs: [T_xi, T_brg_front, speed_rpm]\noutputs: [z, radial]\n"
        "params:\n  alpha_per_k: 1.36e-05\n  length_mm: 165.0\n  t0_c: 22.5\n  xi_mm: null\n"
        "  radial:\n    r_a_mm: 25.0\n    r_b_mm: 27.34\n    r_c_mm: 37.66\n    r_d_mm: 40.0\n"
        "    alpha_per_k: 1.15e-05\n    mu: 0.26\n    d_w_mm: 10.319\n    f: 0.53\n    contact_deg: 18.0\n"
        "    preload_share: 0.8\n    clearance: true\n    inner_sensors: 0\n    outer_sensors: 1\n"
        "    k_um_per_rpm2: 2.0e-08\n"
        "fit: {rows: 10}\n"
    )
    m = load_model(f)
    assert m.params.lift is None
    assert (m.params.radial.outer_gain, m.params.radial.inner_gain) == (1.0, 1.0)
    m.start(np.array([22.5, 22.5, 0.0]), 0.0)
    out = np.zeros(2)
    m.evaluate(np.array([26.8, 24.0, 12000.0]), 1.0, out)
    dl = 13.6e-6 * 165.0 * 1000.0 * 4.3
    assert out[0] == pytest.approx(dl)  # no lift on the axial output, however fast it turns
    expect = (
        outer_ring_um(1.5, 1.5, 37.66, 40.0, 11.5e-6)
        - inner_ring_um(4.3, 4.3, 25.0, 27.34, 11.5e-6, 0.26)
        + clearance_um(dl, 10.319, 0.53)
        + 2.0e-8 * 12000.0**2
    )
    assert out[1] == pytest.approx(expect)
    assert out[1] == pytest.approx(4.5749, abs=1e-3)  # of which k n² = 2.88 µm
    assert m.to_dict()["params"]["radial"]["k_um_per_rpm2"] == 2.0e-08


def test_fit_axial_only_with_the_speed_fits_the_lift() -> None:
    """--inputs T_xi speed_rpm with one target: the lift is fitted, no radial output needed."""
    log, truth = _radial_log(1e-7)
    axial = Log(log.file, log.columns[:5], log.data[:, :5])
    fit = FITS.get(XiSpindle.kind)(axial, ["T_xi", "speed_rpm"], ["err_z_um"])
    m = fit.model
    assert m.outputs == ["z"] and m.params.radial is None
    assert m.inputs == ["T_xi", "speed_rpm"]
    assert m.params.lift.k_um_per_rpm2 == pytest.approx(1e-7, rel=1e-6)
    assert m.params.length_mm == pytest.approx(160.0, rel=1e-9)
    X = axial.data[:, 1:4:2]
    np.testing.assert_allclose(m.predict(X, axial.t_s)[:, 0], axial.data[:, 4], atol=1e-8)
    # the speed named otherwise: --option speed_input=COL
    renamed = Log(axial.file, ["t_s", "T_xi", "T_brg_front", "S1", "err_z_um"], axial.data)
    m2 = FITS.get(XiSpindle.kind)(renamed, ["T_xi", "S1"], ["err_z_um"], speed_input="S1").model
    assert m2.params.lift.speed_input == "S1"
    assert m2.params.lift.k_um_per_rpm2 == pytest.approx(1e-7, rel=1e-6)
    with pytest.raises(BadInput, match="speed_input=COL"):
        FITS.get(XiSpindle.kind)(renamed, ["T_xi", "S1"], ["err_z_um"])
    # without the speed, no lift: the axial fit alone, as before
    assert FITS.get(XiSpindle.kind)(axial, ["T_xi"], ["err_z_um"]).model.params.lift is None


def test_model_file_round_trip_keeps_the_lift() -> None:
    m = _axial_lift_model()
    d = m.to_dict()
    assert d["params"]["lift"] == {"k_um_per_rpm2": 1e-7, "speed_input": "speed_rpm", "preload_share": 0.8}
    back = XiSpindle(XiSpindleParams.model_validate(d["params"]), d["inputs"], d["outputs"])
    assert back.params == m.params


def test_fit_recovers_k_where_the_cap_binds() -> None:
    """k = 1e-7: 8.1 µm at 9000 rpm, more than the 0.8 ΔL open during the warm-up."""
    log, truth = _radial_log(1e-7)
    X = log.data[:, 1:4]
    dl = 13.6e-6 * 160.0 * 1000.0 * (X[:, 0] - X[0, 0])  # the truth's thermal growth
    fit = FITS.get(XiSpindle.kind)(log, ["T_xi", "T_brg_front", "speed_rpm"], ["err_z_um", "err_radial_um"])
    assert fit.report["k_um_per_rpm2"] == pytest.approx(1e-7, rel=1e-6)
    assert fit.model.params.length_mm == pytest.approx(160.0, rel=1e-9)
    capped = 1e-7 * X[:, 2] ** 2 > 0.8 * dl  # rows where the truth's lift is its cap
    assert 5 <= capped.sum() < len(capped) // 2
    np.testing.assert_allclose(fit.model.predict(X, log.t_s), truth.predict(X, log.t_s), atol=1e-6)


def test_fit_of_an_uncapped_k_would_be_worse() -> None:
    """The fit respects the bound: least squares of k n² without the cap misses the truth."""
    log, _ = _radial_log(1e-7)
    X, e = log.data[:, 1:4], log.data[:, 4]
    rise = X[:, 0] - X[0, 0]
    A = np.column_stack([rise, X[:, 2] ** 2])
    g, k = np.linalg.lstsq(A, e, rcond=None)[0]
    assert abs(k - 1e-7) > 1e-9


def test_compd_fit_with_the_speed_compares_with_mlr_on_the_temperatures() -> None:
    """`compd fit --kind all` keeps xi_spindle when the inputs are the ξ sensor and the speed,
    and the held-out MLR baseline regresses on the temperature rises only (SPEC §3.5)."""
    from compd.commissioning import fitting

    log, _ = _radial_log(1e-7)
    assert fitting.applicable("xi_spindle", log, ["T_xi", "speed_rpm"], {}) is None
    assert fitting.applicable("xi_spindle", log, ["T_xi", "T_brg_front"], {}) is not None
    oc = fitting.fit_model("xi_spindle", log, ["T_xi", "T_brg_front", "speed_rpm"], ["err_z_um", "err_radial_um"], {})
    base = oc.report["baseline_mlr"]
    assert base["inputs"] == ["T_xi", "T_brg_front"]
    # the exact law, each speed predicted by a fit that never saw it (k from the other speeds)
    assert base["axes"]["z"]["held_out_rmse_um"] < 0.01 * base["axes"]["z"]["mlr_held_out_rmse_um"]
