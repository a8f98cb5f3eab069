"""Benchmark (make bench only): what the cycle's status record costs per cycle.

Also what composing the status costs the service.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from compd.config import load_config
from compd.cycle.statusblock import StatusBlock, compose, describe
from compd.daemon.app import App
from tests.service_helpers import sim_config

pytestmark = pytest.mark.bench

WRITES = 200_000
WRITE_P50_LIMIT_US = 30.0  # a few µs on this 2-core box; the limit leaves room for a loaded one


def test_status_record_write_and_compose_us(tmp_path: Path) -> None:
    app = App(load_config(sim_config(tmp_path, duration_s=3600)))
    app.open()
    try:
        app.loop.run(max_cycles=500)
        block = StatusBlock(app.loop)
        took = np.zeros(WRITES)
        perf = time.perf_counter_ns
        for i in range(WRITES):
            t0 = perf()
            block.write()
            took[i] = perf() - t0
        took /= 1000.0
        desc = describe(app.loop, observe=False)
        t0 = time.perf_counter()
        for _ in range(100):
            compose(block.read(), desc)
        compose_us = (time.perf_counter() - t0) / 100 * 1e6
    finally:
        app.close()
    p50, p99, p999 = np.percentile(took, (50, 99, 99.9))
    print(
        f"status record write, {WRITES} writes: p50 {p50:.2f} us, p99 {p99:.2f} us, p99.9 {p999:.1f} us,"
        f" max {took.max():.1f} us; the service's read + compose: {compose_us:.0f} us"
    )
    assert p50 <= WRITE_P50_LIMIT_US
