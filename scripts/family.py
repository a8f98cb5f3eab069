"""Issue 29: compd's models on randomized families of simulated machines, judged as a distribution.

usage: python scripts/family.py [--kinds lathe spindle gantry feed_axis] [--seeds 1-20] [--jobs N]
       [--workdir build/family] [--fresh] [--json FILE] [--probe-every-h H] [--day-h H] [--gate]
       [--train day|plan]

The harness
-----------
For each kind and seed, hil_sim.family draws one machine (its physics, sensors and two days,
hil_sim/README.md "Randomized families") and logs its training and its unseen day (lathe
every 60 s, spindle 10 s, gantry 30 s, feed axis 10 s; the logs and machine files are kept
in --workdir and reused while the drawn machine is the same, unless --fresh). On the
training day it fits, through compd.commissioning.fitting.fit_model with compd's default options,

  lathe      ar1 on the bed sensors T3 T4 T5
  spindle    xi_spindle on T_xi and speed_rpm, target err_z_um only
  gantry     lvr on every temperature
  feed_axis  feed_axis, with linear_p0_mm at mid-stroke and length_mm the drawn stroke

and the baseline mlr on every temperature column (same targets). Each model is replayed on
the machine's unseen day by compd.commissioning.replay.replay_log, in process, into the machine's sink
wired as rig/closedloop.py's MACHINES are (lathe and feed axis: Siemens NC, spindle: FANUC
PMC word, gantry: PCI-1756 card; the guard's slew 0.2 µm/s as there); the replay tells the
Siemens NC the logged axis position of each row, as the live plant does in the closed loop.

The table gives per type, axis and model the median, 10th percentile and worst RMS reduction
(the replay report's axes.<axis>.reduction_pct) over the machines' unseen days, the MLR
median, and on how many machines MLR did better. A fit or replay that fails counts as a
failure (reduction −∞ in the order statistics, "fail" where one lands, and the `failed`
column), never dropped; --json gets every machine's figures and each failure's reason. The
10th percentile is a machine's figure (the lower one: with 10 machines, the worst). The
summary also lists the machines whose working-day RMS error (to the end of the day's last
run) falls outside 5-40 µm, the band a machine of the family should lie in.

Probes (--probe-every-h H; defaults lathe 2 h, feed axis 1 h, 0 = none): a copy of the unseen
log gets probe_<axis>_um (every H hours the true error + N(0, 0.3 µm), blank between; the
feed axis also probe_pos_<axis>_mm) and is replayed with compd's adapter (its default
settings); the table then gives the medians with and without probes and the largest loss in
points that probing caused on one machine.

The goals (issue 29) are printed under the table, and with --gate a missed one exits 1 (`make
accept`): on every type the physics model's 10th percentile at least 85 % (the spindle's axial
error 90 %), its median at least MLR's, and probing never costing a machine more than 0.5 points.

Machines run side by side in --jobs processes (default: the CPU count). --day-h shortens
both days (durations scaled, the same draws otherwise): for quick checks and the tests.

--train plan fits each machine on the thermal test `compd testplan` designs for it instead of its
drawn training day (hil_sim.family.PLAN: the type's speed range, or its axis's stroke and feed
range, the day's hours, compd's defaults otherwise; the same ambient); the unseen day is the same.
Its logs go to build/family-plan unless --workdir says otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from compd.core.errors import BadInput  # noqa: E402
from hil_sim import family  # noqa: E402

PHYSICS = {"lathe": "ar1", "spindle": "xi_spindle", "gantry": "lvr", "feed_axis": "feed_axis"}
PROBE_EVERY_H = {"lathe": 2.0, "feed_axis": 1.0}  # issue 17's probing rows
PROBE_SIGMA_UM = 0.3
SLEW_UM_PER_S = 0.2  # the guard's slew in rig/closedloop.py's compd config (plant time)
STALE_AFTER_S = 600.0  # rows come every 10-60 s: a row is never stale before the next
SANE_UM = (5.0, 40.0)  # the working-day RMS error a machine of the family should have (the summary lists others)
SCORED = {"spindle": ("z",)}  # axes a kind is judged on, where not every error column
# issue 29's goals: the physics model's 10th percentile on every type (the spindle's axial error higher),
# its median at least MLR's, and probes never costing more than half a point
GOAL_P10 = {"lathe": 85.0, "spindle": 90.0, "gantry": 85.0, "feed_axis": 85.0}
PROBE_LOSS_MAX_PTS = 0.5
CALIBRATED = 0.8  # issue 40: the stated unseen-day RMS within 0.5-2x of the actual on this share of the machines


# --------------------------------------------------------------------------------------
# logs
def machine_logs(
    kind: str, seed: int, work: Path, fresh: bool, day_h: float, train: str = "day"
) -> tuple[Path, Path, family.Machine, bool]:
    """(train log, unseen log, machine, whether they were reused) in `work`; logged again when
    --fresh or when the cached machine file is not the machine drawn now."""
    import yaml

    m = family.draw(kind, seed, day_h, train)
    rate = family.RATES_S[kind]
    stem = work / f"{kind}_{seed}"
    train, unseen, machine_file = (Path(f"{stem}_{s}") for s in ("train.csv", "unseen.csv", "machine.yaml"))
    if not fresh and train.exists() and unseen.exists() and machine_file.exists():
        try:
            cached = yaml.safe_load(machine_file.read_text(encoding="utf-8")) or {}
        except (OSError, yaml.YAMLError):
            cached = {}
        cached.pop("errors_um", None)
        if cached == {**m.to_dict(), "log_rate_s": rate}:
            return train, unseen, m, True
    family.write_machine(m, work, rate)
    return train, unseen, m, False


# --------------------------------------------------------------------------------------
# fits
def fit_plan(
    kind: str, m: family.Machine, temps: list[str]
) -> dict[str, tuple[str, list[str] | None, list[str] | None, dict[str, Any]]]:
    """tag → (model kind, inputs, targets, options): the type's physics model and MLR."""
    if kind == "lathe":
        physics = ("ar1", ["T3", "T4", "T5"], None, {})
    elif kind == "spindle":
        physics = ("xi_spindle", ["T_xi", "speed_rpm"], ["err_z_um"], {})
    elif kind == "gantry":
        physics = ("lvr", list(temps), None, {})
    else:
        stroke = float(m.drawn["placement"]["stroke_mm"])
        physics = ("feed_axis", None, None, {"linear_p0_mm": stroke / 2.0, "length_mm": stroke})
    return {PHYSICS[kind]: physics, "mlr": ("mlr", list(temps), physics[2], {})}


