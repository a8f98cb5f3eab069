"""`python -m hil_sim log`: run a scenario on its plant and write a log CSV with the true errors.

The scenario may be a `compd testplan` plan; the log CSV is docs/formats.md's.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from compd.core.errors import BadInput

PROBE_SIGMA_UM = 0.3  # a touch probe's repeatability, as the live plant's probing has it


def add_parser(sub: Any) -> None:
    """Register the `log` subcommand on an argparse subparsers object."""
    p = sub.add_parser("log", help="simulate a scenario and write a log CSV (true errors)")
    p.add_argument("--scenario", required=True, help="scenario YAML (with a machine: key)")
    p.add_argument("--out", required=True, help="log CSV to write")
    p.add_argument("--rate-s", type=float, default=1.0, help="seconds between rows (default 1)")
    p.add_argument("--seed", type=int, default=None, help="overrides the scenario's seed")
    p.add_argument("--duration-s", type=float, default=None, help="stop early (default: whole scenario)")
    p.add_argument(
        "--profile",
        default=None,
        help="also write E(y) sweeps (feed_axis, gantry): a log with one row per grid position",
    )
    p.add_argument("--profile-every-s", type=float, default=900.0, help="seconds between sweeps")
    p.add_argument(
        "--plan",
        default=None,
        metavar="PLAN.csv",
        help="run this `compd testplan` plan instead of the scenario's segments (the scenario gives"
        " the machine, its params and the ambient); its measurements become probe_<axis>_um",
    )
    p.add_argument(
        "--plan-axis",
        default=None,
        metavar="NAME",
        help="the plan's axis whose feed the plant's linear axes follow (default: its only one)",
    )
    p.add_argument(
        "--stroke-mm",
        type=float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="where the linear axes reciprocate in the plan's feed holds (default: the plant's stroke)",
    )
    p.add_argument(
        "--probe-sigma-um",
        type=float,
        default=PROBE_SIGMA_UM,
        help=f"the probe's noise, 1 sigma, at the plan's measurements (default {PROBE_SIGMA_UM:g})",
    )
    p.set_defaults(func=cmd_log)


def load_plant(
    scenario_file: str,
    seed: int | None = None,
    plan: Any = None,
    plan_axis: str | None = None,
    stroke_mm: tuple[float, float] | None = None,
) -> Any:
    """The plant named by a scenario file's `machine:` key, built with its `params:`; with `plan`
    (compd.commissioning.testplan.Plan) it runs the plan's rows instead of the file's segments."""
    from hil_sim.plants import PLANTS
    from hil_sim.scenario import Scenario, plan_segments

    try:
        sc = Scenario.load(scenario_file)
    except ValueError as e:
        raise BadInput(str(e)) from None
    if sc.machine is None:
        raise BadInput("machine: missing (which plant runs this scenario?)", file=scenario_file)
    if seed is not None:
        sc.seed = seed
    if plan is not None:
        if stroke_mm is not None and not stroke_mm[1] > stroke_mm[0]:
            raise BadInput("HIGH must be above LOW", path="--stroke-mm")
        try:
            segments = plan_segments(plan, plan_axis, None if stroke_mm is None else tuple(stroke_mm))
        except ValueError as e:
            raise BadInput(str(e), file=plan.info.get("file"), path="--plan-axis") from None
        sc = Scenario(segments, sc.ambient, sc.seed, sc.machine, sc.params)
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
    plant: Any,
    out: str | Path,
    rate_s: float,
    duration_s: float | None = None,
    profile: str | Path | None = None,
    profile_every_s: float = 900.0,
    probes_s: np.ndarray | None = None,
    probe_sigma_um: float = PROBE_SIGMA_UM,
) -> dict[str, Any]:
    """Simulate, write the log (and the sweeps), return a summary. At each time of `probes_s` the
    log has a row whose probe_<axis>_um is the true error plus the probe's noise (σ
    `probe_sigma_um`), and probe_pos_<axis>_mm the axis's position where it has one; blank
    elsewhere."""
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
    if not (math.isfinite(probe_sigma_um) and probe_sigma_um >= 0):
        raise BadInput("--probe-sigma-um must be >= 0")
    times = np.arange(0.0, dur + 1e-9, rate_s)
    probe_rows = np.zeros(0, int)
    if probes_s is not None:  # the measurements' times are rows of the log
        at = np.asarray(probes_s, float)
        times = np.unique(np.round(np.concatenate([times, at[at <= dur + 1e-9]]), 9))
        probe_rows = np.flatnonzero(np.isin(times, np.round(at, 9)))
    sweeps: list[tuple[int, np.ndarray]] = []
    next_sweep = [0.0]

    def on_row(k: int, t: float) -> None:
        if t + 1e-9 >= next_sweep[0]:
            sweeps.append((k, np.atleast_2d(plant.error_profile_um())))
            next_sweep[0] += profile_every_s

    t0 = time.perf_counter()
    rows = plant.record(times, on_row if profile is not None else None)
    sim_s = time.perf_counter() - t0
    columns, data = ["t_s", *plant.signal_names], [times[:, None], rows]
    if probes_s is not None:
        columns, data = _with_probes(plant, rows, probe_rows, probe_sigma_um, columns, data)
    try:
        write_csv(out, columns, np.hstack(data))
    except OSError as e:
        raise BadInput(f"cannot write log: {e.strerror or e}", file=str(out)) from None
    summary: dict[str, Any] = {"rows": len(times), "sim_s": sim_s, "axes": {}, "probes": int(probe_rows.size)}
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


def _with_probes(
    plant: Any, rows: np.ndarray, probe_rows: np.ndarray, sigma_um: float, columns: list[str], data: list[np.ndarray]
) -> tuple[list[str], list[np.ndarray]]:
    """The log's columns with probe_<axis>_um (and probe_pos_<axis>_mm) at `probe_rows`."""
    rng = np.random.default_rng([int(plant.scenario.seed), 40])  # the probes' own stream: the log stays put
    pos_idx, err_idx = _positions(plant)
    columns, data = list(columns), list(data)
    for a, jp, je in zip(plant.axes, pos_idx, err_idx, strict=True):
        z = np.full(rows.shape[0], np.nan)
        z[probe_rows] = rows[probe_rows, je] + rng.normal(0.0, sigma_um, probe_rows.size)
        columns.append(f"probe_{a}_um")
        data.append(z[:, None])
        if jp >= 0:
            p = np.full(rows.shape[0], np.nan)
            p[probe_rows] = rows[probe_rows, jp]
            columns.append(f"probe_pos_{a}_mm")
            data.append(p[:, None])
    return columns, data


