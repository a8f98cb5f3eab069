"""Commissioning commands, each one's arguments beside it.

`compd testplan`, `fit`, `predict`, `score`, `xi`, `replay`, `plot`, `report`, `output-test`.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from compd.cli.args import (
    check_output,
    check_plot,
    command,
    count,
    finite,
    non_negative,
    positive,
    writing,
)
from compd.core.errors import BadInput

log = logging.getLogger("compd")


def args_testplan(sub: Any) -> None:
    """`compd testplan`'s arguments."""
    s = sub.add_parser(
        "testplan",
        help="design the thermal test of a machine: the plan as CSV and the program for its control",
        description="Design the thermal test of a machine for identification (docs/testplan.md): every speed level"
        " held short and long in a pseudo-random order, cool-down pauses, an idle stretch at the start,"
        " a measurement every N minutes; write it as CSV and, with --gcode, as a program.",
        epilog="example:\n  compd testplan --max-rpm 12000 --hours 24 --out plan.csv --gcode linuxcnc"
        " --program plan.ngc"
        "\n  compd testplan --max-rpm 4500 --hours 24 --axis z:600:8000 --out plan.csv --gcode fanuc"
        " --program O2303.nc --probe-call 'M98 P9010'",
    )
    s.add_argument(
        "--max-rpm",
        required=True,
        type=non_negative,
        dest="max_rpm",
        metavar="N",
        help="the spindle's highest speed (0: no spindle; the axes' feeds are the spectrum)",
    )
    s.add_argument("--hours", required=True, type=positive, metavar="H", help="the time the test may take")
    s.add_argument("--out", required=True, metavar="PLAN.csv")
    s.add_argument(
        "--min-rpm",
        type=positive,
        default=None,
        dest="min_rpm",
        metavar="N",
        help="the lowest running speed (default 10 %% of --max-rpm)",
    )
    s.add_argument(
        "--levels",
        type=count,
        default=7,
        metavar="N",
        help="speed levels, the lowest and the highest included (default 7)",
    )
    s.add_argument(
        "--time-constant-min",
        type=positive,
        default=60.0,
        dest="time_constant_min",
        metavar="MIN",
        help="your guess of the machine's thermal time constant: the holds span a quarter of it to"
        " three times it (default 60)",
    )
    s.add_argument(
        "--probe-every-min",
        type=positive,
        default=10.0,
        dest="probe_every_min",
        metavar="MIN",
        help="a measurement every MIN minutes (default 10)",
    )
    s.add_argument(
        "--step-min",
        type=positive,
        default=None,
        dest="step_min",
        metavar="MIN",
        help="every change falls on this grid (default: the measuring interval, so every change is measured)",
    )
    s.add_argument(
        "--idle-hours",
        type=non_negative,
        default=1.0,
        dest="idle_hours",
        metavar="H",
        help="the machine at rest at the start, for the shop's air alone (default 1)",
    )
    s.add_argument(
        "--axis",
        action="append",
        default=None,
        metavar="NAME:STROKE_MM:MAX_FEED_MM_MIN[:MIN]",
        help="a linear axis the test moves over its stroke (repeat for more; min feed default 10 %%)",
    )
    s.add_argument(
        "--feed-levels", type=count, default=4, dest="feed_levels", metavar="N", help="feed levels per axis (default 4)"
    )
    s.add_argument("--seed", type=int, default=0, help="the pseudo-random order's seed (default 0)")
    s.add_argument(
        "--gcode",
        choices=("linuxcnc", "fanuc", "siemens"),
        default=None,
        help="also write the program for this control",
    )
    s.add_argument("--program", default=None, metavar="FILE", help="the program's file (with --gcode)")
    s.add_argument(
        "--probe-call",
        default=None,
        dest="probe_call",
        metavar="TEXT",
        help="the line that calls your measuring routine (default: linuxcnc 'o<probe> call',"
        " fanuc 'M98 P9000', siemens 'PROBE_Z': placeholders for your own routine)",
    )


