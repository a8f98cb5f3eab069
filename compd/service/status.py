"""Live status of a running daemon: a JSON snapshot written atomically, and `compd status`.

The cycle writes its status record every cycle (compd/cycle/statusblock.py); the service
(compd/daemon/host.py, a process of its own on the wall clock) composes the snapshot from
it about once a second and writes it with `write_atomic` (temp file + rename, so a
reader never sees half a file). `snapshot` composes one in process, through the same
record. `compd status` reads it back with `read_status`, judges whether the daemon is
alive (`liveness`) and prints it (`render`) or passes the JSON through.

The service writes on whether the cycle runs or not, so the snapshot says how old the
cycle's record is (`record_age_s`, monotonic time since its write count last moved) and,
past `stale_after_s`, `state: stale` (`mark_stale`): a cycle stopped (SIGSTOP) or hung is
never shown as running, on any channel (status file, metrics, Sparkplug, OPC UA).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from compd.core.errors import BadInput
from compd.cycle.statusblock import (
    DEFAULT_PATH,
    RELOAD_STALE_S,
    SCHEMA,
    STALE,
    STALE_MIN_S,
    STALE_PERIODS,
    StatusBlock,
    compose,
    describe,
)
from compd.io.histogram import bin_percentiles, over_range, percentile_text, range_limit_us

if TYPE_CHECKING:
    from compd.config import Config
    from compd.cycle.loop import Loop


def stale_after_s(period_s: float, state: str) -> float | None:
    """How long (monotonic s) the cycle's record may stay unwritten before the status calls it
    stale, for a loop of `period_s` whose record says `state`; None: never (the loop is not
    meant to run: stopping, stopped)."""
    if state == "reloading":
        return RELOAD_STALE_S
    if state in ("starting", "running"):
        return max(STALE_PERIODS * period_s, STALE_MIN_S)
    return None


def mark_stale(snap: dict[str, Any]) -> None:
    """Make a snapshot of a stale record say so (see the module): `state` stale, and each axis's
    and contribution's state too, the record's own kept as `last_state`, so that nothing shows an
    axis `normal` that nobody computes any more; each axis's `enable` null (not confirmed: what
    the machine holds now is not known), but false in observe mode (its word is 0)."""
    snap["state"] = STALE
    observe = bool(snap.get("observe"))
    for a in (snap.get("axes") or {}).values():
        a["last_state"], a["state"] = a.get("state"), STALE
        if not observe:
            a["enable"] = None
        for c in (a.get("contributions") or {}).values():
            c["last_state"], c["state"] = c.get("state"), STALE


def timing(stats: Any) -> dict[str, Any]:
    """The loop's timing figures (the names of the bench JSON), with numpy percentiles (≈ 50 µs).

    `over_range`: per percentile group, the keys whose quantile fell in the histogram's
    overflow bin; their value is the range limit (20000 µs), the true one is above it."""
    p50, p99, p999 = bin_percentiles(stats.hist, (0.5, 0.99, 0.999))
    c50, c99 = bin_percentiles(stats.compute_hist, (0.5, 0.99))
    late = {"p50": p50, "p99": p99, "p999": p999, "max": round(stats.late_max_s * 1e6, 1)}
    compute = {"p50": c50, "p99": c99, "max": round(stats.compute_max_ns / 1000, 1)}
    return {
        "period_ms": stats.period_s * 1000.0,
        "cycles": int(stats.cycles),
        "misses": int(stats.misses),
        "skipped": int(stats.skipped),
        "lateness_us": late,
        "cycle_compute_us": compute,
        "over_range": timing_over_range(late, compute, range_limit_us(stats.hist)),
        "stages": stats.stages(),
    }


def timing_over_range(late: dict[str, Any], compute: dict[str, Any], limit_us: float) -> dict[str, list[str]]:
    """`over_range` of the loop's timing: the percentiles of `lateness_us` and `cycle_compute_us`
    at the histogram's range limit `limit_us` (not measurements: the true value is above)."""
    return {"lateness_us": over_range(late, limit_us), "cycle_compute_us": over_range(compute, limit_us)}


