"""Real-time options (`loop.realtime`) for the calling thread: SCHED_FIFO, CPU affinity, mlockall.

Applied from the thread that runs the cycle, after the helper threads (pollers,
status, metrics) exist, so only the cycle gets the real-time policy (Linux applies
sched_setscheduler(0, …) and sched_setaffinity(0, …) to the calling thread). What
the OS refuses is reported, not fatal: compd runs, slower to wake, and says so.
Under systemd the opt-in drop-in `realtime.conf` grants what these need.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from typing import Any

MCL_CURRENT = 1
MCL_FUTURE = 2


def _mlockall() -> int:
    """mlockall(MCL_CURRENT | MCL_FUTURE); returns 0 or the errno."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        return ctypes.get_errno()
    return 0


def apply_realtime(cfg: Any) -> list[tuple[bool, str]]:
    """Apply a RealtimeConfig to the calling thread; returns (ok, what) for each option tried."""
    done: list[tuple[bool, str]] = []
    if cfg.cpu_affinity:
        try:
            os.sched_setaffinity(0, set(cfg.cpu_affinity))
            done.append((True, f"cycle thread pinned to CPUs {sorted(cfg.cpu_affinity)}"))
        except OSError as e:
            done.append((False, f"cannot pin to CPUs {sorted(cfg.cpu_affinity)}: {e.strerror}"))
    if cfg.scheduler == "fifo":
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(cfg.priority))
            done.append((True, f"cycle thread on SCHED_FIFO priority {cfg.priority}"))
        except OSError as e:
            done.append(
                (False, f"cannot use SCHED_FIFO {cfg.priority}: {e.strerror} (install realtime.conf)")
            )
    if cfg.lock_memory:
        err = _mlockall()
        if err == 0:
            done.append((True, "memory locked (mlockall)"))
        else:
            done.append((False, f"cannot lock memory: {os.strerror(err)} (LimitMEMLOCK)"))
    return done
