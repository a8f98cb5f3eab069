"""Issue 32's simulated proof: two contributions summed on one axis, in closed loop, with a sensor unplugged.

usage: python scripts/accept_contributions.py [--workdir build/accept/contributions] [--json FILE]
       [--jobs N] [--speedup X] [--unplug-at-s S] [--xi-window-s FROM TO]

The machine is hil_sim's vertical machining centre (`vmc`, hil_sim/README.md): a motorized
spindle hung on a steel column, one Z error from two heat sources,
err_z_um = err_z_um_spindle (rotor growth + centrifugal lift, toward the table) + err_z_um_column
(−α_c H times the column's mean rise: the column lifts the head). Wiring as rig/closedloop.py's
MACHINES["vmc"]: the PT100 module and the plant's signals over Modbus TCP, the spindle's FANUC
PMC word (Z on its high byte, 1 µm LSB), the guard's slew 0.2 µm/s, lockstep.

Fits (on the training day, `python -m hil_sim log` of vmc_train.yaml every 10 s)
-------------------------------------------------------------------------------
spindle  xi_spindle on T_xi and speed_rpm (paper 003: the ξ sensor sits where the rotor's
         temperature equals its mean, so α L ΔT_ξ is the rotor's growth, plus the lift k n²),
         fitted on the spindle's own growth: the training log with err_z_um replaced by
         err_z_um_spindle, the growth measured against the spindle's own housing (on a machine:
         a probe at the spindle nose held from the headstock, the spindle test of ISO 230-3).
         Fitted on the whole Z error instead, T_xi, which follows the hall's air while the
         spindle stands, takes up the column's opposite response to the air (an omitted
         variable): the stagewise sum then leaves 6.1 µm held out (0.33 µm this way) and 6.5 µm
         of the unseen day (0.49 µm; `compd predict` offline). The ξ model on its own growth
         leaves 0.13 µm on the training day; MLR on T_xi and T_brg_front fitted the same way
         0.81 µm (bearing temperatures follow the housing, not the rotor), and its sum with the
         column 1.3 µm of the unseen day against 0.49 µm.
column   mlr on T_col_top and T_col_bot, `compd fit --on-residual-of spindle.yaml` on the whole
         Z error: what the spindle model leaves is the column's growth, −α_c H ΔT̄ (α_c H = 6.9
         µm/K), and the two face sensors estimate the mean (the fitted gains sum to ≈ −6.9
         µm/K). T_amb acts on Z only through the column's temperature, which these sensors
         read: adding it gained 0.05 µm held out (inside the word's 1 µm LSB), nothing on the
         unseen day (0.50 against 0.49 µm offline), and would be a third sensor whose loss
         takes the column's model off its fitted form.
mlr      MLR on all seven temperatures and the whole Z error (`compd fit --kind mlr`), the baseline.

Closed loop on vmc_unseen.yaml (lockstep, the whole day), one row each: the sum of the two
contributions (`model: {contributions: [spindle, column]}`), the spindle contribution alone, the
column contribution alone, MLR on all inputs. The plant's interferometer scores each (RMS and max
|error| without and with, reduction). The two sources push Z in opposite directions (the spindle
toward the table, the column away), so either contribution alone can leave more error than
none: only the sum removes both.

Unplug runs: copies of vmc_unseen.yaml with `params: {sensor_unplug_s: ...}` (the sensor reads
NaN, a PT100 module reports burn-out), closed loop with the two-contribution config: the column
with fault_policy ramp_to_zero (a structure model with a sensor gone has no value to trust, and
the column moves slowly, so ramping out costs little at once), the spindle with hold (the rotor's
time constant is 0.4-0.9 h: over a short outage the last value is far nearer the truth than 0,
and when the sensor is back the contribution slews from where it stands).

  unplug_col_top  T_col_top from --unplug-at-s (12 h, mid-day) to the end of the day
  unplug_xi       T_xi over --xi-window-s (11.5-12 h: the end of a dry 9000 rpm run and its pause)
  unplug_column   T_col_top and T_col_bot from --unplug-at-s (the column model has no input left)

The column's loss costs more than it may seem: from mid-day the hall is 2 K warmer and the column
holds Z ~11 µm away from the table, while the spindle's growth (toward it) partly cancels that.
With the column ramped out and the spindle still compensated, the axis reads the column's whole
error, more than uncompensated over that span (measured 11.65 µm RMS against 8.31 µm): the checks
below therefore judge the remaining contribution against its own source's error, not the axis's.

Checks, from compd's data log (every 10 s and on every word change; compd's own columns, with the
plant's true error parts that it reads as machine signals) and the plant's residual log:

* slew: |Δcorr_z_um| / Δt ≤ the guard's max_slew_um_per_s on every pair of rows of compd's log
  (plus a unit of the log's 6th significant digit), and on the plant's log the applied correction
  never changes by more than slew·Δt + one LSB of the word (1 µm);
* the axis stays enabled: no axis-level fault event for z (a contribution's own fault event is
  `axis=z/<name>`);
* the other contribution keeps compensating over the unplugged span: its share finite on every
  row, the same, row for row, as in the plugged closed loop (the sources are independent: its
  inputs, its model and its own limits are untouched by the other's loss), and the axis with the
  lost source's uncorrected part set aside (residual − (err_lost − share_lost)) at most half the
  other source's error over the span (or one LSB, the word's resolution, where that is larger);
* the lost contribution does what compd says: hold keeps its value until the sensor is back,
  ramp_to_zero reaches 0 within |value| / guard.ramp_um_per_s (+ two cycles) and stays there,
  or, where its model has a degraded form (MLR: a bad input replaced by its expectation given
  the good ones, compd.models.mlr), that estimate stays finite (compd then applies no policy:
  printed as such);
* the sum of the contributions leaves a smaller RMS than each contribution alone on the unseen day.

Exit 1 if a check fails. The table and the checks are printed; --json writes them all.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rig import closedloop as cl  # noqa: E402

MACHINE = "vmc"
AXIS = "z"
LSB_UM = 1.0  # the PMC word's LSB (compd's codec default)
SPINDLE_INPUTS = ("T_xi", "speed_rpm")
COLUMN_INPUTS = ("T_col_top", "T_col_bot")
POLICIES = {"spindle": "hold", "column": "ramp_to_zero"}
TRUTH = {"spindle": "err_z_um_spindle", "column": "err_z_um_column"}  # the plant's parts of err_z_um
LOG_PERIOD_S = 10.0  # compd's data log, plant s


# --------------------------------------------------------------------------------------
# fitting
def spindle_part_log(train: Path, out: Path) -> Path:
    """The training log with the spindle's own growth as the measured error (err_z_um :=
    err_z_um_spindle) and neither part column: what a spindle test against its housing logs."""
    with train.open(newline="") as f:
        rows = list(csv.reader(f))
    head = rows[0]
    keep = [i for i, n in enumerate(head) if n not in TRUTH.values()]
    z, sp = head.index("err_z_um"), head.index(TRUTH["spindle"])
    with out.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([head[i] for i in keep])
        for r in rows[1:]:
            r = list(r)
            r[z] = r[sp]
            w.writerow([r[i] for i in keep])
    return out


def fit_models(work: Path, rate_s: float = 10.0, verbose: bool = True) -> dict[str, Path]:
    """Log the training day, fit the spindle contribution, the column contribution on what it
    leaves, and MLR on every temperature; returns the model files."""

    def say(text: str) -> None:
        if verbose and text.strip():
            print(text.strip(), flush=True)

    work.mkdir(parents=True, exist_ok=True)
    train = work / f"{MACHINE}_train.csv"
    say(cl.log_day(MACHINE, "train", train, rate_s))
    part = spindle_part_log(train, work / f"{MACHINE}_train_spindle_part.csv")
    models = {n: work / f"{MACHINE}_{n}.yaml" for n in ("spindle", "column", "mlr")}
    say(
        cl.run_cli(
            [
                "-m",
                "compd",
                "fit",
                "--kind",
                "xi_spindle",
                "--log",
                str(part),
                "--inputs",
                *SPINDLE_INPUTS,
                "--target",
                "err_z_um",
                "--out",
                str(models["spindle"]),
            ]
        )
    )
    say(
        cl.run_cli(
            [
                "-m",
                "compd",
                "fit",
                "--kind",
                "mlr",
                "--log",
                str(train),
                "--inputs",
                *COLUMN_INPUTS,
                "--target",
                "err_z_um",
                "--on-residual-of",
                str(models["spindle"]),
                "--out",
                str(models["column"]),
                "--report",
                str(work / f"{MACHINE}_column_fit.json"),
            ]
        )
    )
    say(cl.fit(MACHINE, "mlr", train, models["mlr"]))
    return models


def contributions_section(models: dict[str, Path], policies: dict[str, str] | None = None) -> dict[str, Any]:
    """compd's `model:` section: the spindle and the column contribution, each with its fault policy."""
    pol = policies or POLICIES
    return {
        "contributions": [
            {"name": "spindle", "kind": "xi_spindle", "file": str(models["spindle"]), "fault_policy": pol["spindle"]},
            {"name": "column", "kind": "mlr", "file": str(models["column"]), "fault_policy": pol["column"]},
        ]
    }