def _over(loop: dict[str, Any], group: str, key: str) -> bool:
    """Whether percentile `key` of `group` (`lateness_us`, `cycle_compute_us`) of a status's
    `loop` is over the histogram's range (a status without `over_range`: not known, False)."""
    over = loop.get("over_range")
    return isinstance(over, dict) and key in (over.get(group) or ())


def lateness_buckets(stats: Any, bounds_us: tuple[float, ...]) -> tuple[list[tuple[float, int]], int, float]:
    """Cumulative lateness counts at each bound (µs), the count and an estimated sum (s).

    For a histogram metric; all three come from one copy of the loop's histogram.

    Bin i of the loop's histogram holds lateness in [i, i+1) µs; the sum takes each
    bin's middle, so it is exact to ±0.5 µs per cycle.
    """
    counts = np.frombuffer(stats.hist, dtype=np.int64).copy()
    cum = np.cumsum(counts)
    out = []
    for b in bounds_us:
        i = int(b)  # bins 0..b-1 are all below b µs
        out.append((b, int(cum[min(i, cum.size) - 1]) if i > 0 else 0))
    total_us = float((counts * (np.arange(counts.size) + 0.5)).sum())  # np.dot of int·float is slow
    return out, int(cum[-1]), total_us * 1e-6


def snapshot(loop: Loop, *, state: str, observe: bool, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The status of `loop` now, composed in this process the way the service composes it
    (a record written and read back, the devices described from the pipeline's objects)."""
    block = StatusBlock(loop)
    block.state = state
    block.write()
    reading = block.read()
    assert reading is not None  # written just now, by this thread
    snap = compose(reading, describe(loop, observe))
    snap.update(extra or {})
    return snap


def jsonable(value: Any) -> Any:
    """NaN and infinities become None (JSON has neither); numpy scalars become Python numbers."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to `path` through a temp file and a rename; readable by everyone (0644)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1, sort_keys=False)
        fh.write("\n")
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def read_status(path: str | Path) -> dict[str, Any]:
    """Read a status file; a missing or unreadable one is BadInput naming the file."""
    path = str(path)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise BadInput("no status file (is compd running, with a status path?)", file=path) from None
    except OSError as e:
        raise BadInput(f"cannot read status: {e.strerror or e}", file=path) from None
    except json.JSONDecodeError as e:
        raise BadInput(f"not a status file: {e.msg}", file=path, line=e.lineno) from None
    except (UnicodeDecodeError, ValueError):  # binary, or numbers JSON cannot hold
        raise BadInput("not a status file: not UTF-8 JSON text", file=path) from None
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise BadInput("not a compd status file (schema)", file=path)
    _check_shape(data, path)
    return data


# What `liveness` and `render` read, and the JSON type each must have (None is allowed too).
_NUMBER = (int, float)
_SHAPE: dict[str, tuple[type, ...]] = {
    "pid": (int,),
    "state": (str,),
    "observe": (bool,),
    "written_unix_s": _NUMBER,
    "status_period_s": _NUMBER,
    "uptime_s": _NUMBER,
    "loop_time_s": _NUMBER,
    "word": (str,),
    "word_at_machine": (str,),
    "config": (str,),
    "metrics_url": (str,),
    "version": (str,),
    "axes": (dict,),
    "signals": (dict,),
    "loop": (dict,),
    "model": (dict,),
    "sink": (dict,),
    "faults": (dict,),
    "events": (list,),
    "adapt": (dict,),
    "sources": (list,),
    "record_age_s": _NUMBER,
    "stale_after_s": _NUMBER,
}


_NAMES = {int: "an integer", str: "a string", bool: "true or false", dict: "an object", list: "a list"}


def _check_shape(data: dict[str, Any], path: str) -> None:
    """BadInput naming the key whose JSON type is not what a status snapshot holds."""
    for key, types in _SHAPE.items():
        v = data.get(key)
        if v is not None and (not isinstance(v, types) or (types is _NUMBER and isinstance(v, bool))):
            want = "a number" if types is _NUMBER else _NAMES[types[0]]
            raise BadInput(f"not a compd status file: expected {want}", file=path, path=key)
    for key in ("axes", "signals", "adapt"):
        for name, v in (data.get(key) or {}).items():
            if not isinstance(v, dict):
                raise BadInput("not a compd status file: expected an object", file=path, path=(key, name))
    for key in ("events", "sources"):
        for i, e in enumerate(data.get(key) or []):
            if not isinstance(e, dict):
                raise BadInput("not a compd status file: expected an object", file=path, path=(key, i))
    for key in ("lateness_us",):
        v = (data.get("loop") or {}).get(key)
        if v is not None and not isinstance(v, dict):
            raise BadInput("not a compd status file: expected an object", file=path, path=("loop", key))
    model = data.get("model") or {}
    for key in ("inputs", "outputs"):
        v = model.get(key)
        if v is not None and not (isinstance(v, list) and all(isinstance(n, str) for n in v)):
            raise BadInput("not a compd status file: expected a list of names", file=path, path=("model", key))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process, but it exists
    return True


def _gone(data: dict[str, Any], now_unix_s: float | None) -> str | None:
    """Why no compd process writes this status file any more (stopped, its pid gone, the file
    not updated within max(3 periods, 5 s)), or None: one does."""
    now = time.time() if now_unix_s is None else now_unix_s
    age = now - float(data.get("written_unix_s", 0.0))
    limit = max(3.0 * float(data.get("status_period_s", 1.0)), 5.0)
    if data.get("state", "?") == "stopped":
        return f"stopped ({age:.0f} s ago)"
    pid = data.get("pid")
    if isinstance(pid, int) and not _pid_alive(pid):
        return f"not running: pid {pid} is gone (last update {age:.0f} s ago)"
    if age > limit:
        return f"stale: no update for {age:.0f} s (hung?)"
    return None


def liveness(data: dict[str, Any], now_unix_s: float | None = None) -> tuple[bool, str]:
    """(alive, why): running and updated within max(3 periods, 5 s), by a process that exists,
    whose cycle writes its record (not `stale`: the service writes on for a stopped or hung cycle)."""
    gone = _gone(data, now_unix_s)
    if gone is not None:
        return False, gone
    state = data.get("state", "?")
    if state == STALE:
        age = data.get("record_age_s")
        for_s = f" for {age:.1f} s" if isinstance(age, int | float) else ""
        return False, f"stale: the cycle has not run{for_s} (stopped or hung?; its service still writes the status)"
    if state == "reloading":
        age = data.get("record_age_s")
        return True, f"reloading (the loop paused {age:.1f} s ago)" if isinstance(age, int | float) else state
    return True, state


def held(data: dict[str, Any], now_unix_s: float | None = None) -> bool:
    """Whether a compd process still holds what this status file is of (its devices, its status
    file): alive, or with a stale cycle — stopped or hung, it may run again."""
    return _gone(data, now_unix_s) is None


def _hms(seconds: float | None) -> str:
    s = int(seconds or 0)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _enabled(value: Any) -> str:
    """An axis's `enable` at the machine: yes, no, or `unknown` (null: the link is not up)."""
    return "unknown" if value is None else "yes" if value else "no"


def _num(value: Any, fmt: str) -> str:
    return "nan" if value is None else format(value, fmt)


def _short(value: Any) -> str:
    """A coefficient as text: numbers as given (already rounded), lists and mappings compact."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_short(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    return "-" if value is None else f"{value:g}" if isinstance(value, float) else str(value)


def _model_lines(model: dict[str, Any]) -> list[str]:
    """What is running, per axis: the file, kind, fit date and score, key coefficients, the
    latched start temperatures (T0)."""
    parts = model.get("contributions")
    if isinstance(parts, list):  # a sum of contributions: each one's own model
        out = []
        for p in parts:
            if isinstance(p, dict):
                out.append(
                    f"  contribution {p.get('name')}: {p.get('kind')} ({', '.join(p.get('inputs') or [])}"
                    f" -> {', '.join(p.get('outputs') or [])})"
                )
                own = (model.get("state") or {}).get(p.get("name"))  # the sum's state is the newest, by name
                out += [
                    "  " + ln
                    for ln in _model_lines(
                        {**p, "contributions": None, "state": own if isinstance(own, dict) else p.get("state")}
                    )
                ]
        return out
    fit = model.get("fit") or {}
    coef = dict(model.get("coefficients") or {})
    lines = [
        f"  file: {model.get('file') or '(inline params in the config)'};"
        f" fitted {fit.get('fitted_at') or 'unknown (no fit date in the file)'}"
        + (f" on {fit['log']} ({fit.get('rows', '?')} rows)" if fit.get("log") else "")
        + (f" by compd {fit['compd_version']}" if fit.get("compd_version") else "")
    ]
    rmse = fit.get("rmse_um") or {}
    per_axis = {
        k: v for k, v in coef.items() if isinstance(v, dict) and set(v) <= set(model.get("outputs") or []) and v
    }
    for axis in model.get("outputs") or []:
        parts = [f"{model.get('kind')}"]
        if isinstance(rmse, dict) and rmse.get(axis) is not None:
            parts.append(f"fit RMSE {rmse[axis]:.3g} um")
        parts += [f"{k} {_short(v[axis])}" for k, v in per_axis.items() if axis in v]
        lines.append(f"  axis {axis}: " + ", ".join(parts))
    rest = {k: v for k, v in coef.items() if k not in per_axis}
    if rest:
        lines.append("  coefficients: " + ", ".join(f"{k} {_short(v)}" for k, v in rest.items()))
    state = model.get("state") or {}
    t0 = state.get("t0_c")
    inputs = model.get("inputs") or []
    if isinstance(t0, list) and len(t0) == len(inputs):
        lines.append(
            "  T0 (latched at start): " + ", ".join(f"{n} {_short(v)} C" for n, v in zip(inputs, t0, strict=True))
        )
    elif t0 is not None:
        lines.append(f"  T0 (latched at start): {_short(t0)} C")
    elif "t0_c" in state:
        lines.append("  T0 (latched at start): not yet (no good input vector so far)")
    other = {k: v for k, v in state.items() if k != "t0_c" and v is not None}
    if other:
        lines.append("  model state: " + ", ".join(f"{k} {_short(v)}" for k, v in other.items()))
    return lines


def _plant_lines(data: dict[str, Any]) -> list[str]:
    """The telemetry and OPC UA lines (docs/plant.md), when the config has them."""
    out = []
    tel = data.get("telemetry")
    if isinstance(tel, dict):
        state = "connected" if tel.get("connected") else f"NOT CONNECTED ({tel.get('last_error') or 'connecting'})"
        line = (
            f"telemetry: {tel.get('broker')} {state}; {tel.get('acknowledged', 0)} acknowledged,"
            f" {tel.get('buffered', 0)} buffered, {tel.get('dropped', 0)} dropped"
        )
        if tel.get("buffer") == "memory":  # the buffer's file cannot be used: live, samples wait in memory
            line += f"; BUFFER IN MEMORY ({tel.get('buffer_error')}): the file is tried again"
        out.append(line)
    ua = data.get("opcua")
    if isinstance(ua, dict):
        out.append(f"opcua: {ua.get('endpoint')}" if ua.get("endpoint") else f"opcua: OFF ({ua.get('error')})")
    return out


def render(data: dict[str, Any], alive: bool, why: str) -> str:
    """The human view of a status snapshot."""
    lines = []
    head = f"compd {why}"
    head += f" — pid {data.get('pid')}, up {_hms(data.get('uptime_s'))} loop time"
    head += f", compd {data.get('version') or 'version unknown'}"
    if data.get("observe"):
        head += ", OBSERVE MODE (output held disabled)"
    lines.append(head)
    if data.get("state") == STALE:  # the service writes on; nothing of the cycle's below is live
        last = ", ".join(
            f"{n} {a.get('last_state')}" for n, a in (data.get("axes") or {}).items() if isinstance(a, dict)
        )
        lines.append(
            f"CYCLE STALE: no record from the cycle for {_num(data.get('record_age_s'), '.1f')} s (stale after"
            f" {_num(data.get('stale_after_s'), 'g')} s): what follows is its last record, not live"
            + (f"; the axes' last states: {last}" if last else "")
        )
    if data.get("config"):
        lines.append(f"config: {data['config']}")
    lp = data.get("loop", {})
    lt = lp.get("lateness_us", {})

    def late(key: str) -> str:  # `>20 ms` for a percentile over the histogram's range
        return percentile_text(lt.get(key, 0), _over(lp, "lateness_us", key))

    lines.append(
        f"loop: period {lp.get('period_ms', 0):g} ms, {lp.get('cycles', 0)} cycles,"
        f" {lp.get('misses', 0)} missed, {lp.get('skipped', 0)} skipped;"
        f" lateness p50 {late('p50')}, p99 {late('p99')}, p99.9 {late('p999')}, max {lt.get('max', 0):g} us"
    )
    model = data.get("model", {})
    lines.append(
        f"model: {model.get('kind')} ({', '.join(model.get('inputs', []))} -> {', '.join(model.get('outputs', []))})"
    )
    lines.extend(_model_lines(model))
    sink = data.get("sink", {})
    computed = data.get("word")
    at_machine = data.get("word_at_machine", sink.get("word"))  # a status without it: the sink's own
    if data.get("observe"):  # the computed word is held back: never shown as if the machine had it
        word = f"word: {computed} computed, held back by observe mode (on the output: {at_machine or '0x0000'})"
    else:
        word = f"word: {computed}"
        if at_machine is not None and at_machine != computed:
            word += f" (on the output: {at_machine})"
    link = sink.get("link")
    lines.append(
        f"{word}; sink {sink.get('kind')}, link {link if link in (None, 'up') else str(link).upper()},"
        f" {sink.get('writes', 0)} writes"
    )
    if link not in (None, "up"):
        lines.append(f"OUTPUT NOT REACHING THE MACHINE: the sink's link is {link} (axes shown disabled)")
    lines.append(
        f"{'axis':<8} {'predicted':>10} {'correction':>11} {'target':>9} {'byte':>5} {'enabled':>8}"
        f" {'state':<11} {'policy':<13} sat"
    )
    for name, a in data.get("axes", {}).items():
        lines.append(
            f"{name:<8} {_num(a.get('prediction_um'), '10.2f')} {_num(a.get('correction_um'), '11.2f')}"
            f" {_num(a.get('target_um'), '9.2f')} {a.get('byte') or '-':>5}"
            f" {_enabled(a.get('enable')):>8}"
            f" {str(a.get('inhibit') or a.get('state', '?')):<11} {a.get('policy', '?'):<13}"
            f" {'yes' if a.get('saturated') else 'no'}"
        )
        for part, c in (a.get("contributions") or {}).items():  # a sum of contributions: each one's share
            lines.append(
                f"  + {part:<16} {_num(c.get('prediction_um'), '10.2f')} (its model {_num(c.get('raw_um'), '.2f')})"
                f" {c.get('state', '?')}{' clamped' if c.get('clamped') else ''}"
            )
    shadow = data.get("shadow")
    if isinstance(shadow, dict):  # the candidate beside the model, driving nothing
        sm = shadow.get("model") or {}
        lines.append(
            f"shadow: {sm.get('kind', '?')}"
            + (f" {sm['file']}" if sm.get("file") else "")
            + " (drives nothing; scored on the probes)"
        )
        for axis, sc in (shadow.get("axes") or {}).items():
            pred = (data.get("axes", {}).get(axis) or {}).get("shadow_um")
            lines.append(
                f"  {axis:<6} predicts {_num(pred, '.2f')} um; {sc.get('probes', 0)} probes: RMS active"
                f" {_num(sc.get('active_rms_um'), '.2f')} um, shadow {_num(sc.get('shadow_rms_um'), '.2f')} um"
            )
    lines.append(f"{'signal':<14} {'value':>10} {'quality':<13} {'age_s':>8}")
    for name, s in data.get("signals", {}).items():
        lines.append(
            f"{name:<14} {_num(s.get('value'), '10.3f')} {s.get('quality', '?'):<13} {_num(s.get('age_s'), '8.2f')}"
        )
    for src in data.get("sources") or []:
        if src.get("last_error"):  # why a device's signals are lost, as its I/O worker logged it
            lines.append(f"source {src.get('name')} ({src.get('kind')}): last error: {src['last_error']}")
    adapt = data.get("adapt") or {}
    if adapt:
        lines.append(f"{'adapt':<8} {'offset':>17} {'gain':>7} {'accepted':>9} {'rejected':>9} {'last probe':>11}")
        for name, e in adapt.items():
            gain = e.get("gain")
            last = e.get("last_probe_s")
            note = "" if e.get("applied", True) else " (observe: not applied)"
            if e.get("slope_um_per_m") is not None:
                note += f" slope {e['slope_um_per_m']:+.2f} um/m"
            if e.get("fault"):
                note += " FAULT: probes rejected in a row"
            lines.append(
                f"{name:<8} {_num(e.get('offset_um'), '+8.2f')} ± {_num(e.get('offset_sigma_um'), '5.2f')} um"
                f" {'-' if gain is None else format(gain, '+7.3f'):>7} {e.get('accepted', 0):>9}"
                f" {e.get('rejected', 0):>9} {'never' if last is None else format(last, '.1f') + ' s':>11}{note}"
            )
    faults = data.get("faults") or {}
    lines.append("faults: " + (", ".join(f"{k} {v}" for k, v in sorted(faults.items())) or "none"))
    events = data.get("events") or []
    if events:
        lines.append("recent events:")
        for e in events[-5:]:
            lines.append(f"  t={_num(e.get('t_s'), '.1f')} s {e.get('subject')} {e.get('event')} ({e.get('reason')})")
    if data.get("metrics_url"):
        lines.append(f"metrics: {data['metrics_url']}")
    lines.extend(_plant_lines(data))
    lines.extend(_process_lines(data))
    return "\n".join(lines)


def _process_lines(data: dict[str, Any]) -> list[str]:
    """Which process does what: the cycle's (and its threads of Python), the service's, each
    device's I/O (docs/architecture.md, "Processes")."""
    pid, service = data.get("pid"), data.get("service_pid")
    if pid is None or service is None:
        return []
    threads = data.get("threads") or []
    line = f"processes: cycle {pid} ({len(threads)} thread{'s' if len(threads) != 1 else ''} of Python)"
    line += ", service " + ("in it" if service == pid else str(service))
    io = [f"{s.get('name')} {s['io_pid']}" for s in data.get("sources") or [] if s.get("io_pid") not in (None, pid)]
    if io:
        line += ", device I/O: " + ", ".join(io)
    out = [line]
    # what the supervisor says of each (compd/io/supervisor.py): lost ones and restarts
    for p in data.get("processes") or []:
        if not p.get("up"):
            out.append(f"PROCESS LOST: {p.get('name')} (pid {p.get('pid')}) {p.get('lost')}: restarting")
        elif p.get("restarts"):
            n = p["restarts"]
            out.append(
                f"process {p.get('name')} restarted {n} time{'s' if n != 1 else ''} (last lost: {p.get('lost')})"
            )
    return out


def status_path(cfg: Config, env: dict[str, str] | None = None) -> Path | None:
    """The status file: `status.path` (relative to the config), else $RUNTIME_DIRECTORY/status.json."""
    env = dict(os.environ) if env is None else env
    if cfg.top.status.path:
        return cfg.resolve_path(cfg.top.status.path)
    runtime = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    return Path(runtime) / "status.json" if runtime else None


def daemon_status_path(cfg: Config) -> Path:
    """Where the daemon of `cfg` writes its status, as another process finds it: `status.path`,
    else where the systemd units put it (RuntimeDirectory `compd` for compd.yaml, `compd/NAME`
    for the instance compd@NAME)."""
    found = status_path(cfg, env={})
    if found is not None:
        return found
    stem = Path(cfg.file).stem
    return Path(DEFAULT_PATH if stem == "compd" else f"/run/compd/{stem}/status.json")
