"""PT100 realism: class-A tolerance, noise, 0.1 °C quantization, optional drift."""

from __future__ import annotations

import numpy as np


class Pt100Bank:
    """A bank of PT100 sensors read through a transmitter.

    Each sensor gets a fixed error u·(0.15 + 0.002|T|) °C, u drawn once uniform in
    [−1, 1], so it stays within the IEC 60751 class-A tolerance at any T; white
    noise of `noise_c` (1 σ) and quantization to `resolution_c`. `drift_c_per_h`
    makes chosen sensors drift linearly with time. `read` takes one sample (n,) or a
    batch (rows × n) with `t_s` a column.
    """

    def __init__(
        self,
        n: int,
        rng: np.random.Generator,
        *,
        noise_c: float = 0.02,
        resolution_c: float = 0.1,
        tolerance: bool = True,
        drift_c_per_h: np.ndarray | None = None,
    ) -> None:
        self.rng = rng
        self.tolerance_u = rng.uniform(-1.0, 1.0, n) if tolerance else np.zeros(n)
        self.noise_c = noise_c
        self.resolution_c = resolution_c
        self.drift_c_per_s = (
            np.zeros(n) if drift_c_per_h is None else np.asarray(drift_c_per_h, float) / 3600.0
        )

    def read(self, true_c: np.ndarray, t_s: float | np.ndarray) -> np.ndarray:
        """Readings (°C) for true temperatures `true_c` at time `t_s`."""
        true_c = np.asarray(true_c, float)
        tol = self.tolerance_u * (0.15 + 0.002 * np.abs(true_c))
        v = true_c + tol + self.drift_c_per_s * np.asarray(t_s, float)
        if self.noise_c > 0:
            v = v + self.rng.normal(0.0, self.noise_c, v.shape)
        if self.resolution_c > 0:
            v = np.round(v / self.resolution_c) * self.resolution_c
        return v
