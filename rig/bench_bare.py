"""This machine's limit for `compd bench`: a bare Python loop that sleeps, spins to each deadline and does a fixed work.

`python -m rig.bench_bare CYCLES PERIOD_S SCHEDULER CPU OUT.json` runs CYCLES deadlines
on the same absolute schedule as compd's loop, with the same real-time options (SCHED_FIFO
priority 50, pinned to CPU, memory locked) when SCHEDULER is `fifo`, and in each cycle
the same fixed work (`work`: small numpy operations and Python, some tens of µs, no
I/O, nothing allocated that lives on): how late a cycle can be on this machine, and how
much longer the same work takes in its worst cycle than in its typical one. Run in the
same `compd bench` as compd's loop, under the same load, it separates what compd adds
from what the kernel and the hypervisor do.
"""

from __future__ import annotations

import ctypes
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

SPIN_MARGIN_S = 0.0002  # as compd's wall clock


def work(x: np.ndarray, y: np.ndarray, m: np.ndarray) -> float:
    """A fixed cycle's work: the kind of small-array numpy and Python a cycle does."""
    acc = 0.0
    for _ in range(8):
        np.multiply(x, 1.0001, out=y)
        np.less(y, 50.0, out=m)
        np.logical_and(m, m, out=m)
        acc += float(y[3])
    for i in range(150):
        acc += i * 0.5
    return acc


def run(cycles: int, period_s: float, scheduler: str, cpu: int | None) -> dict[str, object]:
    if scheduler == "fifo":
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        ctypes.CDLL(None).mlockall(1 | 2 | 4)
    late = np.zeros(cycles)
    compute = np.zeros(cycles)
    x, y, m = np.full(19, 20.0), np.zeros(19), np.zeros(19, dtype=bool)
    perf = time.perf_counter_ns
    mono = time.monotonic
    t0 = mono() + 0.01
    for k in range(cycles):
        deadline = t0 + k * period_s
        rest = deadline - mono() - SPIN_MARGIN_S
        if rest > 0:
            time.sleep(rest)
        while mono() < deadline:
            pass
        late[k] = mono() - deadline
        c0 = perf()
        work(x, y, m)
        compute[k] = perf() - c0
    us = late * 1e6
    cu = compute / 1000.0
    return {
        "cycles": cycles,
        "misses": int(np.count_nonzero(late > period_s / 2)),
        "late_200us": int(np.count_nonzero(us > 200.0)),
        "lateness_us": {
            "p50": float(np.percentile(us, 50)),
            "p99": float(np.percentile(us, 99)),
            "p999": float(np.percentile(us, 99.9)),
            "max": float(us.max()),
        },
        "cycle_compute_us": {
            "p50": float(np.percentile(cu, 50)),
            "p99": float(np.percentile(cu, 99)),
            "max": float(cu.max()),
        },
    }


def main(argv: list[str]) -> int:
    cycles, period_s, scheduler, cpu, out = argv
    result = run(int(cycles), float(period_s), scheduler, None if cpu == "-" else int(cpu))
    Path(out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
