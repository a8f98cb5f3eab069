"""`compd bench`: the 2 ms cycle against real Modbus devices, beside the loop a user writes by hand.

compd's CLI parses the command and reaches `main` here through the `compd.commands`
entry point (pyproject.toml): the bench needs the simulator, which compd does not.

The devices run in a separate process (`python -m hil_sim serve`): three 8-channel
PT100 Modbus TCP modules carrying the gantry's 19 sensors (paper 002: 9 per axis plus
ambient), and the FANUC PMC software PLC. compd's own loop runs the LVR model of the
gantry (fitted here on a short simulated warm-up) against them; then, in the same run,
the naive loop — `while True:` one request per register, predict, write, sleep(period)
— against the same devices. Timing is from the cycle's own statistics; memory is the
resident size after warm-up and at the end.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from compd.core.clock import WallClock
from compd.core.errors import BadInput
from compd.identify import FITS
from compd.io.histogram import percentile_text
from hil_sim.plants import PLANTS
from hil_sim.scenario import SCENARIOS, Scenario

N_SENSORS = 19
MODULE_CHANNELS = 8
DAY_S = 86400.0
HOST = "127.0.0.1"  # where the bench serves its simulated devices
CHECK_TIMEOUT_S = 5.0  # each device must answer one read within this before the loops start (a loaded PC is slow)
NAIVE_TIMEOUT_S = 0.25  # the hand-written loop's timeout per request, and its retries after the first try
NAIVE_RETRIES = 3
SERVE = "the simulated devices (python -m hil_sim serve)"


class DeviceSilent(Exception):
    """A device the bench serves did not answer: the message names it, where it listens and what timed
    out. `compd bench` prints it as one line and exits 1, as `compd output-test` does for a device that
    does not answer."""


def _modbus_fault(name: str, port: int, what: str, error: Exception, timeout_s: float, tries: int) -> DeviceSilent:
    """The one-line error for a request to device `name` that raised `error` (pymodbus)."""
    from pymodbus.exceptions import ConnectionException

    if isinstance(error, ConnectionException):
        return DeviceSilent(f"{name} at {HOST}:{port} lost the connection during {what}: {SERVE} stopped serving")
    tried = f"{tries} tries of {timeout_s:g} s" if tries > 1 else f"{timeout_s:g} s"
    return DeviceSilent(
        f"{name} at {HOST}:{port} did not answer {what} within {tried}: {SERVE} stopped"
        " answering; is the PC too loaded to serve them?"
    )


def _quiet_pymodbus() -> None:
    """pymodbus logs every timeout itself; the bench reports its own one line instead."""
    import logging

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def bench_devices(sensors: list[str]) -> list[str]:
    """The devices compd's and the naive loop talk to: the PT100 modules, then the PMC."""
    return [f"pt100_{m // MODULE_CHANNELS + 1}" for m in range(0, len(sensors), MODULE_CHANNELS)] + ["pmc"]


def check_devices(names: list[str], ports: dict[str, int], timeout_s: float | None = None) -> None:
    """Each device answers one read of holding register 0 (unit 1) within `timeout_s` (default
    CHECK_TIMEOUT_S), or DeviceSilent naming the first that does not: a bench against silent devices
    would time nothing but timeouts."""
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException

    _quiet_pymodbus()
    timeout_s = CHECK_TIMEOUT_S if timeout_s is None else timeout_s
    for name in names:
        port = ports.get(name)
        if port is None:
            raise DeviceSilent(f"{name}: {SERVE} did not say where it listens")
        client = ModbusTcpClient(HOST, port=port, timeout=timeout_s, retries=0)
        try:
            if not client.connect():
                raise DeviceSilent(
                    f"{name} at {HOST}:{port}: no connection within {timeout_s:g} s (nothing"
                    f" listens there): {SERVE} are not serving"
                )
            try:
                client.read_holding_registers(0, count=1, device_id=1)
            except ModbusException as e:
                raise _modbus_fault(name, port, "a read of holding register 0 (unit 1)", e, timeout_s, 1) from None
        finally:
            client.close()


