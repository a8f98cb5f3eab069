"""Linear-motor feed axis (paper 000): moving heat, fixed supports, E(y) on the 20 mm grid."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.plants import PLANTS
from hil_sim.scenario import Scenario


def axis(segments, **params):
    sc = Scenario.from_dict({"segments": segments, "seed": 9})
    return PLANTS.get("feed_axis")(sc, params)


def test_signals_positions_and_currents():
    p = axis([{"duration_s": 30, "feed_mm_min": 6000}, {"duration_s": 30, "pos_mm": 250}])
    assert p.axes == ("y",)
    for n in ("T_motor", "T_amb", "pos_y_mm", "current_y_a", "err_y_um"):
        assert n in p.signal_names
    pos = []
    for t in range(1, 31):
        p.advance_to(t)
        pos.append(p.axis.pos_mm)
    assert min(pos) >= 0 and max(pos) <= 600 and max(pos) - min(pos) > 300
    moving_current = p.axis.current_a
    p.advance_to(60)
    assert p.axis.pos_mm == 250
    assert p.axis.current_a < moving_current


def test_profile_grid_and_error_at_the_current_position():
    p = axis([{"duration_s": 3600, "feed_mm_min": 6000}])
    p.advance_to(3600)
    prof = p.error_profile_um()
    assert p.profile_mm[0] == 0 and p.profile_mm[-1] == 600 and len(prof) == 31
    assert np.all(np.diff(p.profile_mm) == 20)
    here = p.true_error_um()[0]
    assert here == pytest.approx(float(p.error_profile_um(np.array([p.axis.pos_mm]))[0]))
    assert prof.max() > 1.0  # µm-level after an hour at 6 m/min


def test_rigid_supports_bring_the_base_error_back_to_zero_at_the_far_support():
    p = axis(
        [{"duration_s": 3600, "feed_mm_min": 6000, "stroke_mm": [0, 300]}],
        support_restraint=1.0,
        tool_offset_mm=0.0,
        stroke_offset_mm=100.0,
        base_length_mm=800.0,
        stroke_mm=[0.0, 700.0],
    )
    p.advance_to(3600)
    e = p.error_profile_um(np.array([0.0, 200.0, 699.999]))
    far = p.error_profile_um(np.array([700.0]))[0]
    assert far == pytest.approx(0.0, abs=1e-6)
    assert e[1] > e[0] > 0  # grows over the hot part, returns towards the far end


def test_end_of_stroke_reversal_with_the_default_supports():
    p = axis([{"duration_s": 5400, "feed_mm_min": 6000, "stroke_mm": [0, 400]}])
    p.advance_to(5400)
    prof = p.error_profile_um()
    k = int(np.argmax(prof))
    assert 0 < k < len(prof) - 1  # the maximum is inside the stroke
    assert prof[-1] < prof[k] - 0.3


def test_energy_balance_with_the_moving_source():
    """Copper loss + friction in = stored + convected (the explicit gap/rail exchange conserves heat)."""
    p = axis([{"duration_s": 1800, "feed_mm_min": 6000}, {"duration_s": 1800, "pos_mm": 100}])
    e0 = p.net.energy_j(20.0)
    q_in = q_out = 0.0
    while p.t_s < 3600:
        t_amb = p.ambient_c()
        p._step(p.segment(), t_amb)
        p.t_s += p.dt_s
        q_in += p._heat.sum() * p.dt_s
        q_out += p.net.reservoir_flux_w(np.array([t_amb])).sum() * p.dt_s
    stored = p.net.energy_j(20.0) - e0
    assert q_in > 0 and stored > 0.05 * q_in
    assert q_in == pytest.approx(stored + q_out, rel=1e-9)
