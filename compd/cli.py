"""The `compd` command line: thin — parse, call, print."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import sys
import typing
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from compd.errors import BadInput

log = logging.getLogger("compd")

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}


def command(name: str) -> Callable[[Callable[[argparse.Namespace], int]], Callable[[argparse.Namespace], int]]:
    def deco(fn: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
        COMMANDS[name] = fn
        return fn

    return deco


# ------------------------------------------------------------- argument checks


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def finite(text: str) -> float:
    """argparse type: a finite number (NaN and infinities are malformed here)."""
    return _number(text)


def positive(text: str) -> float:
    """argparse type: a finite number > 0 (a duration, a period, an LSB)."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def non_negative(text: str) -> float:
    """argparse type: a finite number ≥ 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text!r}")
    return value


def check_output(path: str | None, flag: str, *, folder: bool = False) -> None:
    """BadInput unless `path` can be written — checked before the work starts, so a long
    fit or run does not end in an error. A file that did not exist is not left behind."""
    if path is None:
        return
    p = Path(path)
    if folder:
        if p.exists() and not p.is_dir():
            raise BadInput("exists and is not a folder", file=path, path=flag)
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise BadInput(f"cannot create the folder: {e.strerror or e}", file=path, path=flag) from None
        return
    if p.is_dir():
        raise BadInput("is a folder, not a file", file=path, path=flag)
    existed = p.exists()
    try:
        with open(p, "a", encoding="utf-8"):
            pass
        if not existed:
            p.unlink()
    except OSError as e:
        raise BadInput(f"cannot write: {e.strerror or e}", file=path, path=flag) from None


def check_plot(path: str | None, flag: str = "--plot") -> None:
    """check_output, and a file type matplotlib can write (a figure is drawn after the work)."""
    if path is None:
        return
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix:
        try:
            from matplotlib.backend_bases import FigureCanvasBase
        except ImportError:
            raise BadInput(f"{flag} needs matplotlib: pip install 'compd[plot]'", path=flag) from None
        known = FigureCanvasBase.get_supported_filetypes()
        if suffix not in known:
            raise BadInput(
                f"cannot plot to a .{suffix} file (known: {', '.join(sorted(known))})", file=path, path=flag
            )
    check_output(path, flag)


@contextlib.contextmanager
def writing(path: str | os.PathLike[str], flag: str) -> Iterator[None]:
    """An OSError while writing `path` (disk full, the folder gone since the check) is bad input."""
    try:
        yield
    except OSError as e:
        raise BadInput(f"cannot write: {e.strerror or e}", file=str(path), path=flag) from None


def _parse_word(text: str) -> int:
    try:
        word = int(text, 0)
    except ValueError:
        raise BadInput(f"not a word: {text!r} (give e.g. 0xC543)", path="WORD") from None
    if not 0 <= word <= 0xFFFF:
        raise BadInput(f"a word is 16 bits (0x0000..0xFFFF), got {text}", path="WORD")
    return word


@command("encode")
def cmd_encode(args: argparse.Namespace) -> int:
    from compd.codec import decode, encode_ex

    try:
        word, s1, s2 = encode_ex(args.c1_um, args.c2_um, args.lsb_um, args.deadband_um)
    except ValueError as e:
        raise BadInput(str(e)) from None
    parts = []
    for name, code, sat in zip(("X1", "X2"), decode(word), (s1, s2), strict=True):
        if code.enable:
            desc = f"{name} {'+' if code.direction > 0 else '-'}{code.magnitude * args.lsb_um:g}um"
        else:
            desc = f"{name} off"
        parts.append(desc + (" (saturated)" if sat else ""))
    print(f"0x{word:04X}  " + ", ".join(parts))
    return 0


@command("decode")
def cmd_decode(args: argparse.Namespace) -> int:
    from compd.codec import decode

    word = _parse_word(args.word)
    for name, code in zip(("X1", "X2"), decode(word), strict=True):
        sign = "+" if code.direction > 0 else "-"
        state = "enabled" if code.enable else "disabled"
        value = code.direction * code.magnitude * args.lsb_um if code.enable else 0.0
        print(
            f"{name}: direction {sign} enable {int(code.enable)} ({state}) magnitude {code.magnitude}"
            f" -> {value:+g} um"
        )
    return 0


@command("check-config")
def cmd_check_config(args: argparse.Namespace) -> int:
    from compd import pipeline
    from compd.config import load_config
    from compd.service import check_status_free

    cfg = load_config(args.config)
    pipeline.check(cfg)  # the wiring, by building the pipeline (opens no device)
    check_status_free(cfg)  # no other running compd writes its status file
    print("ok")
    return 0


@command("run")
def cmd_run(args: argparse.Namespace) -> int:
    from compd.daemon import run_with_reload

    check_output(args.json, "--json")
    result = run_with_reload(args.config, args.duration, args.observe, args.log_level)
    comp = result["compensation"]
    loop = result["loop"]
    if result.get("observe"):
        print("compd: observe mode: the output was held disabled (no correction reached the machine)")
    from compd.histogram import percentile_text
    from compd.loop import HIST_US

    late, comp_us = loop["lateness_us"]["p99"], loop["cycle_compute_us"]["p99"]
    print(
        f"compd: {loop['cycles']} cycles, {loop['misses']} missed, lateness p99"
        f" {percentile_text(late, late >= HIST_US, '.0f')}, compute p99 {percentile_text(comp_us, comp_us >= HIST_US, '.0f')}"
    )
    for axis, r in comp.items():
        print(
            f"axis {axis}: RMS error without compensation {r['rms_before_um']:.2f} um,"
            f" with {r['rms_after_um']:.2f} um; max {r['max_abs_before_um']:.2f} ->"
            f" {r['max_abs_after_um']:.2f} um; reduction {r['reduction_pct']:.1f} %"
        )
    for key in ("log_error", "state_error"):
        if result[key]:
            print(f"compd: {result[key]}", file=sys.stderr)
    if args.json:
        with writing(args.json, "--json"), open(args.json, "w", encoding="utf-8") as fh:
            json.dump(result, fh, indent=2)
    if result.get("safe_delivered") is False:
        print("compd: the safe output did not reach the sink's device: the last correction may still be applied",
              file=sys.stderr)
        return 1
    return 0


@command("fit")
def cmd_fit(args: argparse.Namespace) -> int:
    from compd import fitting, report

    options = fitting.parse_options(args.option)
    if args.ambient:
        options["ambient"] = args.ambient
    check_output(args.report, "--report")
    check_plot(args.plot)
    check_output(args.out, "--out", folder=args.kind == "all")  # last: it may create the folder
    log = fitting.read_fit_log(args.log)
    if args.kind == "all":
        rows = fitting.fit_all(log, args.inputs, args.target, options)
        out = Path(args.out)
        for _, label, oc, _ in rows:
            if oc is not None:
                with writing(out / f"{label}.yaml", "--out"):
                    fitting.write_model(oc.model, out / f"{label}.yaml")
                if args.plot:
                    p = Path(args.plot)
                    p = p.with_name(f"{p.stem}_{label}{p.suffix or '.png'}")
                    with writing(p, "--plot"):
                        report.plot_fit(oc, log, p)
                fitting.warn(oc.warnings)
        print(fitting.comparison_table(rows))
        if args.report:
            with writing(args.report, "--report"):
                report.write_json(args.report, {
                    label: oc.report if oc else {"skipped": why} for _, label, oc, why in rows
                })
        return 0
    oc = fitting.fit_model(args.kind, log, args.inputs, args.target, options)
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
        print(f"{args.kind} axis {axis}: RMSE {s['rmse_um']:.3f} um, max {s['max_abs_err_um']:.3f} um,"
              f" {oc.report['rows']} rows, {oc.report['fit_time_s']:.2f} s -> {args.out}")
    fitting.warn(oc.warnings)
    return 0


@command("predict")
def cmd_predict(args: argparse.Namespace) -> int:
    from compd import fitting

    check_output(args.out, "--out")
    model = fitting.load_model(args.model)
    log = fitting.read_fit_log(args.log)
    pred = fitting.predict_log(model, log)
    with writing(args.out, "--out"):
        fitting.write_prediction(args.out, log.t_s, model.outputs, pred)
    print(f"{model.kind}: {len(log)} rows -> {args.out}")
    return 0


@command("score")
def cmd_score(args: argparse.Namespace) -> int:
    from compd import fitting, report

    check_output(args.json, "--json")
    model = fitting.load_model(args.model)
    log = fitting.read_fit_log(args.log)
    result = fitting.score_model(model, log)
    base = result["baseline_mlr"]
    print(f"{model.kind} on {args.log}: {result['rows']} rows")
    for axis, r in result["axes"].items():
        print(f"axis {axis}: RMS {r['rms_before_um']:.2f} -> {r['rms_after_um']:.2f} um,"
              f" max {r['max_abs_before_um']:.2f} -> {r['max_abs_after_um']:.2f} um,"
              f" reduction {r['reduction_pct']:.1f} %")
        b = base.get("axes", {}).get(axis)
        if b:
            print(f"axis {axis}: on the rows MLR did not see: model RMS {b['model_rmse_um']:.2f} um,"
                  f" MLR on {' '.join(base['inputs'])} {b['mlr_held_out_rmse_um']:.2f} um")
            if b["model_rmse_um"] > b["mlr_held_out_rmse_um"]:
                fitting.warn([f"axis {axis}: the MLR baseline predicts this log better than the model"])
    if "skipped" in base:
        fitting.warn([base["skipped"]])
    if args.json:
        with writing(args.json, "--json"):
            report.write_json(args.json, result)
    return 0


@command("xi")
def cmd_xi(args: argparse.Namespace) -> int:
    import numpy as np

    from compd import fitting
    from compd.identify.xi_spindle import find_xi

    x, t = fitting.read_profile(args.profile)
    xi = find_xi(x, t)
    mean = float(np.trapezoid(t, x) / (x[-1] - x[0]))
    print(f"xi_mm {xi:.2f}  (mean temperature {mean:.3f} C over {x[0]:g}..{x[-1]:g} mm)")
    return 0


@command("replay")
def cmd_replay(args: argparse.Namespace) -> int:
    import time

    from compd.replay import replay_config, replay_model, write_plot

    if (args.config is None) == (args.model is None):
        raise BadInput("give a CONFIG or --model MODEL.yaml (one of them)", path="CONFIG")
    check_output(args.report, "--report")
    check_plot(args.plot)
    t0 = time.perf_counter()
    if args.model is not None:
        result = replay_model(args.model, args.log)
    else:
        result = replay_config(args.config, args.log)
    rep = result.report
    rep["wall_s"] = round(time.perf_counter() - t0, 3)
    lim = rep["device_limits"]
    clamp = "no clamp of its own" if lim["max_abs_um"] is None else f"max {lim['max_abs_um']:g} um"
    print(f"compd replay: {rep['rows']} rows in {rep['wall_s']:.2f} s, {rep['codes_sent']} codes sent,"
          f" device {rep['device']} (resolution {lim['resolution_um']:g} um, {clamp})")
    for axis, r in rep["axes"].items():
        print(
            f"axis {axis}: RMS {r['rms_before_um']:.2f} -> {r['rms_after_um']:.2f} um,"
            f" max |residual| {r['max_abs_after_um']:.2f} um, reduction {r['reduction_pct']:.1f} %"
        )
    if args.report:  # what was replayed, for `compd report`
        files = {"log": str(args.log), **({"model": str(args.model)} if args.model else {"config": str(args.config)}),
                 **({"plot": str(args.plot)} if args.plot else {})}
        with writing(args.report, "--report"), open(args.report, "w", encoding="utf-8") as fh:
            json.dump({**rep, **files}, fh, indent=2)
    if args.plot:
        with writing(args.plot, "--plot"):
            write_plot(result, args.plot)
    return 0


@command("plot")
def cmd_plot(args: argparse.Namespace) -> int:
    from compd.log import read_log
    from compd.plots import trend_from_log, write_trend

    check_plot(args.out, "--out")
    trend = trend_from_log(read_log(args.log, allow_nan=True), args.config)
    with writing(args.out, "--out"):
        write_trend(trend, args.out)
    print(f"compd plot: {len(trend.t_s)} rows, axes {', '.join(trend.axes)} -> {args.out}")
    return 0


@command("report")
def cmd_report(args: argparse.Namespace) -> int:
    from compd.htmlreport import write_report

    check_output(args.out, "--out")
    with writing(args.out, "--out"):
        page = write_report(args.out, args.fit, args.replay, args.config, args.png)
    drawn = sum(f.png is not None for f in page.figures)
    print(f"compd report: {page.fit['kind']} fit, replay of {', '.join(page.replay['axes'])},"
          f" {drawn} plots -> {args.out}")
    for f in page.figures:
        if f.png is None:
            print(f"compd: {f.caption}: {f.why_not}", file=sys.stderr)
    return 0


@command("output-test")
def cmd_output_test(args: argparse.Namespace) -> int:
    from compd import outputtest as ot
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
            raise BadInput("writes a correction to the machine: confirm on a terminal, or give --yes",
                           path="--yes", file=cfg.file)
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
    print(f"compd output-test: commanded {res.commanded_um:+.3f} um, applied {res.applied_um:+.3f} um:"
          f" {'ok' if ok else 'MISMATCH'}; now check the axis moved the way the sign says")
    return 0 if ok else 1


@command("status")
def cmd_status(args: argparse.Namespace) -> int:
    from compd.status import DEFAULT_PATH, liveness, read_status, render

    if args.status:
        path = args.status
    elif args.config:
        from compd.config import load_config
        from compd.service import daemon_status_path

        path = str(daemon_status_path(load_config(args.config)))
    else:
        path = DEFAULT_PATH
    if args.watch:
        from compd.watch import watch

        if args.json:
            raise BadInput("--watch shows the live view; --json prints the snapshot once (give one of them)",
                           path="--watch")
        return watch(path, args.interval_s)
    data = read_status(path)
    try:
        alive, why = liveness(data)
        text = json.dumps({**data, "alive": alive, "liveness": why}, indent=1) if args.json else render(data, alive, why)
    except (TypeError, ValueError, AttributeError, KeyError) as e:  # a field deeper down of the wrong type
        raise BadInput(f"not a compd status file: {type(e).__name__}: {e}", file=path) from None
    print(text)
    if not alive:
        print(f"compd: {path}: {why}", file=sys.stderr)
    return 0 if alive else 1


def probe_socket(config: str | None) -> str:
    """The probe socket of the daemon of CONFIG (compd.control.socket_path), where the
    systemd units put it when the config names no status file, or the default."""
    from compd.control import DEFAULT_PATH, sock_beside, socket_path

    if config is None:
        return DEFAULT_PATH
    from compd.config import load_config

    cfg = load_config(config)
    if cfg.top.adapt is None:
        raise BadInput("has no adapt section, so its daemon takes no probes (add `adapt: {}`, or"
                       " `adapt: {apply: false}` to estimate without applying)", file=config, path="adapt")
    from compd.service import daemon_status_path

    return str(socket_path(cfg, env={}) or sock_beside(daemon_status_path(cfg)))


@command("probe")
def cmd_probe(args: argparse.Namespace) -> int:
    from compd.control import NoDaemon, send_probe

    path = probe_socket(args.config)
    request = {"op": "probe", "axis": args.axis, "error_um": args.error_um, "position_mm": args.position_mm,
               "sigma_um": args.sigma_um, "residual": args.residual}
    try:
        answer = send_probe(path, request)
    except NoDaemon as e:
        print(f"compd: {e}", file=sys.stderr)
        return 1
    if not answer.get("ok"):
        why = str(answer.get("error", "refused"))
        raise BadInput(f"the daemon refused the probe: {why}", path="--axis" if why.startswith("unknown axis") else None)
    what = "deviation" if args.residual else "error"
    head = f"compd: probe {args.axis} {what} {args.error_um:g} um"
    outcome = answer.get("outcome")
    if outcome in ("accepted", "rejected"):
        print(f"{head} {outcome} at t={answer['t_s']:.1f} s: thermal error {answer['error_um']:.2f} um,"
              f" innovation {answer['innovation_um']:.2f} um (sigma {answer['innovation_sigma_um']:.2f} um),"
              f" offset now {answer['offset_um']:.2f} um")
    elif outcome == "queued":
        print(f"{head} queued at t={answer['t_s']:.1f} s (the loop has not taken it yet; see the daemon's log)")
    else:  # no_prediction, no_correction_known: handed over but not used
        print(f"{head} not used: {outcome} (pid {answer.get('pid')})")
    return 0


@command("arm-model")
def cmd_arm_model(args: argparse.Namespace) -> int:
    from compd.config import load_config
    from compd.control import NoDaemon, send_probe, sock_beside, socket_path
    from compd.service import daemon_status_path

    cfg = load_config(args.config)
    tel = cfg.top.telemetry
    if tel is None or not tel.remote_models.allow:
        raise BadInput("its daemon takes no remote models (set telemetry.remote_models.allow: true)",
                       file=args.config, path="telemetry.remote_models.allow")
    path = str(socket_path(cfg, env={}) or sock_beside(daemon_status_path(cfg)))
    try:
        answer = send_probe(path, {"op": "arm_model", "window_s": args.seconds})
    except NoDaemon as e:
        print(f"compd: {e}", file=sys.stderr)
        return 1
    if not answer.get("ok"):
        raise BadInput(f"the daemon refused: {answer.get('error', 'refused')}")
    print(f"compd: armed for {answer['armed_s']:.0f} s: the next model from the command topic is applied"
          f" (once) if it validates (pid {answer.get('pid')})")
    return 0


@command("opcua-cert")
def cmd_opcua_cert(args: argparse.Namespace) -> int:
    from pathlib import Path

    try:
        from compd.plant.opcua import generate_certificate
    except ImportError:
        raise BadInput("needs the plant extra: pip install 'compd[plant]'") from None
    for path, key in ((args.cert, "--cert"), (args.key, "--key")):
        check_output(path, key)
        if Path(path).exists():
            raise BadInput(f"{path} exists: compd never overwrites a certificate or a key", path=key)
    generate_certificate(Path(args.cert), Path(args.key), common_name=args.name, application_uri=args.uri,
                         hosts=args.host or ["127.0.0.1"])
    print(f"compd: wrote {args.cert} and {args.key} (key 0600) for {args.uri}")
    return 0


@command("docs")
def cmd_docs(args: argparse.Namespace) -> int:
    from compd.docgen import generate

    if args.metrics:
        from compd.metrics import metrics_markdown

        text = metrics_markdown()
    else:
        text = generate()
    if args.check:
        if args.out is None:
            raise BadInput("--check needs --out FILE")
        try:
            with open(args.out, encoding="utf-8") as fh:
                same = fh.read() == text
        except OSError as e:
            raise BadInput(f"cannot read: {e.strerror}", file=args.out) from None
        except UnicodeDecodeError:
            same = False  # not even text: out of date
        if not same:
            print(f"compd: {args.out} is out of date: run compd docs --out {args.out}", file=sys.stderr)
            return 1
        return 0
    if args.out is None:
        sys.stdout.write(text)
    else:
        check_output(args.out, "--out")
        with writing(args.out, "--out"), open(args.out, "w", encoding="utf-8") as fh:
            fh.write(text)
    return 0


@command("bench")
def cmd_bench(args: argparse.Namespace) -> int:
    if args.cycles < 1:
        raise BadInput("--cycles must be at least 1", path="--cycles")
    if not 0 <= args.load <= 64:
        raise BadInput("--load must be 0 to 64 processes", path="--load")
    if args.bare_cycles is not None and args.bare_cycles < 0:
        raise BadInput("--bare-cycles must be 0 or more", path="--bare-cycles")
    if args.naive_cycles is not None and args.naive_cycles < 1:
        raise BadInput("--naive-cycles must be at least 1", path="--naive-cycles")
    check_output(args.json, "--json")
    check_output(args.trace, "--trace")
    return installed_command("bench", "runs against simulated devices served by the closed-loop test rig")(args)


def installed_command(name: str, needs: str) -> Callable[[argparse.Namespace], int]:
    """The command another installed package provides (entry point group `compd.commands`),
    or BadInput (exit 2) naming what is missing."""
    from compd.registry import entry_point

    ep = entry_point("compd.commands", name)
    if ep is None:
        raise BadInput(f"`compd {name}` {needs}, which is not installed (no '{name}' in entry point group"
                       " compd.commands): install compd from its source tree, with the rig, to run it")
    try:
        return ep.load()
    except (ImportError, AttributeError) as e:
        raise BadInput(f"`compd {name}` comes from {ep.value}, which cannot be loaded: {e}") from None


def _fit_options_help() -> str:
    """`compd fit --help`'s list of the options of every kind (from compd.identify, imported here only)."""
    from compd.identify import options_help

    return options_help()


