"""Benchmarks (make bench only): the CPU a day of 1 s rows takes through `compd replay` (issue 29: ≤ 2 s)."""

from __future__ import annotations

import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytestmark = pytest.mark.bench

BIN = Path(sys.executable).parent
LIMIT_CPU_S = 2.0


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(list(args), cwd=cwd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return done


def _cpu_s(*args: str, cwd: Path) -> tuple[float, str]:
    """User + system CPU of one command (a child process), and what it printed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = _run(*args, cwd=cwd).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), out


def _log(machine: str, day: str, rate_s: float, out: Path, cwd: Path) -> None:
    scenario = Path(__file__).resolve().parents[2] / "hil_sim" / "scenarios" / f"{machine}_{day}.yaml"
    _run(
        sys.executable,
        "-m",
        "hil_sim",
        "log",
        "--scenario",
        str(scenario),
        "--out",
        str(out),
        "--rate-s",
        str(rate_s),
        cwd=cwd,
    )


@pytest.fixture(scope="module")
def days(tmp_path_factory):
    """The issue's three replays: each machine's training day at 60 s fitted, its unseen day at 1 s."""
    d = tmp_path_factory.mktemp("rp")
    compd = str(BIN / "compd")
    for machine in ("lathe", "gantry", "spindle"):
        _log(machine, "train", 60.0, d / f"{machine}_train.csv", d)
        _log(machine, "unseen", 1.0, d / f"{machine}_unseen_1s.csv", d)
    _run(compd, "fit", "--kind", "ar1", "--log", "lathe_train.csv", "--out", "ar1.yaml", "--inputs", "T3", cwd=d)
    _run(compd, "fit", "--kind", "lvr", "--log", "gantry_train.csv", "--out", "lvr.yaml", cwd=d)
    _run(
        compd,
        "fit",
        "--kind",
        "xi_spindle",
        "--log",
        "spindle_train.csv",
        "--out",
        "xi.yaml",
        "--inputs",
        "T_xi",
        "speed_rpm",
        "--target",
        "err_z_um",
        cwd=d,
    )
    for name, model, sink in (
        ("gantry_pci.yaml", {"kind": "lvr", "file": "lvr.yaml"}, {"kind": "pci1756"}),
        ("spindle_pmc.yaml", {"kind": "xi_spindle", "file": "xi.yaml"}, {"kind": "fanuc_pmc"}),
    ):
        (d / name).write_text(
            yaml.safe_dump(
                {
                    "loop": {"period_s": 0.002},
                    "sources": [{"kind": "replay", "name": "log", "path": "unused.csv"}],
                    "model": model,
                    "sink": sink,
                }
            )
        )
    return d


@pytest.mark.parametrize(
    ("what", "args"),
    [
        ("lathe ar1, FANUC PMC (model file)", ("--model", "ar1.yaml", "--log", "lathe_unseen_1s.csv")),
        ("gantry lvr, PCI-1756 (config)", ("gantry_pci.yaml", "--log", "gantry_unseen_1s.csv")),
        ("spindle xi_spindle, FANUC PMC (config)", ("spindle_pmc.yaml", "--log", "spindle_unseen_1s.csv")),
    ],
)
def test_a_day_of_1_s_rows_through_compd_replay(days, what, args):
    cpu_s, out = _cpu_s(str(BIN / "compd"), "replay", *args, cwd=days)
    print(f"\ncompd replay {' '.join(args)}  [{what}]: CPU {cpu_s:.2f} s (user + sys)\n{out.strip()}")
    assert "86401 rows" in out
    assert cpu_s <= LIMIT_CPU_S


def test_bench_day_of_1hz_log(tmp_path):
    """86 400 rows (a day at 1 Hz) through the PMC: the target is seconds, not minutes."""
    from compd.commissioning.replay import replay_model
    from tests.commissioning.test_replay import ALPHA, LENGTH_MM, spindle_log

    model = tmp_path / "xi.yaml"
    model.write_text(
        yaml.safe_dump(
            {
                "kind": "xi_spindle",
                "inputs": ["T_xi"],
                "outputs": ["z"],
                "params": {"alpha_per_k": ALPHA, "length_mm": LENGTH_MM, "t0_c": None},
                "fit": {},
            }
        )
    )
    log = tmp_path / "day.csv"
    spindle_log(log, hours=24.0)
    t0 = time.perf_counter()
    result = replay_model(model, log)
    wall_s = time.perf_counter() - t0
    print(f"replay of {result.report['rows']} rows: {wall_s:.2f} s")
    assert result.report["rows"] == 86400
    assert wall_s < 60.0