@command("testplan", args_testplan)
def cmd_testplan(args: argparse.Namespace) -> int:
    from compd.commissioning import testplan as tp

    if (args.gcode is None) != (args.program is None):
        raise BadInput("give --gcode and --program together", path="--program" if args.gcode else "--gcode")
    if args.probe_call is not None and args.gcode is None:
        raise BadInput("the measuring call goes into a program: give --gcode and --program", path="--probe-call")
    call = tp.check_probe_call(args.probe_call or tp.PROBE_CALLS[args.gcode], args.gcode) if args.gcode else ""
    axes = [tp.parse_axis(a) for a in args.axis or []]
    check_output(args.out, "--out")
    check_output(args.program, "--program")
    plan = tp.design(
        args.max_rpm,
        args.hours,
        min_rpm=args.min_rpm,
        probe_every_min=args.probe_every_min,
        step_min=args.step_min,
        time_constant_min=args.time_constant_min,
        levels=args.levels,
        feed_levels=args.feed_levels,
        axes=axes,
        idle_hours=args.idle_hours,
        seed=args.seed,
    )
    with writing(args.out, "--out"):
        plan.write_csv(args.out)
    for line in tp.summary_lines(plan):
        print(f"compd testplan: {line}")
    done = f"compd testplan: {len(plan)} rows -> {args.out}"
    if args.gcode:
        text = tp.PROGRAMS[args.gcode](plan, call, Path(args.out).name)
        with writing(args.program, "--program"), open(args.program, "w", encoding="ascii", newline="\n") as fh:
            fh.write(text)
        done += f"; {args.gcode} program -> {args.program} (measuring call: {call})"
    print(done)
    for w in tp.warnings(plan):
        print(f"compd: warning: {w}", file=sys.stderr)
    return 0


def _fit_options_help() -> str:
    """`compd fit --help`'s list of the options of every kind (from compd.identify, imported here only)."""
    from compd.core.registry import NOT_INSTALLED, commissioning_missing

    try:
        from compd.identify import options_help
    except ModuleNotFoundError as e:
        if not commissioning_missing(e):
            raise
        return f"compd fit is {NOT_INSTALLED}."
    return options_help()


def args_fit(sub: Any) -> None:
    """`compd fit`'s arguments."""
    s = sub.add_parser(
        "fit",
        help="identify a model's coefficients from a log",
        description="Identify a model's coefficients from a log and write the model file (with its fit date and"
        " scores); --kind all fits every kind that applies and compares them."
        " With --on-residual-of the model is fitted stage by stage: on what a model fitted before leaves of the"
        " error (its prediction over the log subtracted, as compd predict evaluates it), and the report's stagewise"
        " block compares, held out, that sum with the kind alone, the model before alone and MLR on every input.",
        epilog="example:\n  compd fit --kind lvr --log day1.csv --out lvr.yaml --report fit.json"
        "\n  compd fit --kind ar1 --log day1.csv --out ar1.yaml --inputs T_bed --ambient T_amb --option dt_s=60"
        "\n  compd fit --kind mlr --log day1.csv --inputs T_col1 T_col2 --on-residual-of spindle.yaml"
        " --out column.yaml --report column.json",
    )
    s.add_argument("--kind", required=True, choices=["feed_axis", "lvr", "xi_spindle", "ar1", "mlr", "all"])
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--out", required=True, metavar="MODEL.yaml", help="model file (a folder with --kind all)")
    s.add_argument("--target", nargs="+", action="extend", default=None, metavar="COL")
    s.add_argument("--inputs", nargs="+", action="extend", default=None, metavar="COL")
    s.add_argument("--ambient", default=None, metavar="COL", help="ambient sensor (ar1 C3, feed_axis ζ)")
    s.add_argument(
        "--option",
        action="append",
        default=None,
        metavar="KEY=VALUE",
        help="a fit option of the kind (value read as YAML)",
    )
    s.add_argument("--report", default=None, metavar="REPORT.json")
    s.add_argument("--plot", default=None, metavar="FILE.png")
    s.add_argument(
        "--on-residual-of",
        action="append",
        default=None,
        dest="on_residual_of",
        metavar="MODEL.yaml",
        help="fit on what this model (fitted before) leaves: each target whose axis it predicts, less its"
        " prediction over the log; repeat it to subtract the sum of several models. The new model"
        " predicts the rest: the two add up (the model file's fit.on_residual_of names the first)",
    )
    s.epilog_extra = _fit_options_help