def unplug_scenario(unplug: dict[str, Any], out: Path, base: Path | None = None) -> Path:
    """A copy of the unseen day (or `base`) with `params.sensor_unplug_s` = `unplug`."""
    doc = yaml.safe_load((base or cl.SCENARIOS / f"{MACHINE}_unseen.yaml").read_text())
    doc.setdefault("params", {})["sensor_unplug_s"] = unplug
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


# --------------------------------------------------------------------------------------
# reading the logs
def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Every column of a CSV as floats (an empty cell: NaN)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.reader(f))
    head = rows[0]
    data = np.array([[float(c) if c not in ("", "nan") else math.nan for c in r] for r in rows[1:]], dtype=float)
    data = data.reshape(len(rows) - 1, len(head))
    return {n: data[:, i] for i, n in enumerate(head)}


def log_tol_um(values: np.ndarray) -> float:
    """One unit in the 6th significant digit of the largest |value| (compd's log writes %.6g)."""
    big = float(np.nanmax(np.abs(values))) if np.any(np.isfinite(values)) else 0.0
    return 10.0 ** (math.floor(math.log10(big)) - 5) if big > 0 else 1e-9


def rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v**2))) if v.size else math.nan


def axis_faults(events: str | Path) -> list[str]:
    """compd's event lines (stderr) of a fault of the axis itself (not of one contribution)."""
    out = []
    for line in Path(events).read_text().splitlines():
        if "event=axis_fault" in line:
            m = re.search(r"\baxis=(\S+)", line)
            if m and m.group(1) == AXIS:
                out.append(line)
    return out