# --------------------------------------------------------------------------------------
# sinks, wired as rig/closedloop.py's MACHINES
def make_sink(kind: str, axes: list[str]) -> Any:
    """The machine's sink on its in-process device (no host)."""
    if kind == "spindle":
        from compd.sinks.fanuc_pmc import FanucPmcConfig, FanucPmcSink

        return FanucPmcSink(FanucPmcConfig(kind="fanuc_pmc", mode="word", max_step_um=5.0, min_update_s=1.0))
    if kind == "gantry":
        from compd.sinks.pci1756 import Pci1756Config, Pci1756Sink

        # the card's DO bytes 0-3 as wired to the PMC's X0-X3: word on X0/X1, strobe X2.0
        return Pci1756Sink(
            Pci1756Config(kind="pci1756", device="emulated", x_register=0, strobe_bit=16, heartbeat_bit=24)
        )
    from compd.sinks.siemens import SiemensConfig, SiemensSink

    cfg = SiemensConfig(kind="siemens", axes={a: i for i, a in enumerate(axes)}, min_change_um=0.2, min_update_s=5.0)
    return SiemensSink(cfg)  # compd's replay tells the NC each row's pos_<axis>_mm, as the live plant does


def replay(kind: str, model: Any, log: Any) -> dict[str, Any]:
    """compd's replay of `log` through `model` into the machine's sink: the report."""
    from compd.commissioning.fitting import clone
    from compd.commissioning.replay import replay_log
    from compd.core.config import CodecConfig, GuardConfig

    axes = list(model.outputs)
    guard = GuardConfig(max_slew_um_per_s=SLEW_UM_PER_S, stale_after_s=STALE_AFTER_S)
    return replay_log(log, clone(model), make_sink(kind, axes), guard, CodecConfig(axes=axes)).report


