"""Thermal network of coupled rods and lumped masses, stepped by implicit Euler.

Each node i has a heat capacity C_i (J/K); nodes exchange heat through conductances
G_ij (W/K: conduction along a rod λA/dx, bearings, joints, an air gap) and with
reservoirs r (ambient air, coolant) through G_ir:

    C_i dT_i/dt = Σ_j G_ij (T_j − T_i) + Σ_r G_ir (T_r − T_i) + Q_i

Implicit Euler, (C/dt + K + diag ΣG_r) T' = C/dt T + G_r T_r + Q, is unconditionally
stable and conserves energy exactly per step (heat in = stored + given to reservoirs,
with the reservoir flux taken at the new temperatures). The step matrix is inverted
once per operating mode (e.g. spindle speed, coolant on/off) and cached, so a step
is three small matrix-vector products.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable

import numpy as np


class Network:
    """Nodes, links and reservoirs; call `freeze()` once built, then `use()` and `step()`."""

    def __init__(self, dt_s: float, t_init_c: float) -> None:
        if not dt_s > 0:
            raise ValueError("dt_s must be > 0")
        self.dt_s = float(dt_s)
        self.t_init_c = float(t_init_c)
        self._cap: list[float] = []
        self._surface: list[float] = []
        self._links: list[tuple[int, int, float]] = []
        self.bodies: dict[str, np.ndarray] = {}
        self.x_m: dict[str, np.ndarray] = {}
        self.dx_m: dict[str, float] = {}
        # per mode: [M C/dt | M], M G_r, M, G_r  with M = (C/dt + K + diag ΣG_r)⁻¹
        self._modes: dict[Hashable, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._mode: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.T = np.zeros(0)
        self.T_init = np.zeros(0)
        self.K = np.zeros((0, 0))

    @property
    def n(self) -> int:
        return len(self._cap)

    def add_rod(
        self,
        name: str,
        length_m: float,
        n: int,
        *,
        area_m2: float,
        perimeter_m: float,
        conductivity_w_mk: float,
        density_kg_m3: float,
        heat_capacity_j_kgk: float,
    ) -> np.ndarray:
        """A prismatic rod of `n` cells of dx = L/n (cell i centred at (i + ½)dx), ends insulated.

        Returns the node indices. Each cell stores ρ c A dx, exchanges λA/dx with its
        neighbours and has a lateral surface P dx for convection.
        """
        if n < 2:
            raise ValueError(f"rod {name!r} needs at least two nodes")
        if min(length_m, area_m2, perimeter_m, conductivity_w_mk) <= 0:
            raise ValueError(f"rod {name!r}: length, area, perimeter and λ must be > 0")
        dx = length_m / n
        start = self.n
        idx = np.arange(start, start + n)
        self._cap += [density_kg_m3 * heat_capacity_j_kgk * area_m2 * dx] * n
        self._surface += [perimeter_m * dx] * n
        g = conductivity_w_mk * area_m2 / dx
        self._links += [(start + i, start + i + 1, g) for i in range(n - 1)]
        self.bodies[name] = idx
        self.x_m[name] = (np.arange(n) + 0.5) * dx
        self.dx_m[name] = dx
        return idx

    def add_mass(self, name: str, cap_j_k: float, surface_m2: float = 0.0) -> int:
        """A lumped mass (uniform temperature) of heat capacity `cap_j_k`; returns its index."""
        if not cap_j_k > 0:
            raise ValueError(f"mass {name!r}: heat capacity must be > 0")
        i = self.n
        self._cap.append(float(cap_j_k))
        self._surface.append(float(surface_m2))
        self.bodies[name] = np.array([i])
        return i

    def link(self, i: int, j: int, g_w_k: float) -> None:
        """A fixed conductance `g_w_k` between nodes i and j."""
        if i == j or g_w_k < 0:
            raise ValueError("a link joins two different nodes with g >= 0")
        self._links.append((int(i), int(j), float(g_w_k)))

    def freeze(self) -> None:
        """Build the conduction matrix K (W/K) and start every node at `t_init_c`."""
        n = self.n
        self.cap_j_k = np.asarray(self._cap, float)
        self.surface_m2 = np.asarray(self._surface, float)
        K = np.zeros((n, n))
        for i, j, g in self._links:
            K[i, i] += g
            K[j, j] += g
            K[i, j] -= g
            K[j, i] -= g
        self.K = K
        self.T = np.full(n, self.t_init_c)
        self.T_init = self.T.copy()
        self._modes.clear()

    def use(self, key: Hashable, g_res: Callable[[], np.ndarray]) -> np.ndarray:
        """Select the operating mode `key`; `g_res()` gives its (n × R) reservoir conductances.

        The step matrices are built on first use of a key and cached. Returns the
        mode's reservoir conductances.
        """
        mode = self._modes.get(key)
        if mode is None:
            g = np.asarray(g_res(), float)
            if g.ndim != 2 or g.shape[0] != self.n:
                raise ValueError(f"reservoir conductances must be ({self.n} × R)")
            a = np.diag(self.cap_j_k / self.dt_s + g.sum(axis=1)) + self.K
            m = np.linalg.inv(a)
            mode = (np.hstack([m * (self.cap_j_k / self.dt_s), m]), m @ g, m, g)
            if len(self._modes) > 256:
                self._modes.clear()
            self._modes[key] = mode
        self._mode = mode
        return mode[3]

    def step(self, t_res_c: np.ndarray, heat_w: np.ndarray | None = None) -> None:
        """Advance one dt with reservoir temperatures `t_res_c` and `heat_w` (W into each node)."""
        if self._mode is None:
            raise RuntimeError("call use() before step()")
        mcm, mg, _, _ = self._mode
        q = np.zeros(self.n) if heat_w is None else heat_w
        self.T = mcm @ np.concatenate((self.T, q)) + mg @ t_res_c

    def steady_state(self, g_res: np.ndarray, t_res_c: np.ndarray, heat_w: np.ndarray) -> np.ndarray:
        """The steady temperatures for constant inputs: (K + diag ΣG_r) T = G_r T_r + Q."""
        g = np.asarray(g_res, float)
        a = self.K + np.diag(g.sum(axis=1))
        return np.linalg.solve(a, g @ np.asarray(t_res_c, float) + heat_w)

    def reservoir_flux_w(self, t_res_c: np.ndarray) -> np.ndarray:
        """Heat flowing now from the nodes into each reservoir (W), for the current mode."""
        if self._mode is None:
            raise RuntimeError("call use() first")
        g = self._mode[3]
        return (g * (self.T[:, None] - np.asarray(t_res_c, float)[None, :])).sum(axis=0)

    def probe(self, body: str, x_m: float) -> np.ndarray:
        """Weights w over all nodes with w·T = the rod's temperature at `x_m` (linear interpolation)."""
        idx = self.bodies[body]
        w = np.zeros(self.n)
        w[idx] = _interp_weights(self.x_m[body], x_m)
        return w

    def energy_j(self, t_ref_c: float) -> float:
        """Stored heat Σ C_i (T_i − t_ref) (J)."""
        return float(np.dot(self.cap_j_k, self.T - t_ref_c))

    def rise(self, body: str) -> np.ndarray:
        """Temperature rise of a body's nodes over the start (K)."""
        idx = self.bodies[body]
        return self.T[idx] - self.T_init[idx]

    def growth_um(self, body: str, alpha_per_k: float, upto_m: float | None = None) -> float:
        """Free thermal growth α ∫ ΔT dx of a rod, from x = 0 to `upto_m` (whole rod if None), µm."""
        return float(alpha_per_k * integrate_cells(self.rise(body), self.dx_m[body], upto_m) * 1e6)

    def at(self, body: str, x_m: float) -> float:
        """Temperature of a rod at `x_m` (linear between cell centres)."""
        idx = self.bodies[body]
        return float(np.interp(x_m, self.x_m[body], self.T[idx]))