def part_fault_times(events: str | Path, name: str) -> list[float]:
    """Plant times of the `axis=z/<name>` fault events (the contribution took its fault policy)."""
    out = []
    for line in Path(events).read_text().splitlines():
        if "event=axis_fault" in line and f"axis={AXIS}/{name} " in line + " ":
            m = re.search(r"\bt_s=([\d.]+)", line)
            if m:
                out.append(float(m.group(1)))
    return out


# --------------------------------------------------------------------------------------
# checks
class Checks:
    """Named pass/fail lines, printed as they come."""

    def __init__(self) -> None:
        self.items: list[dict[str, Any]] = []
        self.notes: list[dict[str, str]] = []

    def add(self, run: str, what: str, ok: bool, detail: str) -> None:
        self.items.append({"run": run, "check": what, "ok": bool(ok), "detail": detail})
        print(f"  {'ok  ' if ok else 'FAIL'} {run:<15} {what:<34} {detail}", flush=True)

    def note(self, run: str, what: str, detail: str) -> None:
        self.notes.append({"run": run, "note": what, "detail": detail})
        print(f"  note {run:<15} {what:<34} {detail}", flush=True)

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [c for c in self.items if not c["ok"]]


def guard_of(result: dict[str, Any]) -> dict[str, float]:
    """The run's guard: slew (from the config compd ran with), ramp and loop period."""
    from compd.core.config import GuardConfig

    work = Path(result["residual_log"]).parent
    cfg = yaml.safe_load((work / f"compd_{result['machine']}_{result['model']}.yaml").read_text())
    g = cfg["guard"]
    return {
        "slew": float(g["max_slew_um_per_s"]),
        "ramp": float(g.get("ramp_um_per_s", GuardConfig().ramp_um_per_s)),
        "period": float(cfg["loop"]["period_s"]),
    }


