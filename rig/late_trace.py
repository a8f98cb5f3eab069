"""Why a cycle was late or slow: the kernel's trace of the cycle's CPU, matched with the cycles compd marked.

`compd bench --trace FILE` runs compd's loop under `perf record` (scheduler switches and
wake-ups, the cycle thread's page faults, the local timer interrupt; CLOCK_MONOTONIC
time stamps, the clock of `time.perf_counter_ns`). The loop marks every cycle that woke
more than `--late-us` after its deadline (from the deadline to the cycle's first
bytecode) and every cycle whose own work took longer than that (compd.io.activity). Each
marked window gets the causes the trace shows in it:

| cause | what the trace shows |
|---|---|
| `gil` | the cycle thread went to sleep and another thread of its own process woke it: it waited for that thread to\
 hand over the interpreter's lock |
| `blocked` | the cycle thread went to sleep and something else woke it (a lock, a pipe) |
| `preempted` | the cycle thread was switched out still runnable: another task took its CPU |
| `page_faults` | the cycle thread faulted pages in (first touch, or copy-on-write after a fork) |
| `timer_late` | the wake-up before the deadline came more than 100 µs after it was due: the timer interrupt reached a\
 CPU that was not running (the hypervisor had it) |
| `host` | (late) none of these: the thread was on its CPU, spinning to its deadline, and still started late: the\
 hypervisor ran something else on the CPU |
| `cpu` | (slow) none of these: the thread was on its CPU the whole time; its own work took that long, or the\
 hypervisor took the CPU meanwhile (the kernel cannot tell: the bare loop's fixed work shows how far the machine\
 stretches the same work) |

The first four are compd's (or its machine's configuration's) to fix; `timer_late` and
`host` are the host's, and the bare loop of the same bench run shows them too.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from compd.core.errors import BadInput

EVENTS = ("sched:sched_switch", "sched:sched_waking", "exceptions:page_fault_user", "irq_vectors:local_timer_entry")
TIMER_SLACK_S = 100e-6  # a wake-up this much later than due counts as a late timer
CAUSES = ("gil", "blocked", "preempted", "page_faults", "timer_late", "host", "cpu")

_LINE = re.compile(
    r"\s*(?P<comm>.+?)\s+(?P<tid>\d+)\s+\[(?P<cpu>\d+)\]\s+(?P<t>[\d.]+):\s+(?P<name>[\w:]+):\s*(?P<rest>.*)"
)
_KV = re.compile(r"(\w+)=(\S+)")


@dataclass
class Event:
    """One line of `perf script`."""

    t_s: float
    comm: str
    tid: int
    cpu: int
    name: str  # without the subsystem: sched_switch, sched_waking, page_fault_user, local_timer_entry
    fields: dict[str, str]


def parse(text: str) -> list[Event]:
    """`perf script -F comm,tid,cpu,time,event,trace` output as events, in time order."""
    out = []
    for line in text.splitlines():
        m = _LINE.match(line)
        if m is None:
            continue
        rest = m.group("rest").replace(" ==> ", " ")
        out.append(
            Event(
                float(m.group("t")),
                m.group("comm"),
                int(m.group("tid")),
                int(m.group("cpu")),
                m.group("name").split(":")[-1],
                dict(_KV.findall(rest)),
            )
        )
    out.sort(key=lambda e: e.t_s)
    return out


def classify(
    events: list[Event],
    window: tuple[str, float, float],
    cycle_tid: int,
    process_tids: set[int],
    margin_s: float,
) -> dict[str, Any]:
    """The causes of one marked window (`late`: from its deadline to its first bytecode;
    `slow`: from its first bytecode to its end), in seconds of CLOCK_MONOTONIC. A late
    cycle's wake-up is due `margin_s` before its deadline (the clock spins from there)."""
    kind, start, end = window
    due = start - margin_s
    begin = due if kind == "late" else start
    tid = str(cycle_tid)
    seen: Counter[str] = Counter()
    detail: list[str] = []
    asleep = False
    timer_checked = kind != "late"
    for e in events:
        if e.t_s < due - 0.001:
            continue
        if e.t_s > end:
            break
        f = e.fields
        if e.name == "sched_waking" and f.get("pid") == tid:
            if not timer_checked and e.t_s >= due - 0.0005:  # the wake-up of the clock's sleep
                timer_checked = True
                if e.t_s > due + TIMER_SLACK_S:
                    seen["timer_late"] += 1
                    detail.append(f"woken {1e6 * (e.t_s - due):.0f} us after due")
            elif asleep:
                asleep = False
                if e.tid in process_tids and e.tid != cycle_tid:
                    seen["gil"] += 1
                    detail.append(f"woken by thread {e.tid} of its process")
                else:
                    seen["blocked"] += 1
                    detail.append(f"woken by {e.comm}/{e.tid}")
        elif e.name == "sched_switch" and f.get("prev_pid") == tid and e.t_s >= begin:
            state = f.get("prev_state", "")
            if state.startswith("R"):
                seen["preempted"] += 1
                detail.append(f"preempted by {f.get('next_comm')}/{f.get('next_pid')}")
            else:
                asleep = True
        elif e.name == "page_fault_user" and e.tid == cycle_tid and e.t_s >= begin:
            seen["page_faults"] += 1
    if seen["page_faults"]:
        detail.append(f"{seen['page_faults']} page faults")
    causes = [c for c in CAUSES if seen[c]] or ["host" if kind == "late" else "cpu"]
    return {"kind": kind, "start_s": start, "us": round(1e6 * (end - start), 1), "causes": causes, "detail": detail[:6]}