def _interp_weights(xs: np.ndarray, x: float) -> np.ndarray:
    """Weights over the points `xs` that linearly interpolate at `x` (held flat outside)."""
    w = np.zeros(xs.size)
    if x <= xs[0]:
        w[0] = 1.0
    elif x >= xs[-1]:
        w[-1] = 1.0
    else:
        k = int(np.searchsorted(xs, x)) - 1
        f = (x - xs[k]) / (xs[k + 1] - xs[k])
        w[k], w[k + 1] = 1.0 - f, f
    return w


def integrate_cells(values: np.ndarray, dx_m: float, upto_m: float | None = None) -> float:
    """∫_0^upto of a cell-wise constant profile (cells of width dx_m starting at 0)."""
    v = np.asarray(values, float)
    if upto_m is None:
        return float(v.sum() * dx_m)
    full = int(np.clip(upto_m // dx_m, 0, v.size))
    out = v[:full].sum() * dx_m
    if full < v.size:
        out += v[full] * (upto_m - full * dx_m)
    return float(out)


def cumulative_cells(values: np.ndarray, dx_m: float, x_m: np.ndarray) -> np.ndarray:
    """∫_0^x of a cell-wise constant profile at each x (vectorised `integrate_cells`)."""
    v = np.asarray(values, float)
    edges = np.concatenate([[0.0], np.cumsum(v) * dx_m])
    x = np.clip(np.asarray(x_m, float), 0.0, v.size * dx_m)
    k = np.minimum((x // dx_m).astype(int), v.size - 1)
    return edges[k] + v[k] * (x - k * dx_m)
