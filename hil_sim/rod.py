"""1-D finite-difference heat conduction in a rod with lateral convection (implicit Euler).

ρ c ∂T/∂t = λ ∂²T/∂x² − (2h/R)(T − T_amb) + q_v, insulated ends unless heat is put
in there. Implicit Euler is unconditionally stable; the step matrix is inverted once,
so a step is one small matrix-vector product.
"""

from __future__ import annotations

import numpy as np


class Rod:
    """A round rod cut into `n` nodes of length dx = L/n (node i at (i + ½)dx)."""

    def __init__(
        self,
        length_m: float,
        n: int,
        radius_m: float,
        *,
        conductivity_w_mk: float = 45.0,
        density_kg_m3: float = 7850.0,
        heat_capacity_j_kgk: float = 460.0,
        h_w_m2k: float = 30.0,
        dt_s: float = 1.0,
        t_init_c: float = 20.0,
    ) -> None:
        if n < 2:
            raise ValueError("a rod needs at least two nodes")
        self.length_m = length_m
        self.n = n
        self.dx_m = length_m / n
        self.radius_m = radius_m
        self.lam = conductivity_w_mk
        self.rho_c = density_kg_m3 * heat_capacity_j_kgk
        self.h = h_w_m2k
        self.dt_s = dt_s
        self.area_m2 = np.pi * radius_m**2
        self.x_m = (np.arange(n) + 0.5) * self.dx_m
        self.T = np.full(n, float(t_init_c))
        self.T_init = self.T.copy()
        self._build()

    @property
    def diffusivity_m2_s(self) -> float:
        return self.lam / self.rho_c

    @property
    def b_per_s(self) -> float:
        """Lateral convection rate b = 2h/(ρ c R) (paper 001)."""
        return 2.0 * self.h / (self.rho_c * self.radius_m)

    def _build(self) -> None:
        n, dx, dt = self.n, self.dx_m, self.dt_s
        a = self.diffusivity_m2_s
        A = np.zeros((n, n))
        k = a / dx**2
        for i in range(n):
            if i > 0:
                A[i, i - 1] += k
                A[i, i] -= k
            if i < n - 1:
                A[i, i + 1] += k
                A[i, i] -= k
        A -= np.eye(n) * self.b_per_s
        self._M = np.linalg.inv(np.eye(n) - dt * A)
        self._node_heat_k_per_j = 1.0 / (self.rho_c * self.area_m2 * dx)

    def step(self, t_amb_c: float, heat_w: np.ndarray | None = None) -> None:
        """Advance one dt with ambient `t_amb_c` and `heat_w` (W into each node)."""
        rhs = self.T + self.dt_s * self.b_per_s * t_amb_c
        if heat_w is not None:
            rhs = rhs + self.dt_s * heat_w * self._node_heat_k_per_j
        self.T = self._M @ rhs

    def growth_um(self, alpha_per_k: float) -> float:
        """Thermal growth α ∫ (T − T_init) dx, µm."""
        return float(alpha_per_k * np.sum(self.T - self.T_init) * self.dx_m * 1e6)

    def energy_j(self, t_ref_c: float) -> float:
        """Stored heat relative to a uniform `t_ref_c`."""
        return float(self.rho_c * self.area_m2 * self.dx_m * np.sum(self.T - t_ref_c))
