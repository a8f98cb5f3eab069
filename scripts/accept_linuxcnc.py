"""Acceptance (make accept): the closed loop on LinuxCNC over compd testplan's whole 24 h test,\
 beside the same plan in process.

`python scripts/accept_linuxcnc.py [--hours 24] [--speedup 240] [--workdir DIR] [--json FILE]` runs a headless
LinuxCNC sim mill (the test suite's, tests/linuxcnc/sim.py), the loop of rig/linuxcnc_loop.py on it (6 min of
wall time at 240), then the same plan on the same plant in process (`hil_sim log --plan`, `compd replay` through
the linuxcnc sink's emulation), and prints both reductions. Exit 1 when the loop on LinuxCNC misses: its offset
more than 1 µm from compd's correction in a read where the correction held still, an offset left after SIGTERM,
or a reduction more than 5 points below the in-process one.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig import linuxcnc_loop  # noqa: E402
from tests.linuxcnc.sim import Sim, require  # noqa: E402

MAX_LOSS_PTS = 5.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--speedup", type=float, default=240.0)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    require()
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="accept-linuxcnc-"))
    (work / "linuxcnc").mkdir(parents=True, exist_ok=True)
    (work / "in_process").mkdir(parents=True, exist_ok=True)
    with Sim() as sim:
        loop = linuxcnc_loop.run(
            sim, work / "linuxcnc", args.hours, args.speedup, timeout_s=args.hours * 3600 / args.speedup + 600
        )
    inproc = linuxcnc_loop.in_process(work / "in_process", args.hours)["axes"]["z"]
    z = loop["z"]
    print(
        f"LinuxCNC ({args.hours:g} h plan at {args.speedup:g}x): z RMS {z['rms_before_um']:.2f} ->"
        f" {z['rms_after_um']:.2f} um ({z['reduction_pct']:.1f} %); offset - correction: {loop['follow_reads']}"
        f" steady reads, largest {loop['follow_max_um']:.3f} um; after SIGTERM {loop['eoffset_after_um']:+.3f} um"
    )
    print(
        f"in process (the same plan, compd replay): z RMS {inproc['rms_before_um']:.2f} ->"
        f" {inproc['rms_after_um']:.2f} um ({inproc['reduction_pct']:.1f} %)"
    )
    missed = []
    if not (loop["follow_reads"] > 20 and loop["follow_max_um"] <= 1.0):
        missed.append("the offset did not follow compd's correction within 1 um")
    if loop["compd_exit"] != 0 or abs(loop["eoffset_after_um"]) >= 0.15:
        missed.append("SIGTERM did not leave 0")
    if z["reduction_pct"] < inproc["reduction_pct"] - MAX_LOSS_PTS:
        missed.append(f"the reduction on LinuxCNC is more than {MAX_LOSS_PTS:g} points below the in-process one")
    print("goals: " + ("; ".join(missed) if missed else "met"))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"linuxcnc": loop, "in_process": inproc, "missed": missed}, indent=1))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
