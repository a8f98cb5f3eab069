"""`compd bench` runs end to end against real devices and writes the bench JSON (docs/formats.md) (no timing asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from rig.bench import format_table


def test_bench_writes_contract_json(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [sys.executable, "-m", "compd", "bench", "--cycles", "400", "--naive-cycles", "30", "--load", "1",
         "--late-us", "1", "--json", str(out)],
        capture_output=True, text=True, timeout=180,
    )
    assert r.returncode == 0, r.stderr
    assert "compd loop" in r.stdout and "naive loop" in r.stdout
    b = json.loads(out.read_text())
    assert b["period_ms"] == 2.0 and b["cycles"] == 400
    assert set(b["lateness_us"]) == {"p50", "p99", "p999", "max"}
    assert set(b["cycle_compute_us"]) == {"p50", "p99", "max"}
    assert isinstance(b["misses"], int)
    assert set(b["model_eval_us"]) == {"feed_axis", "lvr", "xi_spindle", "ar1", "mlr"}
    assert all(v > 0 for v in b["model_eval_us"].values())
    assert b["naive"]["cycles"] == 30
    # the naive loop sleeps a whole period after its work, so it can only fall behind
    assert b["naive"]["lateness_us"]["max"] > b["naive"]["lateness_us"]["p50"] >= 0
    assert b["rss_kb"]["end_kb"] > 0
    # the work between cycles is measured; the bare loop ran beside compd, and without it
    # (--bare-cycles 0) its column says so instead of showing zeros
    assert b["between_max_us"] > 0 and 0 <= b["between_overruns"] <= 400
    assert b["bare"]["cycles"] == 400 and "bare loop" in r.stdout
    table = format_table({**b, "bare": None})
    assert [ln.split()[-2] for ln in table.splitlines() if ln.startswith(("misses", "lateness max"))] == ["-", "-"]
    # compd's I/O threads are timed: every poll of the three modules and every PMC write
    io = b["io_us"]
    assert io["read"]["count"] >= 3 and 0 < io["read"]["p50"] <= io["read"]["p99"] <= io["read"]["max"] + 1
    # the loop emitted words; how many the PMC acknowledged within 0.8 s of wall time depends on
    # the machine's load, but an acknowledged write is timed both ways
    assert b["words_sent"] >= 1
    assert (io["write"]["count"] >= 1) == (io["output_latency"]["count"] >= 1)
    # the naive loop's own start-to-start interval is at least the period it sleeps
    assert b["naive"]["period_us"]["p50"] >= 2000
    # every cycle later than 1 us is matched with the other threads' work: each counted
    # once per thread at most, and every thread that recorded is a device's or compd's own
    assert b["load_processes"] == 1
    la = b["late_attribution"]
    assert la["threshold_us"] == 1.0 and 0 <= la["overlapping_none"] <= la["late_cycles"] <= 400
    assert all(0 <= v <= la["late_cycles"] for v in la["overlapping"].values())
    # the threads that can overlap: the three modules' pollers, the PMC's link, the status writer
    assert set(la["overlapping"]) <= {"poll-pt100_1", "poll-pt100_2", "poll-pt100_3", "modbus-link-fanuc_pmc",
                                      "compd-status", "compd-log"}


def test_bench_rejects_a_negative_load() -> None:
    r = subprocess.run([sys.executable, "-m", "compd", "bench", "--load", "-1"], capture_output=True, text=True)
    assert r.returncode == 2 and "--load" in r.stderr


def test_bench_rejects_zero_cycles() -> None:
    r = subprocess.run([sys.executable, "-m", "compd", "bench", "--cycles", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "--cycles" in r.stderr