@command("fit", args_fit)
def cmd_fit(args: argparse.Namespace) -> int:
    from compd.commissioning import fitting, report

    options = fitting.parse_options(args.option)
    if args.ambient:
        options["ambient"] = args.ambient
    check_output(args.report, "--report")
    check_plot(args.plot)
    _not_over_a_model_before(args)
    # --kind all --out MODEL.yaml: the recommended model there, every kind's in MODEL.candidates/;
    # --out FOLDER: every kind's in the folder, the recommended one as FOLDER/recommended.yaml
    one_file = args.kind == "all" and Path(args.out).suffix in (".yaml", ".yml")
    folder = Path(args.out).with_suffix(".candidates") if one_file else Path(args.out)
    check_output(args.out, "--out", folder=args.kind == "all" and not one_file)  # last: it may create the folder
    if one_file:
        check_output(str(folder), "--out", folder=True)
    log = fitting.read_fit_log(args.log)
    stage = fitting.residual_stage(log, args.on_residual_of, args.target) if args.on_residual_of else None
    if stage is not None:
        print(fitting.stage_line(stage))
    if args.kind == "all":
        rows = fitting.fit_all(log, args.inputs, args.target, options, stage)
        pick, sums = fitting.recommendation(stage.log if stage else log, rows, args.target, stage)
        out = folder
        for _, label, oc, _ in rows:
            if oc is not None:
                with writing(out / f"{label}.yaml", "--out"):
                    fitting.write_model(oc.model, out / f"{label}.yaml")
                if args.plot:
                    p = Path(args.plot)
                    p = p.with_name(f"{p.stem}_{label}{p.suffix or '.png'}")
                    with writing(p, "--plot"):
                        report.plot_fit(oc, stage.log if stage else log, p)
                fitting.warn(oc.warnings)
        print(fitting.comparison_table(rows))
        for line in fitting.recommendation_lines(pick, sums):
            print(line)
        for so in sums:
            fitting.warn(so.warnings)
        recommended = Path(args.out) if one_file else folder / "recommended.yaml"
        if pick is not None:
            with writing(recommended, "--out"):
                fitting.write_recommended(pick, stage.log if stage else log, recommended)
            print(f"recommended model -> {recommended}" + (f" (every kind's in {folder}/)" if one_file else ""))
        if args.report:
            with writing(args.report, "--report"):
                report.write_json(
                    args.report,
                    {
                        **{label: oc.report if oc else {"skipped": why} for _, label, oc, why in rows},
                        **fitting.recommendation_report(pick, sums, recommended),
                    },
                )
        if pick is None:
            print(
                "compd: no model to recommend: every fit did not converge, removes almost nothing or could not be"
                " scored held out (see the warnings above)",
                file=sys.stderr,
            )
            return 1
        return 0
    oc = fitting.fit_model(args.kind, log, args.inputs, args.target, options, stage=stage)
    if stage is not None:
        log = stage.log  # the plot shows what the model was fitted to
    with writing(args.out, "--out"):
        fitting.write_model(oc.model, args.out)
    if args.report:  # the model file and plot beside the figures, for `compd report`
        files = {"model": str(args.out), **({"plot": str(args.plot)} if args.plot else {})}
        with writing(args.report, "--report"):
            report.write_json(args.report, {**oc.report, **files})
    if args.plot:
        with writing(args.plot, "--plot"):
            report.plot_fit(oc, log, args.plot)
    for axis, s in oc.report["axes"].items():
        print(
            f"{args.kind} axis {axis}: RMSE {s['rmse_um']:.3f} um, max {s['max_abs_err_um']:.3f} um,"
            f" {oc.report['rows']} rows, {oc.report['fit_time_s']:.2f} s -> {args.out}"
        )
    for line in fitting.stagewise_lines(oc):
        print(line)
    fitting.warn(oc.warnings)
    return 0


def _not_over_a_model_before(args: argparse.Namespace) -> None:
    """BadInput when `--out` would overwrite a model given to `--on-residual-of`."""
    from compd.identify import KINDS

    for file in args.on_residual_of or []:
        model = Path(file).resolve()
        out = Path(args.out).resolve()
        if args.kind != "all" and model == out:
            raise BadInput(f"would overwrite {file}, the model given to --on-residual-of", path="--out")
        if (
            args.kind == "all"
            and model.parent == out
            and any(model.stem == k or model.stem.startswith(f"{k}_") for k in KINDS)
        ):
            raise BadInput(
                f"the folder holds {file}, the model given to --on-residual-of, which --kind all could overwrite",
                path="--out",
            )


