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
MCL_ONFAULT = 4  # Linux 4.4: lock each page when it is first touched, not every mapped page now


def _mlockall() -> tuple[int, bool]:
    """mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT), or without MCL_ONFAULT on a kernel
    that does not know it; returns (0 or the errno, whether on fault).

    Without MCL_ONFAULT, mlockall makes resident every page mapped: the whole text of every
    shared library (numpy's OpenBLAS alone, with a kernel for each CPU type, is tens of MB),
    every thread's 8 MB stack, the BLAS buffers. compd's process measured 216 MB that way
    against 53 MB on fault. On fault, every page the process has touched stays in RAM, and
    the cycle touches its paths in the priming cycle before the schedule starts."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
        return 0, True
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        return ctypes.get_errno(), False
    return 0, False


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
        err, onfault = _mlockall()
        if err == 0:
            done.append((True, "memory locked (mlockall, as touched)" if onfault else "memory locked (mlockall)"))
        else:
            done.append((False, f"cannot lock memory: {os.strerror(err)} (LimitMEMLOCK)"))
    return done
