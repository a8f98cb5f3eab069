"""The thermal network: a rod in it behaves as Rod; energy is conserved; steady state."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_sim.network import Network, cumulative_cells, integrate_cells
from hil_sim.rod import Rod


def _round_rod(net: Network, name: str, n: int = 30) -> np.ndarray:
    r = 0.05
    return net.add_rod(
        name,
        0.6,
        n,
        area_m2=math.pi * r * r,
        perimeter_m=2 * math.pi * r,
        conductivity_w_mk=45.0,
        density_kg_m3=7850.0,
        heat_capacity_j_kgk=460.0,
    )


def test_a_rod_in_the_network_matches_rod():
    net = Network(2.0, 20.0)
    idx = _round_rod(net, "r")
    net.freeze()
    rod = Rod(0.6, 30, 0.05, h_w_m2k=25.0, dt_s=2.0, t_init_c=20.0)
    net.use("run", lambda: (25.0 * net.surface_m2)[:, None])
    heat = np.zeros(30)
    heat[0] = 40.0
    for k in range(500):
        t_amb = 20.0 + 0.001 * k
        rod.step(t_amb, heat)
        net.step(np.array([t_amb]), heat)
    np.testing.assert_allclose(net.T[idx], rod.T, atol=1e-9)
    assert net.growth_um("r", 12e-6) == pytest.approx(rod.growth_um(12e-6), rel=1e-9)


def build_two_bodies(dt_s: float = 5.0) -> tuple[Network, np.ndarray, np.ndarray, int]:
    net = Network(dt_s, 20.0)
    a = _round_rod(net, "a")
    b = net.add_rod(
        "b",
        1.0,
        20,
        area_m2=0.02,
        perimeter_m=0.6,
        conductivity_w_mk=50.0,
        density_kg_m3=7200.0,
        heat_capacity_j_kgk=500.0,
    )
    m = net.add_mass("m", 5000.0, 0.2)
    net.link(int(a[0]), int(b[3]), 4.0)
    net.link(int(a[-1]), m, 2.0)
    net.freeze()
    return net, a, b, m


def g_res(net: Network, h: float, coolant: bool, b: np.ndarray) -> np.ndarray:
    g = np.zeros((net.n, 2))
    g[:, 0] = h * net.surface_m2
    if coolant:
        g[b[5:10], 1] = 3.0
    return g


def test_energy_balance_with_links_reservoirs_and_mode_changes():
    net, a, b, m = build_two_bodies()
    e0 = net.energy_j(20.0)
    q_in = to_res = 0.0
    for k in range(4000):
        coolant = (k // 500) % 2 == 1
        h = 10.0 if k < 2000 else 18.0
        net.use((h, coolant), lambda h=h, coolant=coolant: g_res(net, h, coolant, b))
        t_res = np.array([20.0 + math.sin(k / 400.0), 17.0])
        heat = np.zeros(net.n)
        heat[a[0]] = 60.0 if k < 2500 else 0.0
        heat[m] = 10.0
        net.step(t_res, heat)
        q_in += heat.sum() * net.dt_s
        to_res += net.reservoir_flux_w(t_res).sum() * net.dt_s
    stored = net.energy_j(20.0) - e0
    assert q_in == pytest.approx(stored + to_res, rel=1e-9)
    assert abs(stored) > 1e-3 * q_in


def test_steady_state_is_where_stepping_ends():
    net, a, b, m = build_two_bodies()
    g = g_res(net, 10.0, True, b)
    heat = np.zeros(net.n)
    heat[a[0]] = 30.0
    ss = net.steady_state(g, np.array([20.0, 15.0]), heat)
    big = build_two_bodies(dt_s=1e6)[0]
    big.use("ss", lambda: g)
    for _ in range(200):
        big.step(np.array([20.0, 15.0]), heat)
    np.testing.assert_allclose(big.T, ss, atol=1e-6)
    # heat balance of the steady state: all input leaves through the reservoirs
    out = (g * (ss[:, None] - np.array([20.0, 15.0]))).sum()
    assert out == pytest.approx(30.0, rel=1e-9)


def test_probe_interpolates_a_rod():
    net, a, b, m = build_two_bodies()
    net.T[b] = 20.0 + net.x_m["b"] * 10.0  # linear profile 10 K/m
    for x in (0.2, 0.5, 0.73):
        assert net.probe("b", x) @ net.T == pytest.approx(20.0 + 10.0 * x)
        assert net.at("b", x) == pytest.approx(20.0 + 10.0 * x)


def test_cell_integrals():
    v = np.array([1.0, 2.0, 3.0, 4.0])
    assert integrate_cells(v, 0.5) == pytest.approx(5.0)
    assert integrate_cells(v, 0.5, 0.75) == pytest.approx(0.5 + 2.0 * 0.25)
    np.testing.assert_allclose(cumulative_cells(v, 0.5, np.array([0.0, 0.75, 2.0, 3.0])), [0.0, 1.0, 5.0, 5.0])


def test_bad_network_inputs():
    net = Network(1.0, 20.0)
    with pytest.raises(ValueError):
        net.add_rod("x", 1.0, 1, area_m2=1, perimeter_m=1, conductivity_w_mk=1, density_kg_m3=1, heat_capacity_j_kgk=1)
    with pytest.raises(ValueError):
        net.add_mass("m", 0.0)
    with pytest.raises(RuntimeError):
        net.freeze()
        net.step(np.array([20.0]))
