"""DurationHist: 1 µs bins, percentiles, overflow bin and merging."""

from __future__ import annotations

from compd.cycle.loop import TimingStats
from compd.io.histogram import DurationHist, percentile_text
from compd.service.status import render, timing


def test_percentiles_and_max() -> None:
    h = DurationHist(max_us=1000)
    for us in range(1, 101):  # 1..100 µs
        h.add_ns(us * 1000 + 500)
    s = h.summary()
    assert s["count"] == 100
    assert s["p50"] == 50.0 and s["p99"] == 99.0
    assert s["max"] == 100.5


def test_overflow_lands_in_last_bin_but_max_is_exact() -> None:
    """A quantile in the overflow bin is no measurement: it reads as the range limit, flagged."""
    h = DurationHist(max_us=10)
    h.add_ns(5_000_000)
    assert h.percentile_us(0.5) == 10.0  # the range limit, not the last bin's 9
    assert h.summary()["max"] == 5000.0
    assert h.summary()["over_range"] == ["p50", "p99"]


def test_a_p99_over_the_ceiling_is_flagged_and_printed_as_over_20_ms() -> None:
    h = DurationHist()  # 1 µs bins up to 20 ms
    for _ in range(97):
        h.add_ns(50_000)  # 50 µs
    for _ in range(3):
        h.add_ns(812_000_000)  # 812 ms: over the range
    s = h.summary()
    assert s["p50"] == 50.0 and s["p99"] == 20000.0  # the range limit, not 19999
    assert s["over_range"] == ["p99"]
    assert percentile_text(s["p99"], "p99" in s["over_range"]) == ">20 ms"
    assert percentile_text(s["p50"], "p50" in s["over_range"]) == "50 us"
    assert s["max"] == 812000.0  # the maximum is exact


def test_just_below_the_ceiling_is_a_measurement() -> None:
    h = DurationHist(max_us=100)
    h.add_ns(98_500)  # 98 µs: the last bin that is not the overflow
    assert h.percentile_us(0.99) == 98.0 and h.summary()["over_range"] == []
    h.add_ns(99_000)  # 99 µs lands in the overflow bin (99 µs and above)
    h.add_ns(99_000)
    assert h.percentile_us(0.99) == 100.0 and h.summary()["over_range"] == ["p50", "p99"]


def test_over_range_of_loop_timing() -> None:
    st = TimingStats(0.002)
    for _ in range(98):
        st.record(30e-6, 80_000)
    for _ in range(2):
        st.record(0.9, 30_000_000)  # a stall: 0.9 s late, 30 ms of work
    t = timing(st)
    assert t["lateness_us"]["p50"] == 30.0 and t["lateness_us"]["p99"] == 20000.0
    assert t["over_range"] == {"lateness_us": ["p99", "p999"], "cycle_compute_us": ["p99"]}
    assert t["lateness_us"]["max"] == 900000.0
    text = render({"loop": t}, True, "running")
    assert "lateness p50 30 us, p99 >20 ms, p99.9 >20 ms, max 900000 us" in text
    assert "19999" not in text


def test_merged_adds_counts() -> None:
    a, b = DurationHist(100), DurationHist(100)
    a.add_ns(10_000)
    b.add_ns(30_000)
    b.add_ns(30_000)
    m = DurationHist.merged([a, b])
    assert m.count == 3 and m.percentile_us(0.5) == 30.0 and m.max_ns == 30_000
    assert DurationHist().summary()["p99"] == 0.0
