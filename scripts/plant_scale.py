"""`make accept`: a plant of N compd telemetry publishers into one mosquitto on loopback:\
 loss, duplicates, latency, CPU.

Each machine is a `compd.plant.telemetry.Telemetry` (the daemon's own publisher, its own
MQTT connection, its own store-and-forward file) replaying a data log at one sample a
second; `--procs` processes hold them all. One more process is the plant's historian: a
Sparkplug primary host (its STATE online, its will offline) that decodes every message.
With `--outage-at-s`/`--outage-s` the broker is killed (SIGKILL) for that long mid-run
and started again. At the end every publisher stops taking samples, sends what it still
holds and its NDEATH; then the historian's record is compared with what each machine
took: lost, duplicated, out of order, and the end-to-end latency (sample taken → decoded
by the historian) of the samples that were not historical.

CPU: user + system time of the broker, of the publishers' processes and of the historian
over the run (from /proc), divided by the run's wall time and the number of machines.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
LOG = ROOT / "configs" / "logs" / "spindle_demo_30s.csv"
HOST_ID = "historian"
GROUP = "plant"
TICK_S = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and its waited-for children, from /proc."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(f[11]) + int(f[12])) / TICK_S


# ------------------------------------------------------------------ publishers
def snapshots(log: Path) -> list[dict[str, Any]]:
    """The log's rows as status snapshots: its signals, and the axis its error column names."""
    with open(log, newline="") as fh:
        rows = list(csv.DictReader(fh))
    out = []
    for r in rows:
        err = float(r["err_z_um"])
        out.append(
            {
                "state": "running",
                "observe": False,
                "word": f"0x{(0x4000 | (round(abs(err)) & 0x7F) << 8):04X}",
                "axes": {
                    "z": {
                        "correction_um": -err,
                        "target_um": -err,
                        "prediction_um": err,
                        "enable": True,
                        "state": "normal",
                    }
                },
                "signals": {
                    k: {"value": float(v), "quality": "good"} for k, v in r.items() if k not in ("t_s", "err_z_um")
                },
                "model": {"kind": "xi_spindle", "file": "model.yaml", "fit": {"fitted_at": "2026-11-01T00:00:00Z"}},
            }
        )
    return out


def publish(args: argparse.Namespace) -> int:
    import logging

    from compd.plant.spec import TelemetrySpec
    from compd.plant.telemetry import Telemetry

    logging.getLogger("compd.telemetry").setLevel(logging.ERROR)  # not a line per machine per outage
    work = Path(args.workdir)
    snaps = snapshots(LOG)
    tels = []
    for i in range(args.first, args.first + args.count):
        spec = TelemetrySpec(
            host="127.0.0.1",
            port=args.port,
            client_id=f"m{i:03d}",
            group_id=GROUP,
            edge_node_id=f"m{i:03d}",
            device_id="machine",
            buffer_path=work / "buffers" / f"m{i:03d}.sqlite",
            buffer_max_bytes=64_000_000,
            period_s=1.0,
            keepalive_s=10,
            reconnect_max_s=5.0,
            primary_host_id=HOST_ID,
            poll_s=args.poll_s,
            slack_s=0.5,
            properties={"config": f"m{i:03d}.yaml"},
        )
        tel = Telemetry(spec)
        tel.start()
        tels.append(tel)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    taken = [0] * len(tels)
    t0 = time.time()
    k = 0
    while not stop.is_set():
        now = time.time()
        for j, tel in enumerate(tels):
            if tel.sample(snaps[(k + 7 * (args.first + j)) % len(snaps)], t_unix_s=now):
                taken[j] += 1
        k += 1
        stop.wait(max(0.0, t0 + k - time.time()))
    finals = [tel.stop(drain_s=args.drain_s) for tel in tels]
    out = {f"m{args.first + j:03d}": {"taken": taken[j], "final": finals[j]} for j in range(len(tels))}
    Path(args.out).write_text(json.dumps(out))
    return 0


