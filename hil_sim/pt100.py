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
        self.drift_c_per_s = np.zeros(n) if drift_c_per_h is None else np.asarray(drift_c_per_h, float) / 3600.0

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


class SensorLag:
    """First-order lag of each sensor element behind the structure it measures.

    T_s' = (T − T_s)/τ_s, stepped exactly for an input held over the step:
    T_s ← T_s + (1 − e^(−dt/τ_s)) (T − T_s), so a step of T reaches 63 % at τ_s whatever
    the step. An element with τ_s = 0 is not lagged: the plant reads its point directly.
    """

    def __init__(self, lag_s: np.ndarray, dt_s: float, start_c: np.ndarray) -> None:
        lag = np.asarray(lag_s, float)
        if np.any(~np.isfinite(lag)) or np.any(lag < 0):
            raise ValueError("sensor lags must be finite and >= 0 s")
        self.lag_s = lag
        self.lagged = lag > 0
        # the share of the gap closed per step (1 where there is no lag)
        self.gain = np.where(lag > 0, -np.expm1(-dt_s / np.where(lag > 0, lag, 1.0)), 1.0)
        self.state_c = np.array(start_c, float)

    def step(self, target_c: np.ndarray) -> None:
        """One plant step with the element's surroundings at `target_c`."""
        self.state_c += self.gain * (target_c - self.state_c)
