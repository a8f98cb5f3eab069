"""Physics of the FD rod against the analytic 1-D fin (paper 001's rod: R, λ, ρ, c, h)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_sim.rod import Rod

# paper 001 §2 (finite-element check of the AR(1) model)
R, LAM, RHO, C, H, L = 0.1, 50.0, 7850.0, 460.0, 55.0, 0.8
B = 2 * H / (RHO * C * R)  # b = 2h/(ρcR), 1/s


def rod(n: int = 80, dt_s: float = 1.0) -> Rod:
    return Rod(
        L, n, R, conductivity_w_mk=LAM, density_kg_m3=RHO, heat_capacity_j_kgk=C, h_w_m2k=H, dt_s=dt_s, t_init_c=20.0
    )


def test_b_matches_paper_formula():
    assert rod().b_per_s == pytest.approx(B)
    time_constant_s = 1 / B
    assert time_constant_s == pytest.approx(3283.0, rel=1e-3)


def test_steady_state_is_the_analytic_fin_with_a_heat_flux_end():
    """θ(x) = q cosh(m(L − x)) / (λ m sinh(mL)), m² = 2h/(λR), for −λθ'(0) = q, θ'(L) = 0."""
    q = 2000.0  # W/m² into the end x = 0
    r = rod(n=400, dt_s=1e7)
    heat = np.zeros(r.n)
    heat[0] = q * r.area_m2
    for _ in range(20):
        r.step(20.0, heat)
    m = math.sqrt(2 * H / (LAM * R))
    theta = q * np.cosh(m * (L - r.x_m)) / (LAM * m * math.sinh(m * L))
    assert np.max(np.abs((r.T - 20.0) - theta)) < 0.01 * theta[0]
    # hot end well above the cold end: the profile is not trivially flat
    assert theta[0] > 5 * theta[-1]


def test_energy_balance_over_a_run():
    """Heat put in = heat stored + heat convected, integrated over a varying run."""
    r = rod(n=40, dt_s=5.0)
    rng = np.random.default_rng(1)
    q_in = convected = 0.0
    stored0 = r.energy_j(20.0)
    g_node = H * 2 * math.pi * R * r.dx_m  # W/K per node
    for k in range(3000):
        t_amb = 20.0 + 2.0 * math.sin(k / 300.0)
        heat = np.zeros(r.n)
        heat[0] = 300.0 * (k % 700 < 400)
        heat[rng.integers(r.n)] += 50.0
        r.step(t_amb, heat)
        q_in += heat.sum() * r.dt_s
        convected += g_node * np.sum(r.T - t_amb) * r.dt_s  # implicit: at the new T
    stored = r.energy_j(20.0) - stored0
    assert q_in > 0 and abs(stored) > 0.01 * q_in
    assert q_in == pytest.approx(stored + convected, rel=1e-9)


def test_uniform_rod_cools_with_time_constant_one_over_b():
    r = rod(n=20, dt_s=2.0)
    r.T[:] = 30.0
    r.T_init[:] = 20.0
    t, theta = 0.0, [10.0]
    while theta[-1] > 10.0 / math.e:
        r.step(20.0)
        t += r.dt_s
        theta.append(float(np.mean(r.T) - 20.0))
    # interpolate the 1/e crossing
    f = (theta[-2] - 10.0 / math.e) / (theta[-2] - theta[-1])
    t_e = t - r.dt_s * (1 - f)
    assert t_e == pytest.approx(1 / B, rel=0.005)


def test_growth_follows_the_ar1_recursion_of_paper_001():
    """ΔL(k) = C1 ΔL(k−1) + C2, C1 = e^(−bΔτ), C2 = q α a/(λ b)(1 − e^(−bΔτ)) (paper 001)."""
    alpha, q, tau = 12e-6, 2000.0, 30.0
    r = rod(n=40, dt_s=1.0)
    heat = np.zeros(r.n)
    heat[0] = q * r.area_m2
    growth = [0.0]
    for _ in range(200):
        for _ in range(int(tau)):
            r.step(20.0, heat)
        growth.append(r.growth_um(alpha))
    g = np.array(growth)
    c1 = math.exp(-B * tau)
    a = LAM / (RHO * C)
    c2 = q * alpha * a / (LAM * B) * (1 - c1) * 1e6
    assert c1 == pytest.approx(0.9909, abs=1e-4)
    assert c2 == pytest.approx(0.1985, abs=1e-3)
    np.testing.assert_allclose(g[1:] - c1 * g[:-1], c2, rtol=0.01)
