"""compd's loop for `compd bench`, in a process of its own that imports compd only.

The bench's own process fits the gantry model and starts the devices (scipy, the
simulator): none of that belongs in the resident size or the interpreter of the loop
it measures. `python -m rig.bench_loop CONFIG CYCLES LATE_US OUT.json` runs compd's
loop for CYCLES cycles against the devices the config names and writes its timing,
resident size, I/O round trips, host figures and the late cycles' attribution
(compd.io.activity) as JSON.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

RSS_EVERY = 10_000  # cycles between resident-size samples


def rss_kb() -> int:
    """Resident set size of this process, kB (from /proc)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def host_steal_ms() -> float:
    """CPU time the hypervisor took from this machine's CPUs so far (/proc/stat steal), ms."""
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()
        return int(fields[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def thread_switches(tid: int) -> tuple[int, int]:
    """(voluntary, involuntary) context switches of thread `tid` of this process."""
    vol = invol = 0
    try:
        with open(f"/proc/self/task/{tid}/status") as fh:
            for line in fh:
                if line.startswith("voluntary_ctxt_switches:"):
                    vol = int(line.split()[1])
                elif line.startswith("nonvoluntary_ctxt_switches:"):
                    invol = int(line.split()[1])
    except OSError:
        pass
    return vol, invol


def memory_of_kb(pid: int) -> dict[str, int]:
    """Resident (`rss_kb`) and proportional (`pss_kb`: pages shared with the loop's process
    after the fork counted in part) size of process `pid`, kB (0 when it is gone)."""
    out = {"rss_kb": 0, "pss_kb": 0}
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Rss:"):
                    out["rss_kb"] = int(line.split()[1])
                elif line.startswith("Pss:"):
                    out["pss_kb"] = int(line.split()[1])
    except OSError:
        pass
    return out


def io_processes(app: Any) -> list[dict[str, Any]]:
    """The device I/O workers and the service that run in processes of their own: name, pid,
    resident and proportional size (kB)."""
    from compd.io.modbus_link import ModbusLink
    from compd.sources.base import PolledSource

    out = []
    statuses = [(s.name, s.io_status()) for s in app.sources if isinstance(s, PolledSource)]
    link = app.sink.link
    if isinstance(link, ModbusLink):
        statuses.append(("sink", link.get_status()))
    service_pid = app.service.pid
    if service_pid is not None:
        statuses.append(("service", {"pid": service_pid}))
    for name, st in statuses:
        pid = st.get("pid")
        if pid is not None and pid != os.getpid():
            out.append({"name": name, "pid": pid, **memory_of_kb(pid)})
    return out


def io_stats(app: Any) -> dict[str, dict[str, float]]:
    """Modbus TCP round trips of compd's I/O threads: every poll of the PT100 modules
    (8 registers in one request), every write to the PMC, and the output latency from
    the cycle queueing a word to the PMC acknowledging it."""
    from compd.io.histogram import DurationHist

    polls = [s.poll_hist for s in app.sources if s.poll_hist is not None]
    link = app.sink.link
    out = {"read": DurationHist.merged(polls).summary() if polls else {}}
    if link is not None:
        out["write"] = link.write_hist.summary()
        out["output_latency"] = link.latency_hist.summary()
    return out


def run_compd_loop(config: Path, cycles: int) -> dict[str, Any]:
    """compd's loop for `cycles` cycles; timing stats and resident size."""
    from compd.config import load_config
    from compd.cycle.statusblock import LI
    from compd.daemon.app import App

    app = App(load_config(config))
    rss: dict[str, int] = {}
    warm = min(max(cycles // 10, 1000), cycles)
    trace = [0] * (cycles // RSS_EVERY + 2)  # preallocated: the hook appends nothing
    n_trace = [0]

    # misses against the hypervisor: /proc/stat's steal counter read about once a second;
    # a miss in a second in which steal grew is counted as coinciding with host steal
    steal = {"last": host_steal_ms(), "misses": 0, "with_steal": 0}

    def sample_rss(loop: Any, now: float) -> None:
        c = loop.stats.cycles
        m = loop.stats.misses
        if m != steal["misses"]:
            st = host_steal_ms()
            if st > steal["last"]:
                steal["with_steal"] += m - steal["misses"]
            steal["misses"] = m
        if c % 500 == 0:
            steal["last"] = host_steal_ms()
        if c == warm:
            rss["after_warmup_kb"] = rss_kb()
        if c % RSS_EVERY == 0 and c > warm:
            trace[n_trace[0]] = rss_kb()
            n_trace[0] += 1

    app.loop.cycle_hooks.append(sample_rss)
    app.open()
    try:
        # wait for the pollers' first samples so the model starts on real readings
        deadline = time.monotonic() + 5
        while not all(s.sampled() for s in app.sources) and time.monotonic() < deadline:
            time.sleep(0.01)
        tid = threading.get_native_id()
        steal0, sw0 = host_steal_ms(), thread_switches(tid)
        app.loop.run(max_cycles=cycles)
        steal1, sw1 = host_steal_ms(), thread_switches(tid)
        tids = [int(t) for t in os.listdir("/proc/self/task")]  # the loop's process's threads, while running
        io = io_stats(app)  # before close: closing the sink drops its link
        procs = io_processes(app)
    finally:
        app.close()
    service = app.service.counts()
    pub = app.service.publisher
    service["devices_waited"] = pub.devices_waited  # cycles the devices' accounts waited for room
    service["status_write_max_us"] = round(pub.block.read().get(LI.write_max_ns) / 1000, 1)
    rss["end_kb"] = rss_kb()
    base = rss.get("after_warmup_kb", rss["end_kb"])
    rss["growth_kb"] = rss["end_kb"] - base
    samples = trace[: n_trace[0]]
    rss["max_after_warmup_kb"] = max([base, *samples])
    rss["max_growth_kb"] = rss["max_after_warmup_kb"] - base
    rss["samples"] = len(samples)
    stats = app.loop.stats
    out = stats.as_dict()
    from compd.io.histogram import range_limit_us
    from compd.service.status import timing_over_range

    # the percentiles over the histogram's range (their value is its limit, not a measurement)
    out["over_range"] = timing_over_range(out["lateness_us"], out["cycle_compute_us"], range_limit_us(stats.hist))
    out["rss"] = rss
    out["io_us"] = io
    out["io_processes"] = procs
    out["service"] = service
    out["_tids"] = tids
    # what the OS and the hypervisor did to the cycle thread during the run
    out["host"] = {
        "steal_ms": round(steal1 - steal0, 1),
        "cycle_thread_voluntary_switches": sw1[0] - sw0[0],
        "cycle_thread_involuntary_switches": sw1[1] - sw0[1],
        "misses_with_steal": steal["with_steal"],
    }
    out["realtime"] = [what for _, what in app.service.realtime_result]
    out["words_sent"] = app.encoder.words_emitted
    return out


def main(argv: list[str]) -> int:
    config, cycles, late_us, out, *flags = argv
    from compd.io import activity

    activity.enable(float(late_us))
    try:
        result = run_compd_loop(Path(config), int(cycles))
        result["late_attribution"] = activity.attribute()
        if "trace" in flags:  # for rig.late_trace: the marked cycles and who is who in the kernel's trace
            result["spans_ns"] = {"late": activity.spans(activity.LATE), "slow": activity.spans(activity.SLOW)}
            result["cycle_tid"] = threading.get_native_id()
            result["process_tids"] = [int(t) for t in os.listdir("/proc/self/task")] + result.pop("_tids", [])
    finally:
        activity.disable()
    result["modules"] = sorted({m.split(".")[0] for m in sys.modules if not m.startswith("_")})
    Path(out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