def with_probes(log: Any, axes: list[str], every_s: float, rng: np.random.Generator) -> Any:
    """A copy of `log` with probe_<axis>_um (the true error + N(0, σ²) at the first row of
    every `every_s`, NaN between) and, where the axis has a position, probe_pos_<axis>_mm."""
    from compd.log import Log

    t = log.t_s
    rows = []
    nxt = t[0] + every_s
    for i, ti in enumerate(t):
        if ti + 1e-9 >= nxt:
            rows.append(i)
            nxt += every_s * max(1, math.floor((ti - nxt) / every_s) + 1)
    cols, data = list(log.columns), [log.data]
    for a in axes:
        z = np.full(len(log), np.nan)
        z[rows] = log.col(f"err_{a}_um")[rows] + rng.normal(0.0, PROBE_SIGMA_UM, len(rows))
        cols.append(f"probe_{a}_um")
        data.append(z[:, None])
        if f"pos_{a}_mm" in log.columns:
            p = np.full(len(log), np.nan)
            p[rows] = log.col(f"pos_{a}_mm")[rows]
            cols.append(f"probe_pos_{a}_mm")
            data.append(p[:, None])
    return Log(log.file, cols, np.hstack(data))


def _axes_figures(report: dict[str, Any]) -> dict[str, dict[str, float]]:
    return {
        a: {k: float(v[k]) for k in ("reduction_pct", "rms_before_um", "rms_after_um", "max_abs_after_um")}
        for a, v in report["axes"].items()
    }


def _why(stage: str, e: BaseException) -> str:
    tail = traceback.format_exception(type(e), e, e.__traceback__)[-3:]
    return f"{stage}: {type(e).__name__}: {str(e).strip()[:400]} | " + " ".join(s.strip() for s in tail)[-600:]


# --------------------------------------------------------------------------------------
# one machine (in a worker process)
def run_machine(
    kind: str,
    seed: int,
    work: str,
    fresh: bool,
    probe_every_h: float,
    day_h: float,
    train: str = "day",
    recommend: bool = True,
) -> dict[str, Any]:
    """Log, fit, replay one machine: its figures (and the reasons of what failed)."""
    os.environ["TQDM_DISABLE"] = "1"  # no progress bars from parallel fits
    from compd.commissioning import fitting
    from compd.log import read_log

    t0 = time.monotonic()
    out: dict[str, Any] = {"kind": kind, "seed": seed, "models": {}}
    try:
        train_file, unseen_file, m, reused = machine_logs(kind, seed, Path(work), fresh, day_h, train)
        train = fitting.read_fit_log(train_file)
        unseen = read_log(unseen_file, allow_nan=True)
    except Exception as e:  # noqa: BLE001 - a machine that cannot be logged is reported, not fatal
        out["failed"] = _why("log", e)
        out["wall_s"] = time.monotonic() - t0
        return out
    out["logs_reused"] = reused
    out["drawn"] = {
        "duty": m.drawn["duty"],
        "placement": m.drawn["placement"],
        **({"plan": m.drawn["plan"]} if "plan" in m.drawn else {}),
    }
    out["error_um"] = {
        day: {c[4:-3]: float(np.sqrt(np.mean(lg.col(c) ** 2))) for c in lg.error_columns()}
        for day, lg in (("train", train), ("unseen", unseen))
    }
    out["working_error_um"] = {  # to the end of the day's last run: what the machine does at work
        day: {c[4:-3]: family.working_rms_um(lg.col(c), lg.t_s, sc) for c in lg.error_columns()}
        for day, lg, sc in (("train", train, m.train), ("unseen", unseen, m.unseen))
    }
    probe_h = PROBE_EVERY_H.get(kind, 0.0) if probe_every_h < 0 else probe_every_h
    models_dir = Path(work) / "models"
    models_dir.mkdir(parents=True, exist_ok=True)
    for tag, (fit_kind, inputs, targets, options) in fit_plan(kind, m, train.temperature_columns()).items():
        res: dict[str, Any] = {"kind": fit_kind, "inputs": inputs, "targets": targets, "options": options}
        out["models"][tag] = res
        try:
            # as `compd fit` does: the held-out comparison too (its figure is the probe adapter's σ_m)
            oc = fitting.fit_model(fit_kind, train, inputs, targets, dict(options))
        except Exception as e:  # noqa: BLE001
            res["failed"] = _why("fit", e)
            continue
        res["warnings"] = list(oc.warnings)
        res["form"] = oc.report.get("details", {}).get("form")
        try:
            fitting.write_model(oc.model, models_dir / f"{kind}_{seed}_{tag}.yaml")
        except Exception as e:  # noqa: BLE001 - the file is for inspection only
            res["model_file_error"] = _why("write_model", e)
        try:
            res["axes"] = _axes_figures(replay(kind, oc.model, unseen))
        except Exception as e:  # noqa: BLE001
            res["failed"] = _why("replay", e)
            continue
        if probe_h > 0:
            rng = np.random.default_rng([seed, 29])  # the same probes for every model of the machine
            try:
                probed = with_probes(unseen, list(oc.model.outputs), probe_h * 3600.0, rng)
                rep = replay(kind, oc.model, probed)
                res["probed"] = {
                    "every_h": probe_h,
                    "axes": _axes_figures(rep),
                    "adaptation": {k: rep.get("adaptation", {}).get(k) for k in ("accepted", "rejected")},
                }
            except Exception as e:  # noqa: BLE001
                res["probed"] = {"every_h": probe_h, "failed": _why("probed replay", e)}
    if recommend:
        # the machine's deployment options, as its user gives them to `compd fit --kind all` (the feed
        # axis's Siemens sink takes the linear form over the stroke: linear_p0_mm, length_mm)
        deploy = fit_plan(kind, m, train.temperature_columns())[PHYSICS[kind]][3] if kind == "feed_axis" else {}
        out["models"]["recommended"] = recommended(kind, seed, train, unseen, models_dir, probe_h, deploy)
    out["wall_s"] = time.monotonic() - t0
    return out


