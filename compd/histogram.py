"""A fixed-size duration histogram (1 µs bins) for timing I/O threads without allocation."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from compd.io.mailbox import shared_buffer


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
    """Counts durations in 1 µs bins up to `max_us` (the last bin holds everything above).

    Its counts live in memory shared with the children forked after it was made, so an
    I/O worker in a process of its own (compd.io.child) counts into the same histogram.
    """

    def __init__(self, max_us: int = 20000) -> None:
        self._buf = shared_buffer(8 * (max_us + 2))
        self._words = memoryview(self._buf).cast("q")  # count, max ns, then the bins
        self.bins = np.frombuffer(self._buf, dtype=np.int64, offset=16)

    @property
    def count(self) -> int:
        return self._words[0]

    @property
    def max_ns(self) -> int:
        return self._words[1]

    def add_ns(self, d_ns: int) -> None:
        w = self._words
        us = d_ns // 1000
        n = len(w) - 2
        w[2 + (us if us < n else n - 1)] += 1
        w[0] += 1
        if d_ns > w[1]:
            w[1] = d_ns

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
            out.bins += h.bins
            out._words[0] += h.count
            out._words[1] = max(out.max_ns, h.max_ns)
        return out
