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

from compd.core.config import RealtimeConfig

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


def apply_realtime(cfg: RealtimeConfig) -> list[tuple[bool, str]]:
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
            done.append((False, f"cannot use SCHED_FIFO {cfg.priority}: {e.strerror} (install realtime.conf)"))
    if cfg.lock_memory:
        err, onfault = _mlockall()
        if err == 0:
            done.append((True, "memory locked (mlockall, as touched)" if onfault else "memory locked (mlockall)"))
        else:
            done.append((False, f"cannot lock memory: {os.strerror(err)} (LimitMEMLOCK)"))
    return done


MADV_POPULATE_WRITE = 23  # Linux 5.14: fault the range in writable, copying what is shared copy-on-write
_PAGE = os.sysconf("SC_PAGE_SIZE")


def unshare_pages() -> int:
    """Copy now every page of this process's private memory that a forked child still
    shares with it; returns the kB copied (0 where the kernel cannot).

    After a fork, parent and child share their pages until one writes: the first write to
    each page then faults and copies it, a few µs each, and the cycle would pay that
    for every page it touches first (measured: a 0.7 ms late cycle right after the
    I/O processes were forked). A memory-locked daemon copies them before its first
    cycle instead. Only pages that are there and shared are copied (pagemap: present,
    anonymous, not mapped by this process alone): nothing new is allocated."""
    import numpy as np

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    copied = 0
    try:
        maps = open("/proc/self/maps", encoding="ascii").read().splitlines()  # noqa: SIM115
        pagemap = open("/proc/self/pagemap", "rb")  # noqa: SIM115
    except OSError:
        return 0
    with pagemap:
        for line in maps:
            fields = line.split()
            perms = fields[1]
            if perms[1] != "w" or perms[3] != "p" or (len(fields) > 5 and fields[5].startswith("[v")):
                continue
            start, end = (int(x, 16) for x in fields[0].split("-"))
            try:
                pagemap.seek(start // _PAGE * 8)
                raw = pagemap.read((end - start) // _PAGE * 8)
            except OSError:
                continue
            bits = np.frombuffer(raw, dtype="<u8")
            shared = ((bits >> 63) & 1 == 1) & ((bits >> 61) & 1 == 0) & ((bits >> 56) & 1 == 0)
            if not shared.any():
                continue
            # runs of shared pages: one madvise each
            edges = np.flatnonzero(np.diff(np.concatenate(([0], shared.view(np.int8), [0]))))
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                if libc.madvise(start + int(a) * _PAGE, (int(b) - int(a)) * _PAGE, MADV_POPULATE_WRITE) != 0:
                    return copied * _PAGE // 1024  # an older kernel: the cycle pays on first write
                copied += int(b) - int(a)
    return copied * _PAGE // 1024