def recommended(
    kind: str,
    seed: int,
    train: Any,
    unseen: Any,
    models_dir: Path,
    probe_h: float,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """`compd fit --kind all` on the training day (every kind with its own defaults and the machine's
    deployment `options`, the sums of two stages), its recommended model replayed on the unseen day;
    beside it what the fit stated it would leave there (fit.expected_unseen) and the ratio of what it
    left to that."""
    from compd.commissioning import fitting

    targets = [f"err_{a}_um" for a in SCORED[kind]] if kind in SCORED else None
    res: dict[str, Any] = {"kind": "all"}
    try:
        rows = fitting.fit_all(train, None, targets, dict(options or {}))
        pick, sums = fitting.recommendation(train, rows, targets)
        if pick is None:
            raise ValueError("no recommendation")
        path = models_dir / f"{kind}_{seed}_recommended.yaml"
        fitting.write_recommended(pick, train, path)
        model = fitting.load_model(path)
    except Exception as e:  # noqa: BLE001
        res["failed"] = _why("fit --kind all", e)
        return res
    res["label"] = pick.candidate.label
    res["held_out_um"] = dict(pick.candidate.axes)
    res["stated"] = {a: s.as_dict() for a, s in pick.stated.items()}
    res["candidates"] = {
        label: {a: v for a, v in (oc.report.get("baseline_mlr", {}).get("axes", {}) or {}).items()}
        for _, label, oc, _ in rows
        if oc is not None
    }
    res["sums"] = {so.label: so.held_out_um for so in sums}
    try:
        res["axes"] = _axes_figures(replay(kind, model, unseen))
    except Exception as e:  # noqa: BLE001
        res["failed"] = _why("replay", e)
        return res
    # the statement is the model's: judged on the model's own unseen-day RMS (compd score), not on the
    # replay, which adds the output's word resolution (a 1 um LSB alone is 0.29 um RMS) and its slew
    scored = fitting.score_model(model, unseen)["axes"]
    res["calibration"] = {
        a: scored[a]["rms_after_um"] / s.rms_um for a, s in pick.stated.items() if a in scored and s.rms_um > 0
    }
    res["calibration_replay"] = {
        a: res["axes"][a]["rms_after_um"] / s.rms_um
        for a, s in pick.stated.items()
        if a in res["axes"] and s.rms_um > 0
    }
    if probe_h > 0:
        rng = np.random.default_rng([seed, 29])
        try:
            probed = with_probes(unseen, list(model.outputs), probe_h * 3600.0, rng)
            res["probed"] = {"every_h": probe_h, "axes": _axes_figures(replay(kind, model, probed))}
        except Exception as e:  # noqa: BLE001
            res["probed"] = {"every_h": probe_h, "failed": _why("probed replay", e)}
    return res


# --------------------------------------------------------------------------------------
# the table
def _reduction(res: dict[str, Any] | None, axis: str, probed: bool = False) -> float:
    """The machine's reduction on `axis` (%), −∞ for a failure."""
    if res is None or "failed" in res:
        return -math.inf
    if probed:
        res = res.get("probed")
        if res is None or "failed" in res:
            return -math.inf
    v = res.get("axes", {}).get(axis)
    return -math.inf if v is None else float(v["reduction_pct"])


def _stats(values: list[float]) -> tuple[float, float, float]:
    """median, 10th percentile (a machine's value: the lower one), worst; −∞ counts."""
    a = np.sort(np.asarray(values, float))
    if a.size == 0:
        return math.nan, math.nan, math.nan
    k = max(0, math.ceil(0.1 * a.size) - 1)
    mid = a.size // 2
    med = a[mid] if a.size % 2 else (a[mid - 1] + a[mid]) / 2.0
    return float(med), float(a[k]), float(a[0])


def _fmt(v: float) -> str:
    if math.isnan(v):
        return "—"
    return "fail" if math.isinf(v) else f"{v + 0.0:.1f}".replace("-0.0", "0.0")


def summary_rows(results: list[dict[str, Any]], kinds: list[str]) -> list[dict[str, Any]]:
    """Per type, axis and model: the order statistics of the reductions."""
    rows = []
    for kind in kinds:
        mine = [r for r in results if r["kind"] == kind]
        if not mine:
            continue
        physics = PHYSICS[kind]
        axes: list[str] = []
        for r in mine:
            for res in r.get("models", {}).values():
                axes += [a for a in res.get("axes", {}) if a not in axes]
        if not axes:  # nothing replayed at all: one row of failures
            axes = ["?"]
        tags = [physics, "mlr"] + (["recommended"] if any("recommended" in r.get("models", {}) for r in mine) else [])
        for axis in axes:
            for tag in tags:
                vals = [_reduction(r.get("models", {}).get(tag), axis) for r in mine]
                mlr = [_reduction(r.get("models", {}).get("mlr"), axis) for r in mine]
                med, p10, worst = _stats(vals)
                row: dict[str, Any] = {
                    "type": kind,
                    "axis": axis,
                    "model": tag,
                    "machines": len(mine),
                    "failed": sum(math.isinf(v) for v in vals),
                    "median": med,
                    "p10": p10,
                    "worst": worst,
                    "mlr_median": _stats(mlr)[0],
                    "mlr_better_on": None if tag == "mlr" else sum(b > a for a, b in zip(vals, mlr, strict=True)),
                }
                with_p = [r.get("models", {}).get(tag, {}).get("probed") for r in mine]
                if any(p is not None for p in with_p):
                    w = [_reduction(r.get("models", {}).get(tag), axis, probed=True) for r in mine]
                    row["probe_every_h"] = next(p["every_h"] for p in with_p if p is not None)
                    row["with_probes_median"] = _stats(w)[0]
                    row["without_probes_median"] = med
                    losses = [a - b for a, b in zip(vals, w, strict=True) if math.isfinite(a) and math.isfinite(b)]
                    row["largest_probe_loss_pts"] = max(losses) if losses else math.nan
                if tag == "recommended":
                    labels = [
                        r["models"]["recommended"].get("label", "fail") for r in mine if "recommended" in r["models"]
                    ]
                    row["picked"] = {k: labels.count(k) for k in sorted(set(labels))}
                    ratios = [r["models"]["recommended"].get("calibration", {}).get(axis) for r in mine]
                    row["calibrated"] = sum(1 for v in ratios if v is not None and 0.5 <= v <= 2.0)
                    row["calibration_ratios"] = [None if v is None else round(v, 3) for v in ratios]
                rows.append(row)
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| type | axis | model | median | 10th pct | worst | MLR median | MLR better on | failed "
        "| probes every | with probes | without | largest loss |"
    )
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        better = "—" if r["mlr_better_on"] is None else f"{r['mlr_better_on']}/{r['machines']}"
        probe = ("—", "—", "—", "—")
        if "probe_every_h" in r:
            probe = (
                f"{r['probe_every_h']:g} h",
                _fmt(r["with_probes_median"]),
                _fmt(r["without_probes_median"]),
                _fmt(r["largest_probe_loss_pts"]),
            )
        lines.append(
            f"| {r['type']} | {r['axis']} | {r['model']} | {_fmt(r['median'])} | {_fmt(r['p10'])} | {_fmt(r['worst'])} "
            f"| {_fmt(r['mlr_median'])} | {better} | {r['failed']}/{r['machines']} | " + " | ".join(probe) + " |"
        )
    picks = [r for r in rows if r["model"] == "recommended"]
    if picks:
        lines += [
            "",
            "| type | axis | recommended kinds | stated within 0.5-2x of the unseen RMS | ratios (unseen / stated) |",
            "|---|---|---|---|---|",
        ]
        for r in picks:
            kinds = ", ".join(f"{k} {n}" for k, n in r["picked"].items())
            ratios = " ".join("—" if v is None else f"{v:.2f}" for v in r["calibration_ratios"])
            lines.append(f"| {r['type']} | {r['axis']} | {kinds} | {r['calibrated']}/{r['machines']} | {ratios} |")
    return "\n".join(lines)