def _fit_gantry_model(work: Path) -> tuple[Path, list[str]]:
    """A short simulated gantry warm-up, logged and fitted with LVR (the bench's model)."""
    from compd.log import read_log, write_log
    from compd.models.lvr import LVR

    scen = Scenario.load(SCENARIOS / "gantry_train.yaml")
    plant = PLANTS.get("gantry")(scen, scen.params)
    rows = []
    for t in range(0, 6 * 3600 + 1, 30):
        plant.advance_to(t)
        rows.append([t, *plant.sample()])
    log_path = work / "gantry_warmup.csv"
    write_log(log_path, ["t_s", *plant.signal_names], np.array(rows))
    log = read_log(log_path)
    temps = log.temperature_columns()[:N_SENSORS]
    model = FITS.get(LVR.kind)(log, temps, None).model
    path = work / "gantry_lvr.yaml"
    path.write_text(yaml.safe_dump(model.to_dict(), sort_keys=False))
    return path, temps


def plant_speedup(cycles: int, period_s: float) -> float:
    """Plant seconds per wall second so the run covers a working day (capped at 1200x)."""
    return min(max(DAY_S / (cycles * period_s), 1.0), 1200.0)


def _device_file(work: Path, sensors: list[str], speedup: float) -> Path:
    """Three PT100 modules fed by a live gantry plant on its unseen day, and the PMC.

    The temperatures move as the machine warms and cools, so the model's output and
    the word sent to the PMC change during the run (the output path is exercised).
    """
    modules = []
    for m in range(0, len(sensors), MODULE_CHANNELS):
        names = sensors[m : m + MODULE_CHANNELS]
        channels: list[dict[str, Any]] = [{"name": n} for n in names]
        modules.append(
            {
                "kind": "pt100_modbus",
                "name": f"pt100_{m // MODULE_CHANNELS + 1}",
                "transport": "tcp",
                "host": "127.0.0.1",
                "port": 0,
                "plant": "gantry",
                "channels": channels,
            }
        )
    plant = {
        "kind": "plant",
        "name": "gantry",
        "scenario": str(SCENARIOS / "gantry_unseen.yaml"),
        "port": 0,
        "speedup": speedup,
        "wall_step_s": 0.02,
    }
    devices = {"devices": [*modules, {"kind": "fanuc_pmc", "name": "pmc", "host": "127.0.0.1", "port": 0}, plant]}
    path = work / "bench_devices.yaml"
    path.write_text(yaml.safe_dump(devices, sort_keys=False))
    return path


DEVICE_NICE = 10