def check_slew(run: str, result: dict[str, Any], checks: Checks) -> None:
    """compd's corr_z_um never faster than the slew; the plant's applied correction never more
    than slew·Δt + one LSB apart between two rows."""
    g = guard_of(result)
    log = read_csv(result["compd_log"])
    t, corr = log["t_s"], log[f"corr_{AXIS}_um"]
    ok_rows = np.isfinite(corr)
    t, corr = t[ok_rows], corr[ok_rows]
    dt, dc = np.diff(t), np.abs(np.diff(corr))
    tol = log_tol_um(corr)
    over = dc - (g["slew"] * dt + tol)
    worst = int(np.argmax(dc / np.maximum(dt, 1e-9))) if dt.size else 0
    rate = float(dc[worst] / dt[worst]) if dt.size else 0.0
    checks.add(
        run,
        "slew of corr_z_um (compd log)",
        bool(dt.size) and bool(np.all(over <= 0.0)) and bool(np.all(dt > 0)),
        f"max |Δcorr|/Δt {rate:.4f} um/s at t={t[worst + 1] if dt.size else math.nan:.0f} s"
        f" (limit {g['slew']:g} um/s, {len(t)} rows)",
    )
    res = read_csv(result["residual_log"])
    ta, ap = res["t_s"], res[f"applied_{AXIS}_um"]
    da, dta = np.abs(np.diff(ap)), np.diff(ta)
    lim = g["slew"] * dta + LSB_UM + 1e-9
    k = int(np.argmax(da - lim)) if da.size else 0
    checks.add(
        run,
        "applied steps (plant log)",
        bool(da.size) and bool(np.all(da <= lim)),
        f"largest |Δapplied| {float(da.max()) if da.size else 0.0:.2f} um in {float(dta[k]) if da.size else 0:.0f} s"
        f" (limit slew·Δt + {LSB_UM:g} um LSB: {float(lim[k]) if da.size else 0.0:.2f} um)",
    )
    # compd's own applied_z_um is its read-back of the PMC's status, polled by the link's thread on
    # wall time: in lockstep it trails the plant by some cycles, so its steps are shown, not judged
    ca, ct = log[f"applied_{AXIS}_um"], log["t_s"]
    m = np.isfinite(ca)
    dca, dct = np.abs(np.diff(ca[m])), np.diff(ct[m])
    if dca.size:
        j = int(np.argmax(dca - g["slew"] * dct))
        checks.note(
            run,
            "compd's applied_z_um read-back",
            f"largest step {float(dca[j]):.0f} um in {float(dct[j]):.0f} s"
            f" at t={float(ct[m][j + 1]):.0f} s ({int(np.sum(dca > g['slew'] * dct + LSB_UM + 1e-9))} rows over"
            " slew·Δt + 1 LSB; the PMC itself: the line above)",
        )


def span_mask(t: np.ndarray, span: tuple[float, float]) -> np.ndarray:
    return (t >= span[0]) & (t < span[1])