def args_predict(sub: Any) -> None:
    """`compd predict`'s arguments."""
    s = sub.add_parser(
        "predict",
        help="batch prediction of a fitted model over a log",
        description="Predict the thermal error of every row of a log with a fitted model (pred_<axis>_um columns).",
        epilog="example:\n  compd predict lvr.yaml --log day2.csv --out pred.csv",
    )
    s.add_argument("model", metavar="MODEL.yaml")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--out", required=True, metavar="PRED.csv")


@command("predict", args_predict)
def cmd_predict(args: argparse.Namespace) -> int:
    from compd.commissioning import fitting

    check_output(args.out, "--out")
    model = fitting.load_model(args.model)
    log = fitting.read_fit_log(args.log)
    pred = fitting.predict_log(model, log)
    with writing(args.out, "--out"):
        fitting.write_prediction(args.out, log.t_s, model.outputs, pred)
    print(f"{model.kind}: {len(log)} rows -> {args.out}")
    return 0


def args_score(sub: Any) -> None:
    """`compd score`'s arguments."""
    s = sub.add_parser(
        "score",
        help="score a model on a log with the measured errors (an unseen day), against MLR",
        description="Score a fitted model on a log that carries the measured error (a day it has not seen):"
        " RMS and max before and after per axis, and the held-out MLR baseline on the same rows.",
        epilog="example:\n  compd score model.yaml --log day2.csv --json score.json",
    )
    s.add_argument("model", metavar="MODEL.yaml")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--json", default=None, metavar="FILE", help="write the scores as JSON")


@command("score", args_score)
def cmd_score(args: argparse.Namespace) -> int:
    from compd.commissioning import fitting, report

    check_output(args.json, "--json")
    model = fitting.load_model(args.model)
    log = fitting.read_fit_log(args.log)
    result = fitting.score_model(model, log)
    base = result["baseline_mlr"]
    print(f"{model.kind} on {args.log}: {result['rows']} rows")
    for axis, r in result["axes"].items():
        print(
            f"axis {axis}: RMS {r['rms_before_um']:.2f} -> {r['rms_after_um']:.2f} um,"
            f" max {r['max_abs_before_um']:.2f} -> {r['max_abs_after_um']:.2f} um,"
            f" reduction {r['reduction_pct']:.1f} %"
        )
        b = base.get("axes", {}).get(axis)
        if b:
            print(
                f"axis {axis}: on the rows MLR did not see: model RMS {b['model_rmse_um']:.2f} um,"
                f" MLR on {' '.join(base['inputs'])} {b['mlr_held_out_rmse_um']:.2f} um"
            )
            if b["model_rmse_um"] > b["mlr_held_out_rmse_um"]:
                fitting.warn([f"axis {axis}: the MLR baseline predicts this log better than the model"])
    if "skipped" in base:
        fitting.warn([base["skipped"]])
    if args.json:
        with writing(args.json, "--json"):
            report.write_json(args.json, result)
    return 0


def args_xi(sub: Any) -> None:
    """`compd xi`'s arguments."""
    s = sub.add_parser(
        "xi",
        help="the mean-value point ξ of a temperature profile (CSV x_mm, T_c)",
        description="Find the mean-value point ξ of a temperature profile along the spindle (CSV columns x_mm, T_c):"
        " where to put the ξ sensor.",
        epilog="example:\n  compd xi --profile profile.csv",
    )
    s.add_argument("--profile", required=True, metavar="FILE.csv")


@command("xi", args_xi)
def cmd_xi(args: argparse.Namespace) -> int:
    import numpy as np

    from compd.commissioning import fitting
    from compd.identify.xi_spindle import find_xi

    x, t = fitting.read_profile(args.profile)
    xi = find_xi(x, t)
    mean = float(np.trapezoid(t, x) / (x[-1] - x[0]))
    print(f"xi_mm {xi:.2f}  (mean temperature {mean:.3f} C over {x[0]:g}..{x[-1]:g} mm)")
    return 0