def _line(r: dict[str, Any]) -> str:
    if "failed" in r:
        return f"{r['kind']} {r['seed']}: FAILED {r['failed'][:200]}"
    parts = []
    for tag, res in r["models"].items():
        if "failed" in res:
            parts.append(f"{tag} FAILED ({res['failed'].split(' | ')[0][:120]})")
            continue
        fig = ", ".join(f"{a} {v['reduction_pct']:.1f} %" for a, v in res["axes"].items())
        if tag == "recommended":
            fig = (
                f"{res.get('label')}: "
                + fig
                + " (stated "
                + ", ".join(f"{a} {s['rms_um']:.2f} um" for a, s in res.get("stated", {}).items())
                + ", left "
                + ", ".join(f"{a} {v['rms_after_um']:.2f} um" for a, v in res["axes"].items())
                + ")"
            )
        if "probed" in res and "axes" in res["probed"]:
            fig += (
                " (probed "
                + ", ".join(f"{a} {v['reduction_pct']:.1f} %" for a, v in res["probed"]["axes"].items())
                + ")"
            )
        parts.append(f"{tag} {fig}")
    err = ", ".join(f"{a} {v:.1f}" for a, v in r["error_um"]["unseen"].items())
    return f"{r['kind']} {r['seed']}: unseen RMS {err} um; " + "; ".join(parts) + f" ({r['wall_s']:.0f} s)"


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("-inf" if x < 0 else "inf")
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", nargs="+", default=list(family.KINDS), help=f"of {', '.join(family.KINDS)}")
    ap.add_argument("--seeds", default="1-20", help="e.g. 1-20 or 1,4,9-12: one machine per seed")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="machines side by side (processes)")
    ap.add_argument(
        "--workdir",
        default=None,
        help="logs, machine files, fitted models (default build/family, with --train plan build/family-plan)",
    )
    ap.add_argument("--fresh", action="store_true", help="log every day again (default: reuse the cached logs)")
    ap.add_argument("--json", default=None, help="write every machine's figures and the table here")
    ap.add_argument(
        "--probe-every-h",
        type=float,
        default=-1.0,
        help="probe every H hours on every kind (0: no probes; default: lathe 2, feed_axis 1)",
    )
    ap.add_argument("--day-h", type=float, default=24.0, help="shorten both days to H hours (quick checks)")
    ap.add_argument(
        "--train",
        choices=family.TRAINS,
        default="day",
        help="fit on the drawn training day (default) or on compd testplan's plan for the machine",
    )
    ap.add_argument(
        "--no-recommend",
        action="store_true",
        help="skip `compd fit --kind all`'s recommended model (the slowest part of a machine)",
    )
    ap.add_argument(
        "--gate",
        action="store_true",
        help="exit 1 when a goal is missed: the physics model's 10th percentile (lathe, gantry, feed axis"
        " 85 %%, spindle 90 %%), its median below MLR's, or probes costing a machine more than 0.5 points",
    )
    args = ap.parse_args(argv)
    try:
        unknown = [k for k in args.kinds if k not in family.KINDS]
        if unknown:
            raise BadInput(f"unknown kind {unknown[0]!r} (known: {', '.join(family.KINDS)})", path="--kinds")
        seeds = family.parse_seeds(args.seeds)
        if args.jobs < 1:
            raise BadInput("--jobs must be >= 1")
        if not args.day_h > 0:
            raise BadInput("--day-h must be > 0")
    except BadInput as e:
        print(f"family: {e}", file=sys.stderr)
        return 2
    work = Path(args.workdir or ("build/family-plan" if args.train == "plan" else "build/family")).resolve()
    work.mkdir(parents=True, exist_ok=True)
    # the costliest kinds first, so the last jobs to start are short ones
    order = {"feed_axis": 0, "gantry": 1, "lathe": 2, "spindle": 3}
    jobs = sorted(((k, s) for k in args.kinds for s in seeds), key=lambda ks: (order.get(ks[0], 9), ks[1]))
    t0 = time.monotonic()
    results: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=min(args.jobs, len(jobs))) as pool:
        futures = {
            pool.submit(
                run_machine,
                k,
                s,
                str(work),
                args.fresh,
                args.probe_every_h,
                args.day_h,
                args.train,
                not args.no_recommend,
            ): (k, s)
            for k, s in jobs
        }
        for fut in as_completed(futures):
            k, s = futures[fut]
            try:
                r = fut.result()
            except Exception as e:  # noqa: BLE001 - a worker that died still counts
                r = {"kind": k, "seed": s, "failed": _why("worker", e), "models": {}}
            results.append(r)
            print(_line(r), flush=True)
    wall_s = time.monotonic() - t0
    results.sort(key=lambda r: (args.kinds.index(r["kind"]), r["seed"]))
    rows = summary_rows(results, list(args.kinds))
    print()
    print(table(rows))
    odd = [
        f"{r['kind']} {r['seed']} {day} {a} {v:.1f}"
        for r in results
        for day, axes in r.get("working_error_um", {}).items()
        for a, v in axes.items()
        if a in SCORED.get(r["kind"], (a,)) and not SANE_UM[0] <= v <= SANE_UM[1]
    ]
    print(f"\nworking-day RMS error outside {SANE_UM[0]:g}-{SANE_UM[1]:g} um: " + ("; ".join(odd) or "none"))
    print(
        f"{len(results)} machines ({', '.join(args.kinds)}; seeds {args.seeds}; trained on the"
        f" {'drawn day' if args.train == 'day' else 'compd testplan plan'}) in {wall_s:.0f} s wall, "
        f"{args.jobs} at once; workdir {work}"
    )
    missed = goals_missed(rows)
    print("goals: " + ("all met" if not missed else "missed: " + "; ".join(missed)))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(
            json.dumps(
                _json_safe(
                    {
                        "kinds": args.kinds,
                        "seeds": seeds,
                        "day_h": args.day_h,
                        "probe_every_h": args.probe_every_h,
                        "train": args.train,
                        "wall_s": wall_s,
                        "table": rows,
                        "goals_missed": missed,
                        "machines": results,
                    }
                ),
                indent=1,
            )
        )
    return 1 if args.gate and missed else 0


