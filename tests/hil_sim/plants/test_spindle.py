"""Motorized spindle (paper 003): ξ point, coolant, bearing rings, the radial error and the axial lift."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_sim.plants import PLANTS
from hil_sim.plants.spindle import centrifugal_thrust_n, preload_clearance_um, ring_displacement_um
from hil_sim.scenario import Scenario


def spindle(segments, **params):
    sc = Scenario.from_dict({"segments": segments, "seed": 5})
    return PLANTS.get("spindle")(sc, {"dt_s": 5.0, **params})


def test_signals_keep_the_demo_names():
    p = spindle([{"duration_s": 100, "speed_rpm": 10000}])
    names = p.signal_names
    for n in ("T_xi", "T_amb", "speed_rpm", "err_z_um", "err_radial_um", "T_brg_front", "T_coolant"):
        assert n in names
    assert names.index("speed_rpm") < names.index("err_z_um")
    assert p.axes == ("z", "radial")


def test_xi_point_gives_the_axial_growth_at_steady_state():
    """Mean-value theorem (paper 003 eq. 2): ΔL = α L [T(ξ) − T0] once the profile settles."""
    p = spindle([{"duration_s": 40 * 3600, "speed_rpm": 10000}])
    p.advance_to(40 * 3600)
    t_xi = p.net.at("rotor", p.xi_mm / 1000.0)
    predicted = 13.6e-6 * 165.0 * 1000.0 * (t_xi - 20.0)
    assert p.axial_um() > 10
    assert predicted == pytest.approx(p.axial_um(), rel=0.01)  # the growth; the error adds the lift
    assert p.true_error_um()[0] == pytest.approx(p.axial_um() + p.lift_um(), rel=1e-12)
    assert 0 < p.xi_mm < 165


def test_coolant_takes_heat_from_the_housing():
    dry = spindle([{"duration_s": 7200, "speed_rpm": 12000}])
    wet = spindle([{"duration_s": 7200, "speed_rpm": 12000, "coolant": True}])
    dry.advance_to(7200)
    wet.advance_to(7200)
    assert wet.net.rise("housing").mean() < 0.5 * dry.net.rise("housing").mean()
    assert wet.true_error_um()[0] < dry.true_error_um()[0]


def test_ring_displacement_of_a_uniform_ring_is_alpha_r_dt():
    for r, a, b in ((27.34, 25.0, 27.34), (37.66, 37.66, 40.0)):
        assert ring_displacement_um(r, a, b, np.full(9, 5.0), 12e-6, 0.26) == pytest.approx(
            12e-6 * r * 5.0 * 1000.0, rel=1e-9
        )


def test_preload_clearance_grows_with_axial_growth():
    assert preload_clearance_um(0.0, 10.319, 0.53, 18.0, 0.8) == pytest.approx(0.0)
    c = [preload_clearance_um(g, 10.319, 0.53, 18.0, 0.8) for g in (5.0, 10.0, 20.0)]
    assert 0 < c[0] < c[1] < c[2] < 20.0


def test_radial_error_rises_with_running_and_speed():
    p = spindle([{"duration_s": 3600, "speed_rpm": 6000}, {"duration_s": 3600, "speed_rpm": 14000}])
    p.advance_to(10)
    r0 = p.true_error_um()[1]
    p.advance_to(3590)
    r1 = p.true_error_um()[1]
    p.advance_to(7190)
    r2 = p.true_error_um()[1]
    assert r0 < r1 < r2


def test_sensors_are_realistic_and_one_drifts():
    p = spindle([{"duration_s": 36000}], noise_c=0.0)
    rows = p.record(np.array([0.0, 36000.0]))
    j = p.signal_names.index("T_brg_rear")
    others = [p.signal_names.index(n) for n in ("T_xi", "T_brg_front")]
    assert rows[1, j] - rows[0, j] == pytest.approx(0.2, abs=0.1)  # 0.02 °C/h for 10 h
    assert np.allclose(rows[1, others], rows[0, others])


def test_unknown_param_is_an_error():
    with pytest.raises(ValueError, match="unknown spindle plant param 'bogus'"):
        spindle([{"duration_s": 10}], bogus=1)
    with pytest.raises(ValueError, match="drift_sensor"):
        spindle([{"duration_s": 10}], drift_sensor="T_nowhere")


# --- centrifugal lift (paper 003 §3.4): axial, ∝ n² below the play the growth opened ---


def test_centrifugal_thrust_scales_with_speed_squared():
    f1 = centrifugal_thrust_n(5000.0, 18, 10.319, 65.0, 7850.0, 18.0)
    f2 = centrifugal_thrust_n(10000.0, 18, 10.319, 65.0, 7850.0, 18.0)
    assert f1 > 0
    assert f2 == pytest.approx(4.0 * f1, rel=1e-12)
    assert centrifugal_thrust_n(0.0, 18, 10.319, 65.0, 7850.0, 18.0) == 0.0
    # by hand: cage 0.5·ω·(1 − 10.319/65·cos 18°), ball 4.52 g on a 32.5 mm radius, ×18 tan 18°
    w = 0.5 * 10000 * math.pi / 30 * (1 - 10.319 / 65 * math.cos(math.radians(18)))
    m = 7850 * math.pi * 10.319e-3**3 / 6
    assert f2 == pytest.approx(18 * m * w**2 * 0.0325 * math.tan(math.radians(18)), rel=1e-12)


def test_lift_is_n_squared_below_the_play_and_bounded_by_it():
    p = spindle([{"duration_s": 40 * 3600, "speed_rpm": 6000}])
    p.advance_to(40 * 3600)  # warm: ~0.8·growth of play, far above the lift
    growth = p.axial_um()
    lift6 = p.lift_um()
    assert 0 < lift6 < 0.8 * growth
    p.segment().speed_rpm = 12000.0  # same thermal state, twice the speed
    assert p.lift_um() == pytest.approx(4.0 * lift6, rel=1e-12)
    stiff = spindle([{"duration_s": 40 * 3600, "speed_rpm": 6000}], axial_stiffness_n_per_um=1e-3)
    stiff.advance_to(40 * 3600)  # a soft bearing: the thrust would lift it by metres
    assert stiff.lift_um() == pytest.approx(0.8 * stiff.axial_um(), rel=1e-12)


def test_no_lift_before_the_growth_opens_any_play():
    p = spindle([{"duration_s": 3600, "speed_rpm": 15000}])
    assert p.axial_um() == pytest.approx(0.0, abs=1e-12)
    assert p.lift_um() == 0.0
    assert p.true_error_um()[0] == pytest.approx(0.0, abs=1e-12)


def test_lift_is_on_the_axial_error_not_the_radial():
    p = spindle([{"duration_s": 40 * 3600, "speed_rpm": 9000}])
    p.advance_to(40 * 3600)
    z, radial = p.true_error_um()
    assert z == pytest.approx(p.axial_um() + p.lift_um(), rel=1e-12)
    lift = p.lift_um()
    assert lift > 1.0
    p.segment().speed_rpm = 0.0  # same thermal state, stopped: radial unchanged, axial falls by the lift
    z0, radial0 = p.true_error_um()
    assert radial0 == pytest.approx(radial, rel=1e-12)
    assert z - z0 == pytest.approx(lift, rel=1e-9)
