"""`python -m hil_sim log`: run a scenario on its plant and write a log CSV (docs/formats.md) with the true errors."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from compd.errors import BadInput


def add_parser(sub: Any) -> None:
    """Register the `log` subcommand on an argparse subparsers object."""
    p = sub.add_parser("log", help="simulate a scenario and write a log CSV (true errors)")
    p.add_argument("--scenario", required=True, help="scenario YAML (with a machine: key)")
    p.add_argument("--out", required=True, help="log CSV to write")
    p.add_argument("--rate-s", type=float, default=1.0, help="seconds between rows (default 1)")
    p.add_argument("--seed", type=int, default=None, help="overrides the scenario's seed")
    p.add_argument("--duration-s", type=float, default=None, help="stop early (default: whole scenario)")
    p.add_argument(
        "--profile", default=None,
        help="also write E(y) sweeps (feed_axis, gantry): a log with one row per grid position",
    )
    p.add_argument("--profile-every-s", type=float, default=900.0, help="seconds between sweeps")
    p.set_defaults(func=cmd_log)


def load_plant(scenario_file: str, seed: int | None = None) -> Any:
    """The plant named by a scenario file's `machine:` key, built with its `params:`."""
    from hil_sim.plants import PLANTS
    from hil_sim.scenario import Scenario

    try:
        sc = Scenario.load(scenario_file)
    except ValueError as e:
        raise BadInput(str(e)) from None
    if sc.machine is None:
        raise BadInput("machine: missing (which plant runs this scenario?)", file=scenario_file)
    if seed is not None:
        sc.seed = seed
    cls = PLANTS.get(sc.machine, path="machine")
    try:
        return cls(sc, sc.params)
    except (ValueError, TypeError) as e:
        raise BadInput(str(e), file=scenario_file, path="params") from None


def write_csv(path: str | Path, columns: list[str], data: np.ndarray) -> None:
    """Write a log CSV quickly (t_s with 10 significant digits, the rest with 6)."""
    fmt = ",".join(["%.10g"] + ["%.6g"] * (len(columns) - 1))
    with open(path, "w", encoding="utf-8", newline="") as fh:
        np.savetxt(fh, data, fmt=fmt, delimiter=",", header=",".join(columns), comments="")


def _positions(plant: Any) -> tuple[list[int], list[int]]:
    """Column indices of pos_<axis>_mm and err_<axis>_um per axis (pos may be missing)."""
    names = plant.signal_names
    pos = [names.index(f"pos_{a}_mm") if f"pos_{a}_mm" in names else -1 for a in plant.axes]
    err = [names.index(f"err_{a}_um") for a in plant.axes]
    return pos, err


def run_log(
    plant: Any, out: str | Path, rate_s: float, duration_s: float | None = None,
    profile: str | Path | None = None, profile_every_s: float = 900.0,
) -> dict[str, Any]:
    """Simulate, write the log (and the sweeps), return a summary."""
    if not rate_s > 0:
        raise BadInput("--rate-s must be > 0")
    dur = plant.scenario.duration_s if duration_s is None else duration_s
    if not dur > 0:
        raise BadInput("--duration-s must be > 0")
    if profile is not None:
        if not hasattr(plant, "error_profile_um"):
            raise BadInput(f"--profile: the {plant.name} plant has no position-dependent error")
        if not profile_every_s > 0:
            raise BadInput("--profile-every-s must be > 0")
    times = np.arange(0.0, dur + 1e-9, rate_s)
    sweeps: list[tuple[int, np.ndarray]] = []
    next_sweep = [0.0]

    def on_row(k: int, t: float) -> None:
        if t + 1e-9 >= next_sweep[0]:
            sweeps.append((k, np.atleast_2d(plant.error_profile_um())))
            next_sweep[0] += profile_every_s

    t0 = time.perf_counter()
    rows = plant.record(times, on_row if profile is not None else None)
    sim_s = time.perf_counter() - t0
    try:
        write_csv(out, ["t_s", *plant.signal_names], np.column_stack([times, rows]))
    except OSError as e:
        raise BadInput(f"cannot write log: {e.strerror or e}", file=str(out)) from None
    summary: dict[str, Any] = {"rows": len(times), "sim_s": sim_s, "axes": {}}
    _, err_idx = _positions(plant)
    for a, j in zip(plant.axes, err_idx, strict=True):
        e = rows[:, j]
        summary["axes"][a] = {"rms_um": float(np.sqrt(np.mean(e**2))), "max_abs_um": float(np.max(np.abs(e)))}
    if profile is not None:
        pos_idx, _ = _positions(plant)
        grid = plant.profile_mm
        prof_rows = []
        for k, errs in sweeps:
            for g, y in enumerate(grid):
                r = rows[k].copy()
                for a in range(len(plant.axes)):
                    if pos_idx[a] >= 0:
                        r[pos_idx[a]] = y
                    r[err_idx[a]] = errs[a % errs.shape[0], g]
                prof_rows.append(np.concatenate([[times[k]], r]))
        try:
            write_csv(profile, ["t_s", *plant.signal_names], np.array(prof_rows))
        except OSError as e:
            raise BadInput(f"cannot write profile: {e.strerror or e}", file=str(profile)) from None
        summary["profile_rows"] = len(prof_rows)
    return summary


def cmd_log(args: argparse.Namespace) -> int:
    plant = load_plant(args.scenario, args.seed)
    s = run_log(plant, args.out, args.rate_s, args.duration_s, args.profile, args.profile_every_s)
    parts = [
        f"{a}: rms {v['rms_um']:.2f} um, max {v['max_abs_um']:.2f} um" for a, v in s["axes"].items()
    ]
    extra = f", {s['profile_rows']} profile rows" if "profile_rows" in s else ""
    print(
        f"{args.out}: {s['rows']} rows ({plant.name}, {plant.t_s / 3600.0:.2f} h simulated in "
        f"{s['sim_s']:.2f} s{extra}); " + "; ".join(parts),
        file=sys.stdout,
    )
    return 0
