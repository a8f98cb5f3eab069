"""PT100 realism: class-A tolerance, noise, 0.1 °C quantization, optional drift."""

from __future__ import annotations

import numpy as np


class Pt100Bank:
    """A bank of PT100 sensors read through a transmitter.

    Each sensor gets a fixed offset within the class-A tolerance ±(0.15 + 0.002|T|) °C
    (drawn once, uniform over ±0.15 °C so it is within tolerance at any T), white
    noise of `noise_c` (1 σ) and quantization to `resolution_c`. `drift_c_per_h`
    makes chosen sensors drift linearly with time.
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
        self.offset_c = rng.uniform(-0.15, 0.15, n) if tolerance else np.zeros(n)
        self.noise_c = noise_c
        self.resolution_c = resolution_c
        self.drift_c_per_s = (
            np.zeros(n) if drift_c_per_h is None else np.asarray(drift_c_per_h, float) / 3600.0
        )

    def read(self, true_c: np.ndarray, t_s: float) -> np.ndarray:
        v = true_c + self.offset_c + self.drift_c_per_s * t_s
        if self.noise_c > 0:
            v = v + self.rng.normal(0.0, self.noise_c, v.shape)
        if self.resolution_c > 0:
            v = np.round(v / self.resolution_c) * self.resolution_c
        return v
