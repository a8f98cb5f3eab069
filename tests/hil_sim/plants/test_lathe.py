"""Lathe (paper 001): magnitudes, Z = bed − spindle, speed dependence, ambient response."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.plants import PLANTS
from hil_sim.scenario import Scenario


def lathe(segments, ambient=None, **params):
    sc = Scenario.from_dict({"segments": segments, "ambient": ambient or {}, "seed": 3})
    return PLANTS.get("lathe")(sc, {"dt_s": 10.0, **params})


def test_signals_follow_the_paper_and_contract():
    p = lathe([{"duration_s": 600, "speed_rpm": 2000}])
    assert p.signal_names == ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "speed_rpm", "err_z_um"]
    assert p.axes == ("z",)
    p.advance_to(300)
    row = p.sample()
    assert row.shape == (9,)
    assert row[7] == 2000
    assert np.allclose(row[:7] * 10, np.round(row[:7] * 10))  # 0.1 °C transmitter


def test_twelve_hours_at_2000_rpm_like_the_paper():
    p = lathe([{"duration_s": 43200, "speed_rpm": 2000}])
    p.advance_to(43200)
    sp, bed = p.spindle_growth_um(), p.bed_growth_um()
    assert 20 < sp < 90  # spindle elongation: tens of µm
    assert 5 < bed < sp
    assert p.true_error_um()[0] == pytest.approx(bed - sp)
    rise = p.true_temperatures_c() - 20.0
    assert rise[0] > 5  # headstock front (bearing) warms most
    assert rise[0] > rise[2] > 0  # bed middle warms little
    # bed growth ≈ α L ΔT_mean over the 1.2 m to the saddle (the paper's 12 µm/K)
    x = p.net.x_m["bed"]
    mean_rise = np.mean(p.net.rise("bed")[x < 1.2])
    assert bed == pytest.approx(10e-6 * 1.2 * mean_rise * 1e6, rel=0.03)


def test_spindle_leads_then_bed_takes_over_after_stop():
    p = lathe([{"duration_s": 43200, "speed_rpm": 2000}, {"duration_s": 43200}])
    errs = []
    for t in range(0, 86401, 3600):
        p.advance_to(t)
        errs.append(p.true_error_um()[0])
    errs = np.array(errs)
    assert errs[4] < -5  # spindle growth dominates while running
    assert errs[-1] > errs[12] + 10  # the spindle cools fast, the bed slowly


def test_heating_grows_with_speed():
    rises = []
    for n in (1000, 1500, 2000):
        p = lathe([{"duration_s": 6000, "speed_rpm": n}])
        p.advance_to(6000)
        rises.append(p.true_temperatures_c()[1] - 20.0)  # T2 rear headstock, first 100 min
    assert 0 < rises[0] < rises[1] < rises[2]


def test_idle_machine_in_a_constant_shop_stays_put():
    p = lathe([{"duration_s": 7200}])
    p.advance_to(7200)
    assert np.allclose(p.net.T, 20.0)
    assert p.true_error_um()[0] == pytest.approx(0.0, abs=1e-9)


def test_uniform_ambient_rise_gives_the_net_expansion():
    """All at +ΔT: Z = (α_bed·1.2 m − α_sp·0.6 m)·ΔT = 4.8 µm/K."""
    p = lathe([{"duration_s": 30 * 86400}], ambient={"points": [[0, 0.0], [1, 2.0]]}, dt_s=300.0)
    p.advance_to(30 * 86400)
    assert np.allclose(p.net.T, 22.0, atol=1e-3)
    assert p.true_error_um()[0] == pytest.approx(4.8 * 2.0, rel=1e-3)


def test_correction_gives_the_residual():
    p = lathe([{"duration_s": 3600, "speed_rpm": 2000}])
    p.advance_to(3600)
    e = p.true_error_um()
    p.correction_um[:] = -e + 1.5
    assert p.residual_um()[0] == pytest.approx(1.5)