def check_unplug(
    run: str,
    result: dict[str, Any],
    plugged: dict[str, Any],
    lost: str,
    span: tuple[float, float],
    policy: str,
    checks: Checks,
) -> dict[str, Any]:
    """The checks of one unplug run (the module's doc); returns the figures printed."""
    other = next(n for n in TRUTH if n != lost)
    g = guard_of(result)
    log = read_csv(result["compd_log"])
    ref = read_csv(plugged["compd_log"])
    res = read_csv(result["residual_log"])
    t = log["t_s"]
    inside = span_mask(t, span)
    share = {n: log[f"pred_{AXIS}_{n}_um"] for n in TRUTH}
    truth = {n: log[TRUTH[n]] for n in TRUTH}
    out: dict[str, Any] = {"run": run, "lost": lost, "other": other, "span_s": list(span), "policy": policy}

    faults = axis_faults(result["compd_events"])
    checks.add(
        run,
        "axis z stays enabled",
        not faults,
        "no axis-level fault event" if not faults else f"{len(faults)} axis faults: {faults[0][:160]}",
    )

    # the other contribution: finite, the same as in the plugged run, compensating its source
    o = share[other][inside]
    finite = bool(o.size) and bool(np.all(np.isfinite(o)))
    common, ia, ib = np.intersect1d(np.round(t[inside], 3), np.round(ref["t_s"], 3), return_indices=True)
    diff = np.abs(o[ia] - ref[f"pred_{AXIS}_{other}_um"][ib]) if common.size else np.array([np.inf])
    tol = log_tol_um(np.concatenate([o, ref[f"pred_{AXIS}_{other}_um"]]))
    out["other_rows"] = int(o.size)
    out["other_range_um"] = float(np.nanmax(o) - np.nanmin(o)) if o.size else math.nan
    out["other_max_diff_to_plugged_um"] = float(np.max(diff))
    checks.add(
        run,
        f"{other} share finite, as plugged",
        finite and bool(np.all(diff <= tol)) and common.size > 0,
        f"{o.size} rows in the span, moving over {out['other_range_um']:.2f} um; max |Δ| to the plugged run"
        f" {out['other_max_diff_to_plugged_um']:.2g} um over {common.size} rows",
    )

    # the axis with the lost source's uncorrected part set aside, against the other source's error
    ct, ir, il = np.intersect1d(np.round(res["t_s"], 3), np.round(t, 3), return_indices=True)
    sel = span_mask(ct, span)
    ir, il = ir[sel], il[sel]
    residual = res[f"residual_{AXIS}_um"][ir]
    err = res[f"err_{AXIS}_um"][ir]
    lost_left = truth[lost][il] - share[lost][il]
    other_err = truth[other][il]
    rest = residual - lost_left
    bound = max(0.5 * rms(other_err), LSB_UM)
    out.update(
        {
            "rows": int(ir.size),
            "rms_uncompensated_um": rms(err),
            "rms_residual_um": rms(residual),
            "rms_lost_part_um": rms(truth[lost][il]),
            "rms_lost_left_um": rms(lost_left),
            "rms_other_part_um": rms(other_err),
            "rms_rest_um": rms(rest),
            "rest_bound_um": bound,
        }
    )
    checks.add(
        run,
        f"{other} keeps compensating",
        ir.size > 0 and rms(rest) <= bound,
        f"axis less the {lost}'s uncorrected part {rms(rest):.2f} um RMS vs the {other}'s error"
        f" {rms(other_err):.2f} um (bound {bound:.2f}); axis {rms(err):.2f} -> {rms(residual):.2f} um"
        f" over {ir.size} rows",
    )

    # the lost contribution: its fault policy, or its model's degraded estimate
    v = share[lost]
    fault_at = [x for x in part_fault_times(result["compd_events"], lost) if span[0] <= x < span[1] + g["period"]]
    before = v[(t < span[0]) & np.isfinite(v)]
    v0 = float(before[-1]) if before.size else 0.0
    lv = v[inside]
    if not fault_at:
        out["lost_behaviour"] = "degraded estimate (no fault policy applied)"
        ok = bool(lv.size) and bool(np.all(np.isfinite(lv)))
        checks.add(
            run,
            f"{lost} degraded estimate",
            ok,
            f"compd kept the {lost}'s model running on its good inputs (no z/{lost} fault event), not"
            f" {policy}: finite on {lv.size} rows; its part's error {rms(lost_left):.2f} um RMS of"
            f" {rms(truth[lost][il]):.2f}",
        )
    elif policy == "hold":
        out["lost_behaviour"] = "hold"
        held = lv[t[inside] >= fault_at[0] + g["period"]]
        ok = bool(held.size) and bool(np.all(held == held[0]))
        checks.add(
            run,
            f"{lost} holds",
            ok,
            f"fault at {fault_at[0]:.0f} s; held {float(held[0]) if held.size else math.nan:.2f} um"
            f" on {held.size} rows (spread {float(np.ptp(held)) if held.size else math.nan:.2g} um)",
        )
    elif policy == "ramp_to_zero":
        out["lost_behaviour"] = "ramp_to_zero"
        due = fault_at[0] + abs(v0) / g["ramp"] + 2 * g["period"]
        late = lv[t[inside] >= due]
        ok = bool(late.size) and bool(np.all(late == 0.0))
        checks.add(
            run,
            f"{lost} ramps to zero",
            ok,
            f"fault at {fault_at[0]:.0f} s from {v0:.2f} um; 0 from"
            f" {due:.0f} s on: {int(np.sum(late == 0.0))} of {late.size} rows",
        )
    else:  # disable: the axis takes its own policy (not a configuration this script runs)
        out["lost_behaviour"] = policy
        checks.add(run, f"{lost} {policy}", False, "this script runs hold and ramp_to_zero only")
    return out


