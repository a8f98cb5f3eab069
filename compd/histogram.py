"""A fixed-size duration histogram (1 µs bins) for timing I/O threads without allocation."""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np


def bin_percentiles(bins: Any, qs: Sequence[float]) -> list[float]:
    """Bin indices (µs) at which the cumulative count first reaches q·total; 0 when empty.

    `bins` is an int64 array (array("q") or numpy); numpy keeps a 20 000-bin pass ≈ 50 µs.
    """
    counts = bins if isinstance(bins, np.ndarray) else np.frombuffer(bins, dtype=np.int64)
    cum = np.cumsum(counts)
    total = cum[-1] if cum.size else 0
    if total == 0:
        return [0.0 for _ in qs]
    return [float(np.searchsorted(cum, q * total, side="left")) for q in qs]


class DurationHist:
    """Counts durations in 1 µs bins up to `max_us` (the last bin holds everything above)."""

    def __init__(self, max_us: int = 20000) -> None:
        self.bins = array("q", bytes(8 * max_us))
        self.count = 0
        self.max_ns = 0

    def add_ns(self, d_ns: int) -> None:
        us = d_ns // 1000
        n = len(self.bins)
        self.bins[us if us < n else n - 1] += 1
        self.count += 1
        if d_ns > self.max_ns:
            self.max_ns = d_ns

    def percentile_us(self, q: float) -> float:
        """The bin (µs) holding the q-quantile; 0 when empty."""
        return bin_percentiles(self.bins, (q,))[0]

    def summary(self) -> dict[str, float]:
        """count, p50, p99 and max in µs."""
        p50, p99 = bin_percentiles(self.bins, (0.5, 0.99))
        return {
            "count": self.count,
            "p50": p50,
            "p99": p99,
            "max": round(self.max_ns / 1000, 1),
        }

    @classmethod
    def merged(cls, hists: Iterable[DurationHist]) -> DurationHist:
        """One histogram holding the counts of all of `hists` (same bin count)."""
        hists = list(hists)
        out = cls(len(hists[0].bins) if hists else 20000)
        for h in hists:
            for i, c in enumerate(h.bins):
                if c:
                    out.bins[i] += c
            out.count += h.count
            out.max_ns = max(out.max_ns, h.max_ns)
        return out
