"""Real-time options: SCHED_FIFO, CPU affinity, memory locking — applied as far as the OS permits."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import os

from compd.config import RealtimeConfig

log = logging.getLogger("compd.realtime")

MCL_CURRENT = 1
MCL_FUTURE = 2


def apply_realtime(cfg: RealtimeConfig) -> dict[str, str]:
    """Apply what `cfg` asks for; returns {option: "applied" | "not applied: why"}.

    Nothing here raises: an unprivileged run goes on with a warning per option
    that could not be applied.
    """
    result: dict[str, str] = {}
    if cfg.cpu_affinity:
        try:
            os.sched_setaffinity(0, set(cfg.cpu_affinity))
            result["cpu_affinity"] = "applied"
        except (OSError, ValueError) as e:
            result["cpu_affinity"] = f"not applied: {e}"
    if cfg.lock_memory:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
                err = ctypes.get_errno()
                raise OSError(err, os.strerror(err))
            result["lock_memory"] = "applied"
        except (OSError, AttributeError) as e:
            result["lock_memory"] = f"not applied: {e}"
    if cfg.scheduler == "fifo":
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(cfg.priority))
            result["scheduler"] = f"applied: SCHED_FIFO priority {cfg.priority}"
        except (OSError, AttributeError) as e:
            result["scheduler"] = f"not applied: {e} (needs CAP_SYS_NICE or root)"
    for option, outcome in result.items():
        if outcome.startswith("not applied"):
            log.warning("event=realtime option=%s outcome=%r", option, outcome)
        else:
            log.info("event=realtime option=%s outcome=%r", option, outcome)
    return result


def reset_scheduler() -> None:
    """Back to SCHED_OTHER (tests, and before forking helpers)."""
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