def goals_missed(rows: list[dict[str, Any]]) -> list[str]:
    """The goals (issue 40) the table's recommended rows miss (GOAL_P10, median ≥ MLR's, the stated accuracy
    within 0.5-2x of the unseen RMS on CALIBRATED of the machines, PROBE_LOSS_MAX_PTS), one line each; where
    no recommended row was run, the physics rows' (issue 29)."""
    out = []
    judged = "recommended" if any(r["model"] == "recommended" for r in rows) else None
    for r in rows:
        if r["model"] != (judged or PHYSICS[r["type"]]):
            continue
        if judged and not r["calibrated"] >= CALIBRATED * r["machines"]:
            out.append(
                f"{r['type']}/{r['axis']} stated accuracy within 0.5-2x on {r['calibrated']}/{r['machines']}"
                f" machines (< {CALIBRATED:.0%})"
            )
        name = f"{r['type']}/{r['axis']}"
        goal = GOAL_P10[r["type"]]
        if not r["p10"] >= goal:
            out.append(f"{name} 10th percentile {_fmt(r['p10'])} % < {goal:g} %")
        if not r["median"] >= r["mlr_median"]:
            out.append(f"{name} median {_fmt(r['median'])} % < MLR's {_fmt(r['mlr_median'])} %")
        loss = r.get("largest_probe_loss_pts")
        if loss is not None and not loss <= PROBE_LOSS_MAX_PTS:
            out.append(f"{name} probes cost a machine {_fmt(loss)} points (> {PROBE_LOSS_MAX_PTS:g})")
    return out


if __name__ == "__main__":
    sys.exit(main())