# ------------------------------------------------------------------ the historian
def listen(args: argparse.Namespace) -> int:
    import paho.mqtt.client as mqtt

    from compd.plant.sparkplug import AliasResolver, SparkplugError, decode

    seen: dict[str, list[tuple[int, bool, float]]] = {}  # edge → (Sample, historical, latency s)
    counts = {"messages": 0, "births": 0, "deaths": 0, "errors": 0}
    lock = threading.Lock()
    aliases = AliasResolver()  # DDATA metrics come by alias: named from the births
    state_topic = f"spBv1.0/STATE/{HOST_ID}"

    def on_connect(cl: Any, u: Any, f: Any, rc: Any, p: Any) -> None:
        cl.subscribe(f"spBv1.0/{GROUP}/#", qos=1)

    def on_subscribe(cl: Any, *a: Any) -> None:
        cl.publish(state_topic, json.dumps({"online": True, "timestamp": int(time.time() * 1000)}), qos=1, retain=True)

    def on_message(cl: Any, u: Any, msg: Any) -> None:
        t = time.time()
        parts = msg.topic.split("/")
        with lock:
            counts["messages"] += 1
            try:
                payload = decode(msg.payload)
                aliases.resolve(msg.topic, payload)
            except SparkplugError:
                counts["errors"] += 1
                return
            if parts[2] == "NBIRTH":
                counts["births"] += 1
            elif parts[2] == "NDEATH":
                counts["deaths"] += 1
            elif parts[2] == "DDATA":
                for m in payload.metrics:
                    if m.name == "Sample":
                        lat = t - (payload.timestamp_ms or 0) / 1000.0
                        seen.setdefault(parts[3], []).append((int(m.value), bool(m.is_historical), lat))

    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="historian", clean_session=True)
    c.will_set(state_topic, json.dumps({"online": False, "timestamp": 0}), qos=1, retain=True)
    c.on_connect, c.on_subscribe, c.on_message = on_connect, on_subscribe, on_message
    c.reconnect_delay_set(0.1, 1.0)
    c.connect("127.0.0.1", args.port, keepalive=10)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    c.loop_start()
    while not stop.wait(1.0):
        with lock:
            Path(args.out + ".progress").write_text(json.dumps({k: len(v) for k, v in seen.items()}))
    c.disconnect()
    c.loop_stop()
    with lock:
        Path(args.out).write_text(json.dumps({"counts": counts, "seen": seen}))
    return 0


# ------------------------------------------------------------------ the run
class Broker:
    def __init__(self, work: Path, port: int) -> None:
        self.exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        self.conf = work / "mosquitto.conf"
        self.conf.write_text(
            f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
            f"log_dest file {work / 'mosquitto.log'}\nmax_queued_messages 1000000\n"
            "max_inflight_messages 0\nset_tcp_nodelay true\n"
        )
        self.port = port
        self.proc: subprocess.Popen[bytes] | None = None
        self.cpu_s = 0.0  # of the broker processes that have ended

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def kill(self) -> None:
        if self.proc is not None:
            self.cpu_s += cpu_s(self.proc.pid)
            self.proc.kill()
            self.proc.wait()
            self.proc = None

    def cpu(self) -> float:
        return self.cpu_s + (cpu_s(self.proc.pid) if self.proc is not None else 0.0)