def args_replay(sub: Any) -> None:
    """`compd replay`'s arguments."""
    s = sub.add_parser(
        "replay",
        help="replay a log through the pipeline into the software PLC",
        description="Replay a log's signals through the configured pipeline (model, guard, codec) into the software"
        " PLC, as fast as it can, and score the result.",
        epilog="example:\n  compd replay configs/replay_spindle.yaml --log configs/logs/spindle_demo_30s.csv"
        " --report r.json\n  compd replay --model model.yaml --log day1.csv --plot replay.png",
    )
    s.add_argument("config", nargs="?", default=None, metavar="CONFIG")
    s.add_argument("--model", default=None, metavar="MODEL.yaml", help="a model file instead of a config")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--report", default=None, metavar="REPORT.json")
    s.add_argument("--plot", default=None, metavar="FILE.png")


@command("replay", args_replay)
def cmd_replay(args: argparse.Namespace) -> int:
    import time

    from compd.commissioning.replay import replay_config, replay_model, write_plot

    if (args.config is None) == (args.model is None):
        raise BadInput("give a CONFIG or --model MODEL.yaml (one of them)", path="CONFIG")
    check_output(args.report, "--report")
    check_plot(args.plot)
    t0 = time.perf_counter()
    result = replay_model(args.model, args.log) if args.model is not None else replay_config(args.config, args.log)
    rep = result.report
    rep["wall_s"] = round(time.perf_counter() - t0, 3)
    lim = rep["device_limits"]
    clamp = "no clamp of its own" if lim["max_abs_um"] is None else f"max {lim['max_abs_um']:g} um"
    print(
        f"compd replay: {rep['rows']} rows in {rep['wall_s']:.2f} s, {rep['codes_sent']} codes sent,"
        f" device {rep['device']} (resolution {lim['resolution_um']:g} um, {clamp})"
    )
    for axis, r in rep["axes"].items():
        print(
            f"axis {axis}: RMS {r['rms_before_um']:.2f} -> {r['rms_after_um']:.2f} um,"
            f" max |residual| {r['max_abs_after_um']:.2f} um, reduction {r['reduction_pct']:.1f} %"
        )
    if args.report:  # what was replayed, for `compd report`
        files = {
            "log": str(args.log),
            **({"model": str(args.model)} if args.model else {"config": str(args.config)}),
            **({"plot": str(args.plot)} if args.plot else {}),
        }
        with writing(args.report, "--report"), open(args.report, "w", encoding="utf-8") as fh:
            json.dump({**rep, **files}, fh, indent=2)
    if args.plot:
        with writing(args.plot, "--plot"):
            write_plot(result, args.plot)
    return 0


