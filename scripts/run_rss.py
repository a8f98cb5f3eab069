"""Resident size of `compd run` in a lockstep closed loop: fit the machine's paper model, serve its
unseen day, run compd for DURATION plant seconds and sample VmRSS/VmHWM from /proc.

usage: python scripts/run_rss.py MACHINE [--duration-s S] [--compd REPO] [--workdir DIR]
`--compd REPO` runs compd from another checkout (PYTHONPATH=REPO) against this one's plant,
for before/after comparisons.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rig import closedloop as cl  # noqa: E402


def status_kb(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, kB ({} once it has gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    return {k: int(v.split()[0]) for k, v in (ln.split(":", 1) for ln in text.splitlines()) if k in ("VmRSS", "VmHWM")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("machine", choices=list(cl.MACHINES))
    ap.add_argument("--duration-s", type=float, default=3600.0)
    ap.add_argument("--compd", default=str(ROOT), help="checkout whose compd runs (default: this one)")
    ap.add_argument("--workdir", default="build/rss")
    args = ap.parse_args()
    work = (Path(args.workdir) / args.machine).resolve()
    work.mkdir(parents=True, exist_ok=True)
    model = cl.prepare_model(args.machine, cl.MACHINES[args.machine].paper_kind, work)
    scenario = cl.SCENARIOS / f"{args.machine}_unseen.yaml"
    bench = work / "bench.yaml"
    bench.write_text(
        yaml.safe_dump(
            cl.bench(args.machine, scenario, 7200.0, args.duration_s, work / "residual.csv", True), sort_keys=False
        )
    )
    proc, ports = cl.start_serve(bench)
    try:
        cfg = work / "compd.yaml"
        cfg.write_text(
            yaml.safe_dump(cl.compd_config(args.machine, model, ports, 7200.0, lockstep=True), sort_keys=False)
        )
        cmd = [sys.executable, "-m", "compd", "run", str(cfg), "--duration", str(args.duration_s)]
        env = dict(os.environ, PYTHONPATH=str(Path(args.compd).resolve()))
        t0 = time.monotonic()
        # run from the work folder: `python -m` puts the current folder first on sys.path
        p = subprocess.Popen(cmd, env=env, cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        last: dict[str, int] = {}
        while p.poll() is None:
            last = status_kb(p.pid) or last
            time.sleep(0.05)
        print(
            f"{args.machine}: compd from {args.compd}, exit {p.returncode}, {time.monotonic() - t0:.1f} s wall;"
            f" VmRSS {last.get('VmRSS', 0) / 1024:.1f} MB, VmHWM {last.get('VmHWM', 0) / 1024:.1f} MB"
        )
        return p.returncode
    finally:
        cl.stop_serve(proc)


if __name__ == "__main__":
    raise SystemExit(main())