def run(args: argparse.Namespace) -> dict[str, Any]:
    work = Path(args.workdir).resolve()
    if work.exists():
        shutil.rmtree(work)
    (work / "buffers").mkdir(parents=True)
    port = free_port()
    broker = Broker(work, port)
    broker.start()
    me = [sys.executable, str(Path(__file__).resolve()), "--workdir", str(work), "--port", str(port)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    hist = subprocess.Popen([*me, "--role", "listen", "--out", str(work / "historian.json")], env=env)
    time.sleep(1.0)
    per = -(-args.machines // args.procs)
    pubs = []
    for p in range(args.procs):
        first, count = p * per, min(per, args.machines - p * per)
        if count > 0:
            pubs.append(
                subprocess.Popen(
                    [
                        *me,
                        "--role",
                        "publish",
                        "--first",
                        str(first),
                        "--count",
                        str(count),
                        "--poll-s",
                        str(args.poll_s),
                        "--drain-s",
                        str(args.drain_s),
                        "--out",
                        str(work / f"pub{p}.json"),
                    ],
                    env=env,
                )
            )
    t0 = time.monotonic()
    outage = None
    try:
        if args.outage_s > 0:
            time.sleep(max(0.0, args.outage_at_s - (time.monotonic() - t0)))
            broker.kill()
            t_kill = time.monotonic()
            print(f"plant: broker killed at {t_kill - t0:.0f} s for {args.outage_s:g} s", flush=True)
            time.sleep(args.outage_s)
            broker.start()
            outage = {"at_s": round(t_kill - t0, 1), "down_s": round(time.monotonic() - t_kill, 1)}
        time.sleep(max(0.0, args.duration_s - (time.monotonic() - t0)))
        wall = time.monotonic() - t0
        pub_cpu = sum(cpu_s(p.pid) for p in pubs)
        hist_cpu = cpu_s(hist.pid)
        broker_cpu = broker.cpu()
        for p in pubs:
            p.send_signal(signal.SIGTERM)
        for p in pubs:
            p.wait(timeout=args.drain_s + 120)
        taken: dict[str, int] = {}
        finals: dict[str, Any] = {}
        for p in range(len(pubs)):
            for k, v in json.loads((work / f"pub{p}.json").read_text()).items():
                taken[k] = v["taken"]
                finals[k] = v["final"]
        deadline = time.monotonic() + 60  # the last samples on their way to the historian
        while time.monotonic() < deadline:
            try:
                prog = json.loads((work / "historian.json.progress").read_text())
            except (OSError, ValueError):
                prog = {}
            if all(prog.get(k, 0) >= n for k, n in taken.items()):
                break
            time.sleep(1.0)
        time.sleep(1.5)
    finally:
        for p in pubs:
            if p.poll() is None:
                p.kill()
                p.wait()
        hist.send_signal(signal.SIGTERM)
        hist.wait(timeout=60)
        broker.kill()
    got = json.loads((work / "historian.json").read_text())
    lost = dup = disorder = 0
    lat: list[float] = []
    hist_n = 0
    for k, n in taken.items():
        rec = got["seen"].get(k, [])
        nums = [s for s, _, _ in rec]
        uniq = set(nums)
        lost += len(set(range(1, n + 1)) - uniq)
        dup += len(nums) - len(uniq)
        disorder += sum(1 for a, b in zip(nums, nums[1:], strict=False) if b <= a)
        lat += [lt for _, h, lt in rec if not h]
        hist_n += sum(1 for _, h, _ in rec if h)
    lat.sort()

    def pct(q: float) -> float:
        return round(lat[min(len(lat) - 1, int(q * len(lat)))] * 1000, 1) if lat else float("nan")

    n = args.machines
    return {
        "machines": n,
        "processes": args.procs,
        "duration_s": round(wall, 1),
        "outage": outage,
        "samples_taken": sum(taken.values()),
        "received": sum(len(v) for v in got["seen"].values()),
        "lost": lost,
        "duplicated": dup,
        "out_of_order": disorder,
        "historical": hist_n,
        "dropped_by_buffers": sum(f.get("dropped", 0) for f in finals.values()),
        "latency_ms": {"p50": pct(0.5), "p99": pct(0.99), "max": round(lat[-1] * 1000, 1) if lat else None},
        "cpu_pct_per_machine": {
            "broker": round(100 * broker_cpu / wall / n, 3),
            "publishers": round(100 * pub_cpu / wall / n, 3),
            "historian": round(100 * hist_cpu / wall / n, 3),
        },
        "historian": got["counts"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=200)
    ap.add_argument("--procs", type=int, default=4, help="publisher processes")
    ap.add_argument("--duration-s", type=float, default=600.0)
    ap.add_argument("--outage-at-s", type=float, default=120.0)
    ap.add_argument("--outage-s", type=float, default=0.0, help="kill the broker this long (0: no outage)")
    ap.add_argument("--poll-s", type=float, default=0.05, help="each publisher's wait for the network")
    ap.add_argument("--drain-s", type=float, default=30.0)
    ap.add_argument("--workdir", default="build/accept/plant")
    ap.add_argument("--json", default=None)
    ap.add_argument("--role", choices=["run", "publish", "listen"], default="run", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--first", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--out", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "publish":
        return publish(args)
    if args.role == "listen":
        return listen(args)
    result = run(args)
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1))
    ok = result["lost"] == 0 and result["duplicated"] == 0 and result["out_of_order"] == 0
    print(
        f"plant: {result['machines']} machines, {result['samples_taken']} samples: lost {result['lost']},"
        f" duplicated {result['duplicated']}, out of order {result['out_of_order']},"
        f" latency p99 {result['latency_ms']['p99']} ms -> {'PASS' if ok else 'FAIL'}"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
