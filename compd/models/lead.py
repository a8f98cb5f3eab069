"""A sensor's lag compensated: each input's reading led by its lag through a low-pass (compd's form, beyond the papers).

A PT100 in a housing or a drilled hole follows the structure it measures with a lag,
T_s' = (T − T_s)/τ, τ from seconds to minutes. A model fed T_s predicts the error late by
about τ after every change of duty. Inverting the lag, T = T_s + τ dT_s/dt, would amplify
the sensor's noise without bound, so the derivative is taken through a second-order
low-pass of time constant τ_f:

    T̂ = (1 + τ s) / (1 + τ_f s)² · T_s        y1 = LP(T_s), y2 = LP(y1), T̂ = y2 + (τ/τ_f)(y1 − y2)

T̂ follows the structure with the lag 2 τ_f instead of τ, and the noise is attenuated at
high frequencies (the gain falls as 1/ω beyond 1/τ_f). Each step holds the newest
reading over the time since the last one and is exact for that held input, so the
loop's 2 ms cycles, a replay's rows and a batch prediction over a log give the same
T̂ at the same instants. The lags come from the fit (compd.identify.lag); a model's
params carry them per input (`lead_s`, `lead_filter_s`; 0 = no lead).
"""

from __future__ import annotations

import math

import numpy as np


class InputLead:
    """The lead of a model's inputs; stateful (the low-pass), one instance per model."""

    def __init__(self, lead_s: list[float], filter_s: list[float]) -> None:
        lead = np.asarray(lead_s, dtype=float)
        filt = np.asarray(filter_s, dtype=float)
        self.idx = np.flatnonzero(lead > 0)  # the inputs that are led
        self.idx_list = [int(i) for i in self.idx]
        self.ratio = [float(lead[i] / filt[i]) for i in self.idx_list]
        self.filter_s = [float(filt[i]) for i in self.idx_list]
        n = len(self.idx_list)
        self.y1 = [math.nan] * n
        self.y2 = [math.nan] * n
        self.t_s = math.nan
        self._out = np.zeros(lead.size)

    def reset(self) -> None:
        """Forget the low-pass (the next reading starts it: no lead until it has history)."""
        n = len(self.idx_list)
        self.y1 = [math.nan] * n
        self.y2 = [math.nan] * n
        self.t_s = math.nan

    def step(self, x: np.ndarray, t_s: float, good: np.ndarray | None = None) -> np.ndarray:
        """The inputs with the led ones replaced by T̂ (a buffer reused every call; no allocation).

        An input that is not finite (or not `good`) leaves its low-pass as it was and passes
        through unchanged; time that runs backwards steps nothing."""
        out = self._out
        np.copyto(out, x)
        dt = t_s - self.t_s if self.t_s == self.t_s else 0.0
        if dt < 0.0:
            dt = 0.0
        self.t_s = t_s
        for k, i in enumerate(self.idx_list):
            v = float(x[i])
            if v != v or (good is not None and not good[i]):
                continue
            y1, y2 = self.y1[k], self.y2[k]
            if y1 != y1:  # the first reading: the low-pass starts there, no lead yet
                self.y1[k] = self.y2[k] = v
                continue
            if dt > 0.0:
                h = dt / self.filter_s[k]
                a = math.exp(-h)
                # both stages exact for the reading held over dt (y1 relaxes exponentially to v)
                y2 = v + (y2 - v) * a + (y1 - v) * h * a
                y1 = v + (y1 - v) * a
                self.y1[k], self.y2[k] = y1, y2
            out[i] = y2 + self.ratio[k] * (y1 - y2)
        return out

    def filter(self, X: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """`step` over the rows of a log at once (vectorised), from this lead's state: (n × inputs)."""
        X = np.asarray(X, dtype=float)
        out = X.copy()
        if not self.idx_list or X.shape[0] == 0:
            return out
        t = np.asarray(t_s, dtype=float)
        prev = self.t_s if self.t_s == self.t_s else t[0]
        dt = np.maximum(np.diff(np.r_[prev, t]), 0.0)
        groups: dict[float, list[int]] = {}  # the inputs with one low-pass share its blocks: filtered together
        for k, f in enumerate(self.filter_s):
            groups.setdefault(f, []).append(k)
        for f, ks in groups.items():
            cols = [self.idx_list[k] for k in ks]
            v = X[:, cols]
            h = dt / f
            a = np.exp(-h)[:, None]
            y1_0 = np.array([self.y1[k] if self.y1[k] == self.y1[k] else v[0, j] for j, k in enumerate(ks)])
            y2_0 = np.array([self.y2[k] if self.y2[k] == self.y2[k] else v[0, j] for j, k in enumerate(ks)])
            # y1 = v + (y1 − v) a, i.e. y1_k = a y1_(k−1) + (1 − a) v_k
            y1 = _first_order(a, (1.0 - a) * v, y1_0)
            y1_prev = np.vstack([y1_0, y1[:-1]])
            # y2_k = a y2_(k−1) + (1 − a) v_k + (y1_(k−1) − v_k) h a
            y2 = _first_order(a, (1.0 - a) * v + (y1_prev - v) * h[:, None] * a, y2_0)
            out[:, cols] = y2 + np.array([self.ratio[k] for k in ks]) * (y1 - y2)
            for j, k in enumerate(ks):
                self.y1[k], self.y2[k] = float(y1[-1, j]), float(y2[-1, j])
        self.t_s = float(t[-1])
        return out


def _first_order(a: np.ndarray, c: np.ndarray, y0: float | np.ndarray) -> np.ndarray:
    """y_k = a_k y_(k−1) + c_k from y_(−1) = y0 (0 ≤ a_k ≤ 1), vectorised as a prefix scan, for one
    column c (n) or several with the same decay (c n × m, a n × 1, y0 per column).

    Each step is the affine map y ↦ a_k y + c_k; maps compose, (a, c) ∘ (a', c') = (a a', a c' + c),
    so log2(n) passes of whole-array products give every prefix (a doubling scan). Only
    products of decays ≤ 1 and sums of terms are formed: no division, whatever the steps' decay
    (a log step many times the filter's τ_f, which the lag search tries, is a row like any other)."""
    A = np.array(a, dtype=float)
    C = np.array(c, dtype=float)
    C[0] += A[0] * y0
    shift = 1
    n = C.shape[0]
    while shift < n:
        C[shift:] += A[shift:] * C[:-shift]
        A[shift:] *= A[:-shift]
        shift *= 2
    return C
