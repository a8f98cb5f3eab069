"""ξ-point axial model (paper 003 Table 1) and the mean-value point tool."""

from __future__ import annotations

import numpy as np
import pytest

from compd.errors import BadInput
from compd.models.xi_spindle import XiSpindle, XiSpindleParams, axial_growth_um, find_xi

# paper 003, Table 1: T(ξ) °C → modelled ΔL µm (α = 13.6e-6 /K, L = 165 mm, T0 = 22.5 °C).
# The paper prints 18.50 for 30.7 °C; α L ΔT gives 18.40 (SPEC §3.3).
TABLE_1 = [
    (22.5, 0.0), (23.2, 1.57), (26.8, 9.65), (28.5, 13.46), (28.9, 14.36), (29.2, 15.03),
    (29.5, 15.71), (29.7, 16.16), (29.9, 16.61), (30.7, 18.40), (30.8, 18.63), (31.0, 19.07),
    (31.1, 19.30), (31.2, 19.52), (31.3, 19.75), (31.4, 19.97), (31.5, 20.20),
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
    with pytest.raises(BadInput, match="one input"):
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
