"""Benchmarks (make bench only): the CPU each kind's fit takes on a day's log, and `--kind all` (issue 40).

Each fit is `compd fit`'s work (compd.commissioning.fitting.fit_model: the fit with its choices —
sensors, lag, form — and its held-out comparison with MLR) on hil_sim logs made here from fixed
seeds: the family's lathe (1441 rows at 60 s), motorized spindle and feed axis (2881 rows at
30 s), gantry (3086 rows × 19 temperatures at 28 s), and two lathe days at a dozen speeds (30 s rows: 10 h, 1241
rows, the sensors named; 25 h, 3081 rows, the sensors chosen). CPU is the process's user + system
time with the linear algebra on one thread (as `compd fit` runs it), imports made before: ≤ 5 s per kind, the gantry's
LVR ≤ 4 s, `--kind all` on the lathe ≤ 60 s."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from compd.commissioning import fitting
from compd.identify import FITS

pytestmark = [
    pytest.mark.bench,
    pytest.mark.timeout(1800),
]  # CPU is measured: a loaded box only stretches the wall time

LIMIT_CPU_S = 5.0  # each kind on a day's log (≤ 3000 rows)
LIMIT_LVR_S = 4.0  # the gantry's LVR, 3086 × 19
LIMIT_ALL_S = 60.0  # --kind all on the lathe

SPECTRUM = """machine: lathe
seed: {seed}
ambient: {{start_c: 20.0, drift_c_per_h: 0.05, daily_amplitude_c: 0.8, daily_phase_h: 6.0}}
segments:
{segments}
"""


def _spectrum(path: Path, hours: float, seed: int) -> Path:
    """A lathe scenario at a dozen speeds (300 … 3600 rpm) in a shuffled order, runs of 30–50 min, stops."""
    import random

    rnd = random.Random(seed)
    levels = list(range(300, 3601, 300))
    segs, t, order = ["  - {duration_s: 1800, speed_rpm: 0}"], 1800, []
    while t < hours * 3600 - 1800:
        order = order or levels[:]
        n = order.pop(rnd.randrange(len(order)))
        d = rnd.choice([1800, 2400, 3000])
        segs.append(f"  - {{duration_s: {d}, speed_rpm: {n}}}")
        t += d
        if rnd.random() < 0.3:
            segs.append("  - {duration_s: 1200, speed_rpm: 0}")
            t += 1200
    segs.append("  - {duration_s: 1800, speed_rpm: 0}")
    path.write_text(SPECTRUM.format(seed=seed, segments="\n".join(segs)), encoding="utf-8")
    return path


def _hil_sim(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "hil_sim", *args], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fitlogs")
    for kind, rate in (("lathe", None), ("spindle", "30"), ("gantry", "28"), ("feed_axis", "30")):
        _hil_sim(
            "family", "--kind", kind, "--seeds", "1", "--out", str(d / kind), *(["--rate-s", rate] if rate else [])
        )
    for name, hours, seed in (("spectrum_10h", 10, 7), ("spectrum_25h", 25, 8)):
        _hil_sim(
            "log",
            "--scenario",
            str(_spectrum(d / f"{name}.yaml", hours, seed)),
            "--out",
            str(d / f"{name}.csv"),
            "--rate-s",
            "30",
        )
    return {
        "lathe": d / "lathe" / "lathe_1_train.csv",
        "spindle": d / "spindle" / "spindle_1_train.csv",
        "gantry": d / "gantry" / "gantry_1_train.csv",
        "feed_axis": d / "feed_axis" / "feed_axis_1_train.csv",
        "spectrum_10h": d / "spectrum_10h.csv",
        "spectrum_25h": d / "spectrum_25h.csv",
    }


def _cpu_s(work) -> float:
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        t0 = time.process_time()
        work()
        return time.process_time() - t0


# (label, log, kind, inputs, options, limit)
CASES = [
    ("ar1 lathe, sensors chosen", "lathe", "ar1", None, {}, LIMIT_CPU_S),
    ("ar1 spectrum 10 h, named", "spectrum_10h", "ar1", ["T3", "T4", "T5"], {"ambient": "T7"}, LIMIT_CPU_S),
    ("ar1 spectrum 25 h, chosen", "spectrum_25h", "ar1", None, {}, LIMIT_CPU_S),
    ("mlr lathe", "lathe", "mlr", None, {}, LIMIT_CPU_S),
    ("lvr lathe", "lathe", "lvr", None, {}, LIMIT_CPU_S),
    ("xi_spindle spindle", "spindle", "xi_spindle", None, {}, LIMIT_CPU_S),
    ("lvr gantry 3086x19", "gantry", "lvr", None, {}, LIMIT_LVR_S),
    ("feed_axis", "feed_axis", "feed_axis", None, {}, LIMIT_CPU_S),
]


def test_each_kind_fits_in_seconds(logs: dict[str, Path]) -> None:
    fitting.fit_model("mlr", fitting.read_fit_log(logs["lathe"]), None, None, {})  # imports, once ...
    for kind in FITS.kinds():  # ... every kind's module (and scipy's parts it loads): no fit pays for them
        FITS.get(kind)
    rows, slow = [], []
    for label, name, kind, inputs, options, limit in CASES:
        log = fitting.read_fit_log(logs[name])
        targets = fitting.default_targets(log, None)
        tc = targets[:1] if kind in ("ar1", "xi_spindle", "feed_axis") else None
        cpu = _cpu_s(
            lambda log=log, kind=kind, inputs=inputs, tc=tc, options=options: fitting.fit_model(
                kind, log, inputs, tc, dict(options)
            )
        )
        rows.append(f"{label:<28} {len(log):>6} {cpu:>8.2f} {limit:>6.1f}")
        if cpu > limit:
            slow.append((label, round(cpu, 2), limit))
    print("\nfit                          rows    cpu_s  limit\n" + "\n".join(rows))
    assert not slow, slow


def test_kind_all_fits_in_a_minute(logs: dict[str, Path]) -> None:
    log = fitting.read_fit_log(logs["lathe"])

    def work() -> None:
        rows = fitting.fit_all(log, None, None, {})
        fitting.recommendation(log, rows, None)

    cpu = _cpu_s(work)
    print(f"\n--kind all, lathe ({len(log)} rows): {cpu:.1f} s CPU (limit {LIMIT_ALL_S:g} s)")
    assert cpu <= LIMIT_ALL_S
