"""A fixed-size duration histogram (1 µs bins) for timing I/O threads without allocation."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from compd.io.mailbox import shared_buffer


def bin_percentiles(bins: Any, qs: Sequence[float]) -> list[float]:
    """Bin indices (µs) at which the cumulative count first reaches q·total; 0 when empty.

    The last bin holds everything above the range (it overflows): a quantile that falls in
    it is not a measurement, and is reported as the range limit, len(bins) µs (the true
    value is at least that; `over_range` tells). `bins` is an int64 array (array("q") or
    numpy); numpy keeps a 20 000-bin pass ≈ 50 µs.
    """
    counts = bins if isinstance(bins, np.ndarray) else np.frombuffer(bins, dtype=np.int64)
    cum = np.cumsum(counts)
    total = cum[-1] if cum.size else 0
    if total == 0:
        return [0.0 for _ in qs]
    last = cum.size - 1  # the overflow bin
    out = []
    for q in qs:
        i = int(np.searchsorted(cum, q * total, side="left"))
        out.append(float(i) if i < last else float(cum.size))
    return out


def range_limit_us(bins: Any) -> float:
    """The range limit (µs) of a histogram of 1 µs bins: its bin count (the last bin overflows)."""
    return float(len(bins))


def over_range(values: dict[str, Any], limit_us: float, keys: Sequence[str] = ("p50", "p99", "p999")) -> list[str]:
    """The keys of `values` (percentiles, µs) that are at the histogram's range limit: their
    quantile fell in the overflow bin, so the value stands for "above `limit_us`"."""
    return [k for k in keys if isinstance(values.get(k), int | float) and values[k] >= limit_us]


def percentile_text(value_us: Any, over: bool, fmt: str = "g") -> str:
    """A percentile (µs) for people: `>20 ms` when it is over the histogram's range (`value_us`
    is then the range limit), else the number as `fmt` with ` us`; `nan` for none."""
    if not isinstance(value_us, int | float):
        return "nan"
    if over:
        return f">{value_us / 1000:g} ms"
    return f"{format(value_us, fmt)} us"


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
        """The bin (µs) holding the q-quantile; 0 when empty; `max_us` when over the range."""
        return bin_percentiles(self.bins, (q,))[0]

    def summary(self) -> dict[str, Any]:
        """count, p50, p99 and max in µs, and `over_range`: the percentiles over the range
        (their value is then the range limit, `max_us`)."""
        p50, p99 = bin_percentiles(self.bins, (0.5, 0.99))
        out: dict[str, Any] = {
            "count": self.count,
            "p50": p50,
            "p99": p99,
            "max": round(self.max_ns / 1000, 1),
        }
        out["over_range"] = over_range(out, range_limit_us(self.bins), ("p50", "p99"))
        return out

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