def _plan_drives(plant: Any, plan: Any, file: str) -> None:
    """BadInput when the plant follows nothing the plan changes; a note for what it does not follow."""
    spindle = "speed_rpm" in plant.signal_names
    axes = any(n.startswith("pos_") for n in plant.signal_names)
    turns = bool(np.any(plan.speed_rpm > 0))
    moves = any(np.any(f > 0) for f in plan.feeds_mm_min.values())
    if (turns and spindle) or (moves and axes):
        if turns and not spindle:
            print(
                f"hil_sim: the {plant.name} plant has no spindle: the plan's speeds are not simulated", file=sys.stderr
            )
        if moves and not axes:
            print(
                f"hil_sim: the {plant.name} plant has no linear axis: the plan's feeds are not simulated",
                file=sys.stderr,
            )
        return
    raise BadInput(
        f"the {plant.name} plant follows nothing this plan changes (it has "
        f"{'a spindle' if spindle else 'linear axes' if axes else 'neither spindle nor axes'};"
        f" the plan {'turns the spindle' if turns else 'moves axes' if moves else 'stands still'})",
        file=file,
        path="--plan",
    )


def cmd_log(args: argparse.Namespace) -> int:
    plan = None
    if args.plan is not None:
        from compd.commissioning.testplan import read_plan

        plan = read_plan(args.plan)
    elif args.plan_axis is not None or args.stroke_mm is not None:
        raise BadInput("--plan-axis and --stroke-mm go with --plan", path="--plan")
    plant = load_plant(args.scenario, args.seed, plan, args.plan_axis, args.stroke_mm)
    probes = None
    if plan is not None:
        _plan_drives(plant, plan, args.plan)
        probes = plan.probe_times_s() - plan.t_s[0]
    s = run_log(
        plant, args.out, args.rate_s, args.duration_s, args.profile, args.profile_every_s, probes, args.probe_sigma_um
    )
    parts = [f"{a}: rms {v['rms_um']:.2f} um, max {v['max_abs_um']:.2f} um" for a, v in s["axes"].items()]
    extra = f", {s['profile_rows']} profile rows" if "profile_rows" in s else ""
    if plan is not None:
        extra += f", plan {args.plan}: {s['probes']} probes"
    print(
        f"{args.out}: {s['rows']} rows ({plant.name}, {plant.t_s / 3600.0:.2f} h simulated in "
        f"{s['sim_s']:.2f} s{extra}); " + "; ".join(parts),
        file=sys.stdout,
    )
    return 0
