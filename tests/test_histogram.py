"""DurationHist: 1 µs bins, percentiles, overflow bin and merging."""

from __future__ import annotations

from compd.histogram import DurationHist


def test_percentiles_and_max() -> None:
    h = DurationHist(max_us=1000)
    for us in range(1, 101):  # 1..100 µs
        h.add_ns(us * 1000 + 500)
    s = h.summary()
    assert s["count"] == 100
    assert s["p50"] == 50.0 and s["p99"] == 99.0
    assert s["max"] == 100.5


def test_overflow_lands_in_last_bin_but_max_is_exact() -> None:
    h = DurationHist(max_us=10)
    h.add_ns(5_000_000)
    assert h.percentile_us(0.5) == 9.0
    assert h.summary()["max"] == 5000.0


def test_merged_adds_counts() -> None:
    a, b = DurationHist(100), DurationHist(100)
    a.add_ns(10_000)
    b.add_ns(30_000)
    b.add_ns(30_000)
    m = DurationHist.merged([a, b])
    assert m.count == 3 and m.percentile_us(0.5) == 30.0 and m.max_ns == 30_000
    assert DurationHist().summary()["p99"] == 0.0