class Parser(argparse.ArgumentParser):
    """argparse with compd's error form: one line on stderr, exit 2 (`--help` shows the usage).
    The description and the epilog (an example) are printed as written; `epilog_extra`, when
    set, adds text computed only when the help is shown (the fit options per kind)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)
        self.epilog_extra: Callable[[], str] | None = None

    def format_help(self) -> str:
        if self.epilog_extra is None:
            return super().format_help()
        saved = self.epilog
        self.epilog = f"{self.epilog_extra()}\n\n{saved or ''}".rstrip()
        try:
            return super().format_help()
        finally:
            self.epilog = saved

    def error(self, message: str) -> typing.NoReturn:
        one_line = " ".join(message.split())
        self.exit(2, f"{self.prog}: {one_line}\n")


def build_parser() -> argparse.ArgumentParser:
    from compd import version

    p = Parser(
        prog="compd", description="Real-time thermal-error compensation for CNC machine tools.",
        epilog="example:\n  compd check-config configs/demo.yaml\n  compd run configs/demo.yaml --observe\n"
        "  compd status --config configs/demo.yaml\n\n`compd COMMAND --help` describes a command.",
    )
    p.add_argument("--version", action="version", version=f"compd {version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("run", help="run the compensation loop",
                       description="Run the compensation loop of CONFIG until SIGTERM or SIGINT (then emit the safe output); SIGHUP reloads the config.",
                       epilog="example:\n  compd run configs/demo.yaml --duration 60\n  compd run /etc/compd/compd.yaml --observe --log-level debug")
    s.add_argument("config")
    s.add_argument("--duration", type=positive, default=None, metavar="S", help="stop after S seconds (> 0)")
    s.add_argument("--json", default=None, metavar="FILE", help="write the run summary as JSON")
    s.add_argument(
        "--observe", action="store_true", help="observe mode: full loop, output held disabled"
    )
    s.add_argument(
        "--log-level", default=None, choices=("debug", "info", "warning", "error"), dest="log_level"
    )

    s = sub.add_parser("status", help="the live state of a running daemon",
                       description="Show the live state of a running daemon: per axis the model (file, fit date, coefficients, T0), correction and state, per signal value and quality; exit 1 when none runs.",
                       epilog="example:\n  compd status --config /etc/compd/compd.yaml\n  compd status --status /run/compd/status.json --watch --interval-s 1")
    s.add_argument("--json", action="store_true", help="print the status snapshot as JSON")
    s.add_argument("--watch", action="store_true",
                   help="redraw every --interval-s until Ctrl-C (rich tables if installed); waits while no daemon runs")
    s.add_argument("--interval-s", type=positive, default=1.0, dest="interval_s", metavar="S",
                   help="--watch: seconds between redraws (default 1)")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--config", default=None, help="the daemon's config (finds its status file)")
    where.add_argument("--status", default=None, metavar="PATH", help="the status file")

    s = sub.add_parser("probe", help="hand one probe measurement to the running daemon",
                       description="Hand one probe measurement (the axis's thermal error measured on the machine) to the running daemon of CONFIG; exit 1 when none runs.",
                       epilog="example:\n  compd probe --axis z --error-um 12.5 --config /etc/compd/compd.yaml")
    s.add_argument("--axis", required=True, metavar="AX", help="the axis (a model output)")
    s.add_argument("--error-um", required=True, type=finite, dest="error_um", metavar="E",
                   help="the axis's whole thermal error measured on the machine, um (see --residual)")
    s.add_argument("--position-mm", type=finite, default=None, dest="position_mm", metavar="P",
                   help="where the probe measured")
    s.add_argument("--sigma-um", type=positive, default=None, dest="sigma_um", metavar="S",
                   help="the measurement's sigma (default: adapt.sigma_um)")
    s.add_argument("--residual", action="store_true",
                   help="E is the deviation that remains on the compensated machine (the daemon adds back"
                   " the correction applied at that moment)")
    s.add_argument("--config", default=None, help="the daemon's config (finds its probe socket)")

    s = sub.add_parser("arm-model", help="let the running daemon apply the next model from the plant",
                       description="Arm the running daemon of CONFIG to apply the next model published to its Sparkplug command topic (once, within --seconds); needs telemetry.remote_models.allow. Exit 1 when no daemon runs.",
                       epilog="example:\n  compd arm-model /etc/compd/compd.yaml --seconds 300")
    s.add_argument("config")
    s.add_argument("--seconds", type=positive, default=None, metavar="S",
                   help="how long it stays armed (default: telemetry.remote_models.arm_window_s)")

    s = sub.add_parser("opcua-cert", help="write a self-signed certificate and key for the OPC UA server",
                       description="Write a self-signed OPC UA application certificate (RSA 2048, SHA-256, the application URI and hosts in its SubjectAltName) and its key (0600) for the opcua section; never overwrites.",
                       epilog="example:\n  compd opcua-cert --cert opcua/server.pem --key opcua/server.key --host cell3-compd --host 10.0.3.17")
    s.add_argument("--cert", required=True, metavar="FILE", help="the certificate to write (PEM)")
    s.add_argument("--key", required=True, metavar="FILE", help="its private key to write (PEM, 0600)")
    s.add_argument("--uri", default="urn:compd:server", help="the application URI (default urn:compd:server)")
    s.add_argument("--name", default="compd", help="the certificate's common name (default compd)")
    s.add_argument("--host", action="append", default=[], metavar="HOST",
                   help="a DNS name or IP address clients use to reach it (repeat; default 127.0.0.1)")

    s = sub.add_parser("docs", help="generate docs/configuration.md from the config schema",
                       description="Generate the configuration reference (docs/configuration.md) from the config schema, or with --metrics the metrics reference (docs/metrics.md); --check tells whether FILE is up to date.",
                       epilog="example:\n  compd docs --out docs/configuration.md\n  compd docs --out docs/configuration.md --check\n  compd docs --metrics --out docs/metrics.md")
    s.add_argument("--out", default=None, metavar="FILE", help="write here (default: stdout)")
    s.add_argument("--check", action="store_true", help="exit 1 if FILE differs from a fresh generation")
    s.add_argument("--metrics", action="store_true",
                   help="the metrics reference (docs/metrics.md) instead of the configuration's")

    s = sub.add_parser("check-config", help="validate a config; prints ok or exits 2",
                       description="Validate a config and its wiring without opening a device: prints ok, or one line naming the file, line and key (exit 2).",
                       epilog="example:\n  compd check-config configs/demo.yaml")
    s.add_argument("config")

    s = sub.add_parser("replay", help="replay a log through the pipeline into the software PLC",
                       description="Replay a log's signals through the configured pipeline (model, guard, codec) into the software PLC, as fast as it can, and score the result.",
                       epilog="example:\n  compd replay configs/replay_spindle.yaml --log configs/logs/spindle_demo_30s.csv --report r.json\n  compd replay --model model.yaml --log day1.csv --plot replay.png")
    s.add_argument("config", nargs="?", default=None, metavar="CONFIG")
    s.add_argument("--model", default=None, metavar="MODEL.yaml", help="a model file instead of a config")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--report", default=None, metavar="REPORT.json")
    s.add_argument("--plot", default=None, metavar="FILE.png")

    s = sub.add_parser(
        "output-test", help="write a known correction through the configured sink, read it back, ramp to 0",
        description="Write a known correction through the configured sink at the guard's slew, hold it, read back"
                    " what the device applied and ramp back to zero: the sign check of commissioning.",
        epilog="example:\n  compd output-test machine.yaml --axis z --um 5 --hold-s 5",
    )
    s.add_argument("config", nargs="?", default=None, metavar="CONFIG")
    s.add_argument("--config", default=None, dest="config_opt", metavar="CONFIG", help="the config (or positional)")
    s.add_argument("--axis", required=True, metavar="AX", help="the axis (one the sink drives)")
    s.add_argument("--um", required=True, type=finite, metavar="U", help="the correction, um (within guard.max_abs_um)")
    s.add_argument("--hold-s", type=positive, default=5.0, dest="hold_s", metavar="S", help="hold it this long (default 5)")
    s.add_argument("--yes", action="store_true", help="do not ask (scripts); without a terminal it is required")
    s.add_argument("--json", default=None, metavar="FILE", help="write the result as JSON")

    s = sub.add_parser(
        "plot", help="trend of a daemon's data log: inputs, error, commanded and applied correction, bands",
        description="Draw the trend of a running daemon's own data log: the model's inputs, the error, the commanded"
                    " and applied correction per axis (µm) and the enable and fault bands.",
        epilog="example:\n  compd plot compensated.csv --out trend.png --config compensate.yaml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("log", metavar="LOG.csv", help="the log the daemon writes (log.path)")
    s.add_argument("--out", required=True, metavar="FILE.png")
    s.add_argument("--config", default=None, metavar="CONFIG.yaml",
                   help="the daemon's config: its LSB, word axes and model inputs (default: LSB 1 um)")

    s = sub.add_parser(
        "report", help="one self-contained HTML commissioning page from a fit and a replay report",
        description="Write one self-contained HTML page for the machine's file: the fit, the unseen-day score,"
                    " the plots and the config.",
        epilog="example:\n  compd report --fit fit.json --replay replay.json --out report.html --config compensate.yaml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("--fit", required=True, metavar="FIT.json", help="compd fit --report")
    s.add_argument("--replay", required=True, metavar="REPLAY.json", help="compd replay --report (the unseen day)")
    s.add_argument("--out", required=True, metavar="report.html")
    s.add_argument("--config", default=None, metavar="CONFIG.yaml",
                   help="the config to show (default: the one the replay report names)")
    s.add_argument("--png", nargs="+", action="extend", default=None, metavar="FILE.png",
                   help="embed these plots instead of drawing them from the reports' data")

    s = sub.add_parser("encode", help="the 16-bit word for two corrections (µm)",
                       description="Print the 16-bit compensation word for two corrections C1, C2 (µm), with what each byte means.",
                       epilog="example:\n  compd encode 12 -3.5")
    s.add_argument("c1_um", type=finite, metavar="C1_UM")
    s.add_argument("c2_um", type=finite, metavar="C2_UM")
    s.add_argument("--lsb-um", type=positive, default=1.0, dest="lsb_um")
    s.add_argument("--deadband-um", type=non_negative, default=1.0, dest="deadband_um")

    s = sub.add_parser("decode", help="direction, enable and magnitude of both axes of a word",
                       description="Print direction, enable and magnitude of both axes of a 16-bit compensation word.",
                       epilog="example:\n  compd decode 0xC543")
    s.add_argument("word", metavar="WORD")
    s.add_argument("--lsb-um", type=positive, default=1.0, dest="lsb_um")
    s = sub.add_parser("fit", help="identify a model's coefficients from a log",
                       description="Identify a model's coefficients from a log and write the model file (with its fit date and scores); --kind all fits every kind that applies and compares them.",
                       epilog="example:\n  compd fit --kind lvr --log day1.csv --out lvr.yaml --report fit.json\n  compd fit --kind ar1 --log day1.csv --out ar1.yaml --inputs T_bed --ambient T_amb --option dt_s=60")
    s.add_argument("--kind", required=True, choices=["feed_axis", "lvr", "xi_spindle", "ar1", "mlr", "all"])
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--out", required=True, metavar="MODEL.yaml", help="model file (a folder with --kind all)")
    s.add_argument("--target", nargs="+", action="extend", default=None, metavar="COL")
    s.add_argument("--inputs", nargs="+", action="extend", default=None, metavar="COL")
    s.add_argument("--ambient", default=None, metavar="COL", help="ambient sensor (ar1 C3, feed_axis ζ)")
    s.add_argument("--option", action="append", default=None, metavar="KEY=VALUE",
                   help="a fit option of the kind (value read as YAML)")
    s.add_argument("--report", default=None, metavar="REPORT.json")
    s.add_argument("--plot", default=None, metavar="FILE.png")
    s.epilog_extra = _fit_options_help

    s = sub.add_parser("predict", help="batch prediction of a fitted model over a log",
                       description="Predict the thermal error of every row of a log with a fitted model (pred_<axis>_um columns).",
                       epilog="example:\n  compd predict lvr.yaml --log day2.csv --out pred.csv")
    s.add_argument("model", metavar="MODEL.yaml")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--out", required=True, metavar="PRED.csv")

    s = sub.add_parser(
        "score", help="score a model on a log with the measured errors (an unseen day), against MLR",
        description="Score a fitted model on a log that carries the measured error (a day it has not seen):"
                    " RMS and max before and after per axis, and the held-out MLR baseline on the same rows.",
        epilog="example:\n  compd score model.yaml --log day2.csv --json score.json",
    )
    s.add_argument("model", metavar="MODEL.yaml")
    s.add_argument("--log", required=True, metavar="LOG.csv")
    s.add_argument("--json", default=None, metavar="FILE", help="write the scores as JSON")

    s = sub.add_parser("xi", help="the mean-value point ξ of a temperature profile (CSV x_mm, T_c)",
                       description="Find the mean-value point ξ of a temperature profile along the spindle (CSV columns x_mm, T_c): where to put the ξ sensor.",
                       epilog="example:\n  compd xi --profile profile.csv")
    s.add_argument("--profile", required=True, metavar="FILE.csv")
    s = sub.add_parser("bench", help="time the 2 ms cycle against real Modbus devices, beside a bare and a naive loop",
                       description="Time the 2 ms cycle against Modbus devices served by the test rig, beside a bare"
                                   " sleep-and-spin loop (the machine's limit) and a naive loop (needs the rig installed).",
                       epilog="example:\n  compd bench --cycles 20000 --json bench.json")
    s.add_argument("--cycles", type=int, default=100_000, metavar="N", help="cycles of compd's loop")
    s.add_argument("--json", default=None, metavar="FILE", help="write the result as JSON (keys: docs/formats.md)")
    s.add_argument("--scheduler", choices=("other", "fifo"), default="other", help="loop.realtime.scheduler")
    s.add_argument("--period-ms", type=positive, default=2.0, dest="period_ms")
    s.add_argument("--load", type=int, default=0, metavar="N",
                   help="start N CPU-bound processes beside the loops for the run (default 0)")
    s.add_argument("--io", choices=("process", "thread"), default="process",
                   help="loop.io: device I/O and the service in processes of their own (default) or threads of"
                        " the loop's process")
    s.add_argument("--late-us", type=positive, default=200.0, dest="late_us", metavar="US",
                   help="cycles later than this are matched with the other threads' work (default 200)")
    s.add_argument(
        "--naive-cycles", type=int, default=None, dest="naive_cycles",
        help="cycles of the hand-written loop (default min(N, 5000))",
    )
    s.add_argument(
        "--trace", default=None, metavar="FILE",
        help="run compd's loop under perf and write why each late or slow cycle was (needs perf; short runs)",
    )
    s.add_argument(
        "--bare-cycles", type=int, default=None, dest="bare_cycles", metavar="N",
        help="cycles of the bare sleep-and-spin loop, the machine's limit (default: as --cycles; 0: none)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    # argparse exits 2 on bad arguments with a usage message: bad input is exit 2.
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except BadInput as e:
        print(f"compd: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        return 0
    except Exception as e:  # anything else: one line, exit 1 (traceback with COMPD_DEBUG=1)
        import os

        if os.environ.get("COMPD_DEBUG"):
            raise
        print(f"compd: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