def args_plot(sub: Any) -> None:
    """`compd plot`'s arguments."""
    s = sub.add_parser(
        "plot",
        help="trend of a daemon's data log: inputs, error, commanded and applied correction, bands",
        description="Draw the trend of a running daemon's own data log: the model's inputs, the error, the commanded"
        " and applied correction per axis (µm) and the enable and fault bands.",
        epilog="example:\n  compd plot compensated.csv --out trend.png --config compensate.yaml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("log", metavar="LOG.csv", help="the log the daemon writes (log.path)")
    s.add_argument("--out", required=True, metavar="FILE.png")
    s.add_argument(
        "--config",
        default=None,
        metavar="CONFIG.yaml",
        help="the daemon's config: its LSB, word axes and model inputs (default: LSB 1 um)",
    )


@command("plot", args_plot)
def cmd_plot(args: argparse.Namespace) -> int:
    from compd.commissioning.plots import trend_from_log, write_trend
    from compd.log import read_log

    check_plot(args.out, "--out")
    trend = trend_from_log(read_log(args.log, allow_nan=True), args.config)
    with writing(args.out, "--out"):
        write_trend(trend, args.out)
    print(f"compd plot: {len(trend.t_s)} rows, axes {', '.join(trend.axes)} -> {args.out}")
    return 0


def args_report(sub: Any) -> None:
    """`compd report`'s arguments."""
    s = sub.add_parser(
        "report",
        help="one self-contained HTML commissioning record from a fit and a replay report",
        description="Write one self-contained HTML page for the machine's file: the record (machine, operator,"
        " measuring instrument, ambient temperature, the time the logs cover, the date), the fit,"
        " the thermal test (per axis the drift from the first measurement, as ISO 230-3 states it,"
        " beside the model's residual), the unseen-day score, the plots, the config and lines to"
        " sign on paper. A record field left out is printed as not given, with the option that gives it.",
        epilog="example:\n  compd report --fit fit.json --replay replay.json --out report.html --config compensate.yaml"
        " \\\n      --machine 'DMU 50 s/n 1234' --operator 'A. Meier' --ambient-c 20.5 22.0"
        " \\\n      --instrument 'Renishaw XL-80 s/n 9876, resolution 0.001 um'",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("--fit", required=True, metavar="FIT.json", help="compd fit --report")
    s.add_argument("--replay", required=True, metavar="REPLAY.json", help="compd replay --report (the unseen day)")
    s.add_argument("--out", required=True, metavar="report.html")
    s.add_argument(
        "--config",
        default=None,
        metavar="CONFIG.yaml",
        help="the config to show (default: the one the replay report names)",
    )
    s.add_argument(
        "--png",
        nargs="+",
        action="extend",
        default=None,
        metavar="FILE.png",
        help="embed these plots instead of drawing them from the reports' data",
    )
    rec = s.add_argument_group("the record (each one line of text; one left out is printed as not given)")
    rec.add_argument("--machine", default=None, metavar="ID", help="the machine: type, serial or asset number")
    rec.add_argument("--operator", default=None, metavar="NAME", help="who ran the test and measured the error")
    rec.add_argument(
        "--ambient-c",
        nargs="+",
        type=finite,
        default=None,
        dest="ambient_c",
        metavar="C",
        help="the shop's air during the test, °C: one reading, or the lowest and the highest"
        " (the logs' amb/room/air columns are shown beside it)",
    )
    rec.add_argument(
        "--instrument",
        default=None,
        metavar="TEXT",
        help="what measured the error, with its serial number and resolution"
        " (e.g. 'Renishaw XL-80 s/n 9876' or 'dial gauge, 1 um')",
    )
    test = s.add_argument_group(
        "the thermal test (per axis the drift from the first measurement, its largest"
        " value and range, as ISO 230-3 gives them, beside the model's residual)"
    )
    test.add_argument(
        "--test-log",
        default=None,
        dest="test_log",
        metavar="LOG.csv",
        help="the test's log: probe_<axis>_um at the measurements, or err_<axis>_um"
        " (default: the log the fit report names)",
    )
    test.add_argument(
        "--model",
        default=None,
        metavar="MODEL.yaml",
        help="the model whose prediction and residual the test shows (default: the fit report's)",
    )
    test.add_argument(
        "--test-every-min",
        type=positive,
        default=None,
        dest="test_every_min",
        metavar="N",
        help="where the log has no probe rows, err_<axis>_um is taken every N minutes from the"
        " first measurement (default 10)",
    )
    test.add_argument(
        "--test-json",
        default=None,
        dest="test_json",
        metavar="FILE",
        help="write the thermal test's figures as JSON too",
    )


@command("report", args_report)
def cmd_report(args: argparse.Namespace) -> int:
    from compd.commissioning import thermaltest
    from compd.commissioning.htmlreport import build_page, make_record, render
    from compd.commissioning.report import write_json

    record = make_record(args.machine, args.operator, args.instrument, args.ambient_c)
    every_min = thermaltest.DEFAULT_EVERY_MIN if args.test_every_min is None else args.test_every_min
    every_s = thermaltest.check_every_min(every_min)
    check_output(args.out, "--out")
    check_output(args.test_json, "--test-json")
    page = build_page(
        args.fit,
        args.replay,
        args.config,
        args.png,
        record,
        test_log=args.test_log,
        test_model=args.model,
        every_s=every_s,
    )
    if args.test_json and page.thermal is None:
        raise BadInput(f"no thermal test to write: {page.thermal_why_not}", path="--test-json")
    with writing(args.out, "--out"):
        Path(args.out).write_text(render(page), encoding="utf-8")
    drawn = sum(f.png is not None for f in page.figures)
    print(
        f"compd report: {page.fit['kind']} fit, replay of {', '.join(page.replay['axes'])}, {drawn} plots -> {args.out}"
    )
    tt = page.thermal
    for ax in tt.axes if tt is not None else []:
        d, r = ax.drift(), ax.residual()
        left = (
            f"; residual RMS {r.rms_um:.2f} um, range {r.range_um:.2f} um"
            if r is not None
            else f"; no residual ({ax.why_no_prediction})"
        )
        print(
            f"compd report: thermal test of {Path(tt.log).name}, axis {ax.axis}: {ax.rows.size} measurements"
            f" ({ax.source}), largest drift {d.max_abs_um:.2f} um at {(d.at_t_s - tt.t0_s) / 3600:.2f} h,"
            f" range {d.range_um:.2f} um{left}"
        )
    if tt is None:
        print(f"compd: the thermal test is not shown: {page.thermal_why_not}", file=sys.stderr)
    elif args.test_json:
        with writing(args.test_json, "--test-json"):
            write_json(args.test_json, tt.as_dict())
    for f in page.figures:
        if f.png is None:
            print(f"compd: {f.caption}: {f.why_not}", file=sys.stderr)
    missing = record.missing()
    if missing:
        print(
            f'compd: the record says "not given" for {", ".join(m.lstrip("-") for m in missing)}'
            f" (give {', '.join(missing)})",
            file=sys.stderr,
        )
    return 0


def args_output_test(sub: Any) -> None:
    """`compd output-test`'s arguments."""
    s = sub.add_parser(
        "output-test",
        help="write a known correction through the configured sink, read it back, ramp to 0",
        description="Write a known correction through the configured sink at the guard's slew, hold it, read back"
        " what the device applied and ramp back to zero: the sign check of commissioning.",
        epilog="example:\n  compd output-test machine.yaml --axis z --um 5 --hold-s 5",
    )
    s.add_argument("config", nargs="?", default=None, metavar="CONFIG")
    s.add_argument("--config", default=None, dest="config_opt", metavar="CONFIG", help="the config (or positional)")
    s.add_argument("--axis", required=True, metavar="AX", help="the axis (one the sink drives)")
    s.add_argument("--um", required=True, type=finite, metavar="U", help="the correction, um (within guard.max_abs_um)")
    s.add_argument(
        "--hold-s", type=positive, default=5.0, dest="hold_s", metavar="S", help="hold it this long (default 5)"
    )
    s.add_argument("--yes", action="store_true", help="do not ask (scripts); without a terminal it is required")
    s.add_argument("--json", default=None, metavar="FILE", help="write the result as JSON")


@command("output-test", args_output_test)
def cmd_output_test(args: argparse.Namespace) -> int:
    from compd.commissioning import outputtest as ot
    from compd.config import load_config

    if (args.config is None) == (args.config_opt is None):
        raise BadInput("give the CONFIG (or --config CONFIG), once", path="CONFIG")
    cfg = load_config(args.config or args.config_opt)
    sink, _, word_axes = ot.build_sink(cfg)
    ot.check_request(cfg, sink, word_axes, args.axis, args.um)  # before asking
    busy = ot.running_daemon(cfg)
    if busy:
        print(f"compd output-test: {busy}", file=sys.stderr)
        return 1
    if not args.yes:
        if not sys.stdin.isatty():
            raise BadInput(
                "writes a correction to the machine: confirm on a terminal, or give --yes", path="--yes", file=cfg.file
            )
        answer = input(f"Write {args.um:+g} um on axis {args.axis} through {sink.device_info()['device']}? [y/N] ")
        if answer.strip().lower() not in ("y", "yes"):
            print("compd output-test: not confirmed, nothing written")
            return 1

    def _interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt  # SIGTERM as Ctrl-C: ramp back to zero at the slew, then the safe state

    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        res = ot.run_output_test(cfg, args.axis, args.um, args.hold_s)
    except ot.DeviceUnreachable as e:
        print(f"compd output-test: {e}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGTERM, previous)
    if args.json:
        with writing(args.json, "--json"), open(args.json, "w", encoding="utf-8") as fh:
            json.dump(res.as_dict(), fh, indent=2)
    ok = res.matches(res.resolution_um) and not res.interrupted
    print(
        f"compd output-test: commanded {res.commanded_um:+.3f} um, applied {res.applied_um:+.3f} um:"
        f" {'ok' if ok else 'MISMATCH'}; now check the axis moved the way the sign says"
    )
    return 0 if ok else 1