def cycle_cpu() -> int | None:
    """The CPU the cycle thread is pinned to with `scheduler: fifo` (the last one); None on one CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) > 1 else None


def _lower_priority() -> None:
    os.nice(DEVICE_NICE)
    # the devices stand in for hardware: keep them off the cycle thread's CPU
    cpu = cycle_cpu()
    if cpu is not None:
        os.sched_setaffinity(0, set(os.sched_getaffinity(0)) - {cpu})


class Devices:
    """`python -m hil_sim serve` in a child process; parses where each device listens."""

    def __init__(self, device_file: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil_sim", "serve", "--config", str(device_file)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            # The devices stand in for hardware that does not share compd's CPU: they
            # run at a lower priority so the simulation competes as little as it can.
            preexec_fn=_lower_priority,
        )
        self.ports: dict[str, int] = {}
        assert self.proc.stdout is not None
        deadline = time.monotonic() + 30
        lines = []
        for line in self.proc.stdout:
            lines.append(line.rstrip())
            if ": " in line and " on " in line:
                name, rest = line.split(": ", 1)
                where = rest.split(" on ", 1)[1].strip()
                if ":" in where:
                    self.ports[name] = int(where.rsplit(":", 1)[1].split()[0])
            if "ready" in line or time.monotonic() > deadline:
                break
        if "ready" not in "".join(lines[-1:]):
            self.stop()
            raise DeviceSilent(f"{SERVE} did not start: " + (" | ".join(lines[-3:]) or "it printed nothing"))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def _compd_config(
    work: Path,
    model_path: Path,
    sensors: list[str],
    ports: dict[str, int],
    scheduler: str,
    period_s: float,
    io: str = "process",
) -> Path:
    realtime: dict[str, Any] = {"scheduler": scheduler, "priority": 50}
    if scheduler == "fifo":
        # what a real-time deployment sets (docs/commissioning.md): memory locked, and the
        # cycle thread on a CPU of its own (the simulated devices are kept off it)
        realtime["lock_memory"] = True
        cpu = cycle_cpu()
        if cpu is not None:
            realtime["cpu_affinity"] = [cpu]
    sources = []
    for m in range(0, len(sensors), MODULE_CHANNELS):
        names = sensors[m : m + MODULE_CHANNELS]
        sources.append(
            {
                "kind": "modbus",
                "name": f"pt100_{m // MODULE_CHANNELS + 1}",
                "transport": "tcp",
                "host": "127.0.0.1",
                "port": ports[f"pt100_{m // MODULE_CHANNELS + 1}"],
                "data_type": "int16",
                "scale": 0.1,
                "poll_period_s": 0.05,
                "timeout_s": 0.25,
                "channels": [{"name": n, "address": i} for i, n in enumerate(names)],
            }
        )
    cfg = {
        "loop": {"period_s": period_s, "io": io, "realtime": realtime},
        "sources": sources,
        "model": {"kind": "lvr", "file": str(model_path)},
        "guard": {"max_slew_um_per_s": 20.0, "stale_after_s": 1.0},
        "sink": {"kind": "fanuc_pmc", "mode": "word", "host": "127.0.0.1", "port": ports["pmc"]},
        # what a daemon in service runs beside its cycle: the status file, the data log, the
        # model state, the metrics endpoint (scraped every second by the bench)
        "status": {"period_s": 1.0, "path": str(work / "status.json")},
        "log": {"path": str(work / "data.csv"), "period_s": 1.0, "flush_s": 1.0},
        "state": {"path": str(work / "state.json")},
        "metrics": {"enabled": True, "port": 0},
    }
    path = work / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_naive_loop(
    model_path: Path, sensors: list[str], ports: dict[str, int], cycles: int, period_s: float
) -> dict[str, Any]:
    """The loop a user writes by hand: one request per register, predict, write, sleep(period)."""
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException

    from compd.codec import encode, word_bytes
    from compd.commissioning.fitting import load_model

    _quiet_pymodbus()
    model = load_model(str(model_path))
    clients = {}
    for name in bench_devices(sensors):
        clients[name] = ModbusTcpClient(HOST, port=ports[name], timeout=NAIVE_TIMEOUT_S, retries=NAIVE_RETRIES)
    try:
        for name, c in clients.items():
            if not c.connect():
                raise DeviceSilent(
                    f"{name} at {HOST}:{ports[name]}: the naive loop got no connection"
                    f" (nothing listens there): {SERVE} stopped serving"
                )
    except BaseException:
        for c in clients.values():
            c.close()
        raise
    pmc = clients.pop("pmc")
    x = np.zeros(len(sensors))
    out = np.zeros(2)
    lateness = np.zeros(cycles)
    compute = np.zeros(cycles)
    starts = np.zeros(cycles)
    started = False
    t0 = time.monotonic()
    try:
        for k in range(cycles):
            start = time.monotonic()
            starts[k] = start
            lateness[k] = start - (t0 + k * period_s)
            for j, _ in enumerate(sensors):
                name = f"pt100_{j // MODULE_CHANNELS + 1}"
                try:
                    rr = clients[name].read_holding_registers(j % MODULE_CHANNELS, count=1, device_id=1)
                except ModbusException as e:
                    raise _modbus_fault(
                        name,
                        ports[name],
                        f"the naive loop's read of holding register {j % MODULE_CHANNELS} (unit 1)",
                        e,
                        NAIVE_TIMEOUT_S,
                        NAIVE_RETRIES + 1,
                    ) from None
                if not rr.isError():
                    v = rr.registers[0]
                    x[j] = (v - 65536 if v > 32767 else v) * 0.1
            if not started:
                model.start(x, 0.0)
                started = True
            model.evaluate(x, 0.0, out)
            word = encode(-out[0], -out[1])
            high, low = word_bytes(word)
            try:
                pmc.write_registers(0, [low, high], device_id=1)  # X0 holds the low byte
            except ModbusException as e:
                raise _modbus_fault(
                    "pmc",
                    ports["pmc"],
                    "the naive loop's write of registers 0-1 (unit 1)",
                    e,
                    NAIVE_TIMEOUT_S,
                    NAIVE_RETRIES + 1,
                ) from None
            compute[k] = time.monotonic() - start
            time.sleep(period_s)
    finally:
        for c in clients.values():
            c.close()
        pmc.close()
    lat_us = lateness * 1e6
    intervals_us = np.diff(starts) * 1e6 if cycles > 1 else np.zeros(1)
    return {
        # what the hand-written loop achieves: start-to-start interval (it drifts off any schedule)
        "period_us": {
            "p50": float(np.percentile(intervals_us, 50)),
            "p99": float(np.percentile(intervals_us, 99)),
            "max": float(intervals_us.max()),
        },
        "cycles": cycles,
        "misses": int(np.count_nonzero((lateness > period_s / 2) | (compute > period_s))),
        "lateness_us": {
            "p50": float(np.percentile(lat_us, 50)),
            "p99": float(np.percentile(lat_us, 99)),
            "p999": float(np.percentile(lat_us, 99.9)),
            "max": float(lat_us.max()),
        },
        "cycle_compute_us": {
            "p50": float(np.percentile(compute, 50) * 1e6),
            "p99": float(np.percentile(compute, 99) * 1e6),
            "max": float(compute.max() * 1e6),
        },
    }


def run_compd_loop_child(
    config: Path,
    cycles: int,
    late_us: float,
    out: Path,
    trace: Path | None = None,
    scheduler: str = "other",
) -> dict[str, Any]:
    """rig.bench_loop in a child process (compd only in its interpreter), its metrics endpoint
    scraped every second meanwhile; its JSON. `trace`: run it under perf (rig.late_trace),
    the kernel's record kept in that file."""
    from rig import late_trace

    prefix = late_trace.record_command(trace, cycle_cpu() if scheduler == "fifo" else None) if trace else []
    scraper = Scraper(config.parent / "status.json")
    try:
        r = subprocess.run(
            [
                *prefix,
                sys.executable,
                "-m",
                "rig.bench_loop",
                str(config),
                str(cycles),
                str(late_us),
                str(out),
                *(["trace"] if trace else []),
            ],
            cwd=Path(__file__).resolve().parent.parent,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
    finally:
        scraper.stop()
    if r.returncode != 0:
        raise RuntimeError("compd's loop failed: " + (r.stderr.strip().splitlines() or ["?"])[-1])
    result = json.loads(out.read_text())
    result.pop("_tids", None)
    result["scrapes"] = scraper.scrapes
    if trace:
        result["trace"] = late_trace.analyse(trace, result, margin_s=WallClock().spin_margin_s)
    return result


class Scraper:
    """Scrapes the daemon's metrics endpoint every `period_s` (its URL from the status
    file), as a Prometheus server would, from the bench's process."""

    def __init__(self, status: Path, period_s: float = 1.0) -> None:
        self.status = status
        self.period_s = period_s
        self.scrapes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-scraper", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import urllib.request

        url = None
        while not self._stop.wait(self.period_s):
            try:
                if url is None:
                    url = json.loads(self.status.read_text())["metrics_url"]
                with urllib.request.urlopen(url, timeout=2.0) as r:
                    r.read()
                self.scrapes += 1
            except (OSError, ValueError, KeyError, TypeError):
                continue

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def run_bare_loop(cycles: int, period_s: float, scheduler: str, out: Path) -> dict[str, Any]:
    """rig.bench_bare in a child process: the machine's limit, with the loop's real-time options."""
    cpu = cycle_cpu()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "rig.bench_bare",
            str(cycles),
            repr(period_s),
            scheduler,
            "-" if cpu is None else str(cpu),
            str(out),
        ],
        cwd=Path(__file__).resolve().parent.parent,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    if r.returncode != 0:
        raise RuntimeError("the bare loop failed: " + (r.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(out.read_text())


def start_load(n: int) -> list[subprocess.Popen]:
    """`n` CPU-bound processes (a Python busy loop each) at the default priority."""
    if n < 0:
        raise BadInput("--load must be 0 or more", path="--load")
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def stop_load(hogs: list[subprocess.Popen]) -> None:
    for p in hogs:
        p.kill()
    for p in hogs:
        p.wait(timeout=10)


def run_bench(
    cycles: int = 100_000,
    *,
    period_s: float = 0.002,
    scheduler: str = "other",
    naive_cycles: int | None = None,
    model_evals: int = 2000,
    load: int = 0,
    late_us: float = 200.0,
    io: str = "process",
    bare_cycles: int | None = None,
    trace: str | None = None,
) -> dict[str, Any]:
    """The whole benchmark; returns the JSON of docs/formats.md (plus baseline, ratio, memory).

    `load`: CPU-bound processes started beside both loops (and stopped after). `late_us`:
    cycles later than this are matched against the spans of the other threads' work
    (compd.io.activity) and counted per thread in `late_attribution`. `io`: loop.io of
    compd's config (device I/O and the service in processes of their own, or threads).
    `bare_cycles` (default: as many as compd's): the bare loop's cycles, the machine's limit.
    `trace`: a JSON file for the causes of compd's late and slow cycles (rig.late_trace, perf)."""
    from rig.bench_models import model_eval_us

    if cycles < 1:
        raise BadInput("--cycles must be at least 1", path="--cycles")
    if naive_cycles is None:
        naive_cycles = min(cycles, 5000)
    if bare_cycles is None:
        bare_cycles = cycles
    with tempfile.TemporaryDirectory(prefix="compd-bench-") as tmp:
        work = Path(tmp)
        model_path, sensors = _fit_gantry_model(work)
        speedup = plant_speedup(cycles, period_s)
        devices = Devices(_device_file(work, sensors, speedup))
        try:
            check_devices(bench_devices(sensors), devices.ports)
        except BaseException:
            devices.stop()
            raise
        hogs = start_load(load)
        try:
            cfg = _compd_config(work, model_path, sensors, devices.ports, scheduler, period_s, io)
            compd = run_compd_loop_child(
                cfg, cycles, late_us, work / "loop.json", work / "perf.data" if trace else None, scheduler
            )
            attribution = compd["late_attribution"]
            bare = run_bare_loop(bare_cycles, period_s, scheduler, work / "bare.json") if bare_cycles else None
            naive = run_naive_loop(model_path, sensors, devices.ports, naive_cycles, period_s)
        finally:
            stop_load(hogs)
            devices.stop()
    evals = model_eval_us(model_evals)
    result: dict[str, Any] = {
        "period_ms": period_s * 1000,
        "cycles": compd["cycles"],
        "lateness_us": compd["lateness_us"],
        "misses": compd["misses"],
        "cycle_compute_us": compd["cycle_compute_us"],
        "over_range": compd["over_range"],
        "model_eval_us": evals,
        "scheduler": scheduler,
        "realtime": compd["realtime"],
        "skipped": compd["skipped"],
        "gc_runs": compd["gc_runs"],
        "gc_max_us": compd["gc_max_us"],
        "between_max_us": compd["between_max_us"],
        "between_overruns": compd["between_overruns"],
        "late_max_cycle": compd["late_max_cycle"],
        "stages": compd["stages"],
        "rss_kb": compd["rss"],
        "words_sent": compd["words_sent"],
        "loop_process_modules": compd["modules"],
        "io_us": compd["io_us"],
        "host": compd["host"],
        "plant_speedup": speedup,
        "load_processes": load,
        "io": io,
        "io_processes": compd["io_processes"],
        "late_attribution": attribution,
        "trace": compd["trace"]["summary"] if trace else None,
        "service": compd["service"],
        "metrics_scrapes": compd["scrapes"],
        "naive": naive,
        "bare": bare,
    }
    if trace:
        Path(trace).write_text(json.dumps(compd["trace"], indent=1))
    miss_rate = compd["misses"] / max(compd["cycles"], 1)
    naive_rate = naive["misses"] / max(naive["cycles"], 1)
    result["ratio_naive_to_compd"] = {
        "miss_rate": naive_rate / miss_rate if miss_rate > 0 else None,
        "p99_lateness": naive["lateness_us"]["p99"] / max(compd["lateness_us"]["p99"], 1.0),
    }
    if bare is not None:  # what compd adds to the machine's own lateness; the worst cycle's work over the typical
        result["ratio_compd_to_bare"] = {
            key: compd["lateness_us"][key] / max(bare["lateness_us"][key], 1.0) for key in ("p99", "p999", "max")
        }
        result["compute_max_over_p50"] = {
            "compd": compd["cycle_compute_us"]["max"] / max(compd["cycle_compute_us"]["p50"], 1.0),
            "bare": bare["cycle_compute_us"]["max"] / max(bare["cycle_compute_us"]["p50"], 1.0),
        }
    return result


def format_table(r: dict[str, Any]) -> str:
    """The human table `compd bench` prints."""
    c, n = r, r["naive"]
    # no bare loop this run (--bare-cycles 0): its column shows "-"
    b = r.get("bare") or {
        "cycles": 0,
        "misses": None,
        "lateness_us": dict.fromkeys(("p50", "p99", "p999", "max")),
        "cycle_compute_us": dict.fromkeys(("p50", "p99", "max")),
    }

    def rate(x: dict[str, Any]) -> float | None:
        return None if x["misses"] is None else 100 * x["misses"] / max(x["cycles"], 1)

    def cell(v: Any, fmt: str) -> str:
        return f"{'-' if v is None else format(v, fmt):>14}"

    over = r.get("over_range") or {}

    def compd_cell(group: str, key: str) -> str:  # compd's histogram: `>20 ms` over its range
        if key in (over.get(group) or ()):
            return f"{percentile_text(c[group][key], True):>14}"
        return f"{c[group][key]:>14.0f}"

    lines = [
        f"compd bench: {r['cycles']} cycles at {r['period_ms']:g} ms, scheduler {r['scheduler']}"
        f" ({'; '.join(r['realtime']) or 'no real-time options'}), {r.get('load_processes', 0)} CPU-bound"
        " processes beside it",
        f"{'':24}{'compd loop':>14}{'bare loop':>14}{'naive loop':>14}",
        f"{'cycles':24}{c['cycles']:>14}{b['cycles']:>14}{n['cycles']:>14}",
        f"{'misses':24}{c['misses']:>14}{cell(b['misses'], '')}{n['misses']:>14}",
        f"{'miss rate %':24}{rate(c):>14.4f}{cell(rate(b), '.4f')}{rate(n):>14.2f}",
    ]
    for key in ("p50", "p99", "p999", "max"):
        lines.append(
            f"{'lateness ' + key + ' us':24}{compd_cell('lateness_us', key)}{cell(b['lateness_us'][key], '.0f')}"
            f"{n['lateness_us'][key]:>14.0f}"
        )
    for key in ("p50", "p99", "max"):
        lines.append(
            f"{'cycle compute ' + key + ' us':24}{compd_cell('cycle_compute_us', key)}"
            f"{cell(b['cycle_compute_us'][key], '.0f')}{n['cycle_compute_us'][key]:>14.0f}"
        )
    rss = r["rss_kb"]
    lines.append(
        f"memory: {rss.get('after_warmup_kb', 0)} kB after warm-up, {rss['end_kb']} kB at the end"
        f" (growth {rss['growth_kb']} kB, largest {rss['max_growth_kb']} kB over {rss['samples']} samples)"
    )
    procs = r.get("io_processes") or []
    if procs:
        lines.append(
            f"device I/O and service: {len(procs)} processes beside the loop's ({', '.join(p['name'] for p in procs)}),"
            f" {sum(p['pss_kb'] for p in procs)} kB proportional set size together"
            f" ({sum(p['rss_kb'] for p in procs)} kB resident, counting pages shared with the loop's)"
        )
    else:
        lines.append("device I/O and service: threads of the loop's process")
    sv = r.get("service") or {}
    log_st = sv.get("log") or {}
    lines.append(
        f"service: {sv.get('status_writes', 0)} status files, {log_st.get('rows_written', 0)} data-log rows"
        f" ({log_st.get('rows_dropped', 0)} dropped), {r.get('metrics_scrapes', 0)} metrics scrapes;"
        f" status record written every cycle (longest write {sv.get('status_write_max_us', 0):g} us),"
        f" devices' accounts waited {sv.get('devices_waited', 0)} cycles for room"
    )
    if "between_max_us" in r:
        lines.append(
            f"between cycles (the service's share, collection): max {r['between_max_us']:.0f} us,"
            f" {r['between_overruns']} times past the next deadline (that cycle late)"
        )
    io = r["io_us"]
    for key, what in (("read", "poll (8 regs)"), ("write", "PMC write"), ("output_latency", "queued->acked")):
        if io.get(key):
            h = io[key]
            io_over = h.get("over_range") or ()
            lines.append(
                f"I/O {what}: {h['count']} round trips, p50 {percentile_text(h['p50'], 'p50' in io_over, '.0f')},"
                f" p99 {percentile_text(h['p99'], 'p99' in io_over, '.0f')}, max {h['max']:.0f} us"
            )
    lines.append(f"words sent to the PMC: {r['words_sent']} (plant at {r['plant_speedup']:.0f}x)")
    h = r["host"]
    lines.append(
        f"host: {h['steal_ms']:.0f} ms stolen by the hypervisor during the run; cycle thread preempted"
        f" {h['cycle_thread_involuntary_switches']} times; {h['misses_with_steal']} of the"
        f" {r['misses']} misses in a second in which the hypervisor stole time"
    )
    la = r.get("late_attribution")
    if la:
        who = ", ".join(f"{k} {v}" for k, v in la["overlapping"].items()) or "no thread recorded"
        lines.append(
            f"cycles late by > {la['threshold_us']:.0f} us: {la['late_cycles']}; their wait overlapped the work of:"
            f" {who};"
            f" of no other thread: {la['overlapping_none']}"
        )
    if r.get("trace"):
        from rig.late_trace import summary_line

        lines.append(summary_line(r["trace"]))
    lines.append("model evaluate, median us: " + ", ".join(f"{k} {v:.2f}" for k, v in r["model_eval_us"].items()))
    lines.append(
        f"naive loop: start-to-start interval p50 {n['period_us']['p50']:.0f} us, p99 {n['period_us']['p99']:.0f} us"
        f" (asked for {1000 * r['period_ms']:.0f}); its lateness is against the same absolute schedule as compd's"
    )
    ratio = r["ratio_naive_to_compd"]
    mr = "n/a (compd missed none)" if ratio["miss_rate"] is None else f"{ratio['miss_rate']:.0f}x"
    lines.append(f"naive / compd: miss rate {mr}, p99 lateness {ratio['p99_lateness']:.0f}x")
    cb = r.get("ratio_compd_to_bare")
    if cb:
        lines.append(
            "compd / bare (what compd adds to the machine's own lateness): "
            + ", ".join(f"{k} {v:.1f}x" for k, v in cb.items())
            + f"; bare loop cycles later than 200 us: {b.get('late_200us', 0)}"
        )
        mo = r["compute_max_over_p50"]
        lines.append(
            f"worst cycle's work over the typical one: compd {mo['compd']:.1f}x, bare loop's fixed work"
            f" {mo['bare']:.1f}x (the machine's own spread)"
        )
    return "\n".join(lines)


def write_json(path: str, result: dict[str, Any]) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=2)


def main(args: Any) -> int:
    """`compd bench` (its arguments parsed and checked by compd's CLI): run, print the table, write the JSON."""
    from compd.cli import writing

    try:
        result = run_bench(
            args.cycles,
            period_s=args.period_ms / 1000.0,
            scheduler=args.scheduler,
            naive_cycles=args.naive_cycles,
            load=args.load,
            late_us=args.late_us,
            io=args.io,
            bare_cycles=args.bare_cycles,
            trace=args.trace,
        )
    except DeviceSilent as e:
        print(f"compd bench: {e}", file=sys.stderr)
        return 1
    print(format_table(result))
    if args.json:
        with writing(args.json, "--json"):
            write_json(args.json, result)
    return 0
