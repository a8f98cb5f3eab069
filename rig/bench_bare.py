"""The limit of this machine for `compd bench`: a bare Python loop that sleeps, spins to each deadline and does nothing else.

`python -m rig.bench_bare CYCLES PERIOD_S SCHEDULER CPU OUT.json` runs CYCLES deadlines
on the same absolute schedule as compd's loop, with the same real-time options (SCHED_FIFO
priority 50, pinned to CPU, memory locked) when SCHEDULER is `fifo`: how late a cycle
can be on this machine when the cycle itself costs nothing. Run in the same `compd bench`
as compd's loop, under the same load, it separates what compd adds from what the
kernel and the hypervisor do.
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


def run(cycles: int, period_s: float, scheduler: str, cpu: int | None) -> dict[str, object]:
    if scheduler == "fifo":
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        ctypes.CDLL(None).mlockall(1 | 2 | 4)
    late = np.zeros(cycles)
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
    us = late * 1e6
    return {
        "cycles": cycles,
        "misses": int(np.count_nonzero(late > period_s / 2)),
        "late_200us": int(np.count_nonzero(us > 200.0)),
        "lateness_us": {
            "p50": float(np.percentile(us, 50)), "p99": float(np.percentile(us, 99)),
            "p999": float(np.percentile(us, 99.9)), "max": float(us.max()),
        },
    }


def main(argv: list[str]) -> int:
    cycles, period_s, scheduler, cpu, out = argv
    result = run(int(cycles), float(period_s), scheduler, None if cpu == "-" else int(cpu))
    Path(out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
