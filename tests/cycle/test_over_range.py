"""A percentile in the 1 µs histogram's overflow bin is not a measurement: every channel says so.

The loop's lateness and compute histograms count up to 20 ms; a p99 that falls in the last
bin is reported as the range limit (20000 µs) and flagged (`loop.over_range`): status text
and the bench print `>20 ms`, Sparkplug sends `Loop/lateness_p99_over_range`, OPC UA's value
carries Uncertain_EngineeringUnitsExceeded. Nothing prints 19999.
"""

from __future__ import annotations

from typing import Any

import pytest

from compd.cycle.loop import HIST_US, TimingStats
from compd.plant.telemetry import device_metrics
from compd.service.status import jsonable, render, timing


def _stalled_stats() -> TimingStats:
    """2 % of the cycles 0.812 s late (the loop stalled) and their work 25 ms: both p99 over the range."""
    st = TimingStats(0.002)
    for _ in range(98):
        st.record(40e-6, 90_000)
    for _ in range(2):
        st.record(0.812, 25_000_000)
    return st


def _snap(st: TimingStats) -> dict[str, Any]:
    # what compose gives beside the loop's timing: the sink's link and the loop's counters at the top
    return jsonable(
        {
            "state": "running",
            "observe": False,
            "word": "0x0000",
            "axes": {},
            "signals": {},
            "loop": timing(st),
            "model": {"kind": "xi_spindle", "fit": {}},
            "sink": {"link": "up"},
            "saturations": 0,
        }
    )


def test_the_loops_p99_is_the_range_limit_and_flagged() -> None:
    t = timing(_stalled_stats())
    assert t["lateness_us"]["p99"] == float(HIST_US) and t["cycle_compute_us"]["p99"] == float(HIST_US)
    assert t["over_range"] == {"lateness_us": ["p99", "p999"], "cycle_compute_us": ["p99"]}
    assert all(isinstance(v, float) for v in t["lateness_us"].values())  # the numbers stay numbers
    assert t["lateness_us"]["max"] == 812000.0  # measured, not from the histogram


def test_in_range_percentiles_are_not_flagged() -> None:
    st = TimingStats(0.002)
    for _ in range(100):
        st.record(40e-6, 90_000)
    t = timing(st)
    assert t["over_range"] == {"lateness_us": [], "cycle_compute_us": []}
    assert "lateness p50 40 us, p99 40 us, p99.9 40 us" in render({"loop": t}, True, "running")


def test_status_text_says_over_20_ms() -> None:
    text = render(_snap(_stalled_stats()), True, "running")
    line = next(ln for ln in text.splitlines() if ln.startswith("loop: "))
    assert "p99 >20 ms, p99.9 >20 ms, max 812000 us" in line
    assert "19999" not in text and "20000" not in line


def test_sparkplug_flags_the_p99() -> None:
    m = {d.name: v for d, v in device_metrics(_snap(_stalled_stats()))}
    assert m["Loop/lateness_p99_us"] == 20000.0 and m["Loop/lateness_p99_over_range"] is True
    assert m["Loop/compute_p99_us"] == 20000.0 and m["Loop/compute_p99_over_range"] is True
    calm = TimingStats(0.002)
    calm.record(40e-6, 90_000)
    m = {d.name: v for d, v in device_metrics(_snap(calm))}
    assert m["Loop/lateness_p99_over_range"] is False and m["Loop/lateness_p99_us"] == 40.0


def test_opcua_marks_the_p99_uncertain() -> None:
    pytest.importorskip("asyncua")  # the `plant` extra
    from asyncua import ua

    from compd.plant.opcua import address_space, data_values

    snap = _snap(_stalled_stats())
    variables = address_space(snap)
    values, problems = data_values(variables, snap)
    assert problems == []
    by_id = dict(zip((v.node_id for v in variables), values, strict=True))
    for node in ("compd.Loop.LatenessP99Us", "compd.Loop.ComputeP99Us"):
        assert by_id[node].Value.Value == 20000.0
        assert by_id[node].StatusCode.value == ua.StatusCodes.UncertainEngineeringUnitsExceeded, node
    assert by_id["compd.Loop.LatenessMaxUs"].StatusCode.is_good()  # the maximum is measured


def test_bench_table_prints_over_20_ms() -> None:
    pytest.importorskip("hil_sim")  # the rig's table; compd installed alone has no bench
    from rig.bench import format_table

    t = timing(_stalled_stats())
    row = {"cycles": 100, "misses": 2, "lateness_us": t["lateness_us"], "cycle_compute_us": t["cycle_compute_us"]}
    naive = {**row, "period_us": {"p50": 2000.0, "p99": 2100.0}}
    r = {
        **row,
        "over_range": t["over_range"],
        "period_ms": 2.0,
        "scheduler": "other",
        "realtime": [],
        "naive": naive,
        "bare": None,
        "rss_kb": {"end_kb": 1, "growth_kb": 0, "max_growth_kb": 0, "samples": 0},
        "service": {},
        "io_us": {"read": {"count": 3, "p50": 50.0, "p99": 20000.0, "max": 900000.0, "over_range": ["p99"]}},
        "words_sent": 0,
        "plant_speedup": 1.0,
        "host": {"steal_ms": 0.0, "cycle_thread_involuntary_switches": 0, "misses_with_steal": 0},
        "model_eval_us": {},
        "ratio_naive_to_compd": {"miss_rate": None, "p99_lateness": 1.0},
    }
    table = format_table(r)
    late = next(ln for ln in table.splitlines() if ln.startswith("lateness p99 us"))
    assert late.split()[3] == ">20" and "19999" not in table
    compute = next(ln for ln in table.splitlines() if ln.startswith("cycle compute p99 us"))
    assert ">20 ms" in compute
    assert "I/O poll (8 regs): 3 round trips, p50 50 us, p99 >20 ms, max 900000 us" in table