# --------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="build/accept/contributions")
    ap.add_argument("--json", default=None, help="write the table, the unplug figures and the checks here")
    ap.add_argument("--jobs", type=int, default=2, help="lockstep closed loops side by side")
    ap.add_argument("--speedup", type=float, default=1200.0, help="sets compd's loop period (2 s at 1200)")
    ap.add_argument("--unplug-at-s", type=float, default=43200.0, help="column sensors unplugged from (plant s)")
    ap.add_argument(
        "--xi-window-s",
        type=float,
        nargs=2,
        default=(41400.0, 43200.0),
        metavar=("FROM", "TO"),
        help="T_xi unplugged over [FROM, TO) (plant s)",
    )
    args = ap.parse_args(argv)
    work = Path(args.workdir).resolve()
    t_all = time.monotonic()
    models = fit_models(work)
    section = contributions_section(models)
    from hil_sim.scenario import Scenario

    day = Scenario.load(cl.SCENARIOS / f"{MACHINE}_unseen.yaml").duration_s
    at, (x0, x1) = args.unplug_at_s, args.xi_window_s
    unplugs = {
        "unplug_col_top": ("column", {"T_col_top": at}, (at, day)),
        "unplug_xi": ("spindle", {"T_xi": [x0, x1]}, (x0, x1)),
        "unplug_column": ("column", {"T_col_top": at, "T_col_bot": at}, (at, day)),
    }
    common = dict(machine=MACHINE, workdir=work, speedup=args.speedup, lockstep=True)
    runs: list[dict[str, Any]] = [
        dict(common, model_file=None, model_section=section, tag="sum", compd_log=True, log_period_s=LOG_PERIOD_S),
        dict(common, model_file=models["spindle"], tag="spindle"),
        dict(common, model_file=models["column"], tag="column"),
        dict(common, model_file=models["mlr"], tag="mlr"),
    ]
    for tag, (_, unplug, _) in unplugs.items():
        runs.append(
            dict(
                common,
                model_file=None,
                model_section=section,
                tag=tag,
                compd_log=True,
                log_period_s=LOG_PERIOD_S,
                scenario=unplug_scenario(unplug, work / f"{MACHINE}_{tag}.yaml"),
            )
        )
    results = dict(zip([r["tag"] for r in runs], cl.closed_loops(runs, args.jobs), strict=True))

    table_rows = [results[k] for k in ("sum", "spindle", "column", "mlr")]
    print("\nvmc unseen day, closed loop (lockstep), FANUC PMC word:")
    print(cl.table(table_rows))
    for r in results.values():
        print(
            f"  {r['model']:<15} {r['plant_s'] / 3600:.0f} plant h in {r['wall_s']:.0f} s wall; compd faults"
            f" {r['faults']}"
        )

    checks = Checks()
    print("\nchecks:")
    after = {k: results[k]["axes"][AXIS]["rms_after_um"] for k in ("sum", "spindle", "column", "mlr")}
    for alone in ("spindle", "column"):
        checks.add(
            "sum",
            f"sum better than {alone} alone",
            after["sum"] < after[alone],
            f"RMS {after['sum']:.2f} um vs {after[alone]:.2f} um",
        )
    for tag in ("sum", *unplugs):
        check_slew(tag, results[tag], checks)
    figures = []
    for tag, (lost, _, span) in unplugs.items():
        figures.append(check_unplug(tag, results[tag], results["sum"], lost, span, POLICIES[lost], checks))

    print("\nunplugged spans (RMS over the span, um):")
    print(
        f"  {'run':<15} {'lost':<8} {'span_h':<11} {'uncomp.':>8} {'residual':>8} {'lost part':>9}"
        f" {'its left':>8} {'other part':>10} {'rest':>6}  lost contribution"
    )
    for f in figures:
        print(
            f"  {f['run']:<15} {f['lost']:<8} {f['span_s'][0] / 3600:4.1f}-{f['span_s'][1] / 3600:<5.1f}"
            f" {f['rms_uncompensated_um']:>8.2f} {f['rms_residual_um']:>8.2f} {f['rms_lost_part_um']:>9.2f}"
            f" {f['rms_lost_left_um']:>8.2f} {f['rms_other_part_um']:>10.2f} {f['rms_rest_um']:>6.2f} "
            f" {f['lost_behaviour']}"
        )
    wall = time.monotonic() - t_all
    print(f"\n{len(results)} closed-loop runs, fits included, in {wall:.0f} s wall (lockstep, {args.jobs} at once)")
    if args.json:
        doc = {
            "models": {k: str(v) for k, v in models.items()},
            "closed_loop": table_rows,
            "unplug_runs": [results[k] for k in unplugs],
            "unplug": figures,
            "checks": checks.items,
            "notes": checks.notes,
            "ok": not checks.failed,
            "wall_s": wall,
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=2))
    if checks.failed:
        print("failed: " + "; ".join(f"{c['run']}: {c['check']}" for c in checks.failed))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