def record_command(data: Path, cpu: int | None) -> list[str]:
    """`perf record …` to put in front of the loop's command (BadInput when perf is missing)."""
    perf = shutil.which("perf")
    if perf is None:
        raise BadInput("--trace needs perf (Debian: apt install linux-perf)", path="--trace")
    cmd = [perf, "record", "-q", "-o", str(data), "-k", "CLOCK_MONOTONIC"]
    for ev in EVENTS:
        cmd += ["-e", ev]
    cmd += ["-C", str(cpu)] if cpu is not None else ["-a"]
    return [*cmd, "--"]


def analyse(data: Path, loop: dict[str, Any], margin_s: float) -> dict[str, Any]:
    """The trace in `data` against the windows the loop marked (its JSON from rig.bench_loop)."""
    r = subprocess.run(
        ["perf", "script", "-i", str(data), "-F", "comm,tid,cpu,time,event,trace"], capture_output=True, text=True
    )
    if r.returncode != 0:
        raise RuntimeError("perf script failed: " + (r.stderr.strip().splitlines() or ["?"])[-1])
    events = parse(r.stdout)
    spans = loop["spans_ns"]
    windows = [("late", a / 1e9, b / 1e9) for a, b in zip(*spans["late"], strict=True)]
    windows += [("slow", a / 1e9, b / 1e9) for a, b in zip(*spans["slow"], strict=True)]
    windows.sort(key=lambda w: w[1])
    tids = set(loop["process_tids"])
    rows = [classify(events, w, loop["cycle_tid"], tids, margin_s) for w in windows]
    summary: dict[str, dict[str, int]] = {}
    for kind in ("late", "slow"):
        c = Counter(cause for row in rows if row["kind"] == kind for cause in row["causes"])
        summary[kind] = {"cycles": sum(1 for row in rows if row["kind"] == kind), **{k: c[k] for k in CAUSES}}
    return {"events": len(events), "summary": summary, "windows": rows}


def summary_line(summary: dict[str, dict[str, int]]) -> str:
    """One line of `analyse`'s summary: per kind of window, how many and their causes."""
    parts = []
    for kind in ("late", "slow"):
        s = summary[kind]
        causes = ", ".join(f"{k} {s[k]}" for k in CAUSES if s[k])
        parts.append(f"{s['cycles']} {kind} ({causes or 'none'})")
    return "kernel trace of the cycle's CPU: " + "; ".join(parts)
