"""The daemon's commands, each one's arguments beside it.

`compd run`, `check-config`, `status`, `probe`, `arm-model`, `opcua-cert`.
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys
from pathlib import Path
from typing import Any

from compd.cli.args import (
    check_output,
    command,
    count,
    finite,
    positive,
    writing,
)
from compd.core.errors import BadInput

log = logging.getLogger("compd")


def probe_socket(config: str | None) -> str:
    """The probe socket of the daemon of CONFIG (compd.service.control.socket_path), where the
    systemd units put it when the config names no status file, or the default."""
    from compd.service.control import DEFAULT_PATH, sock_beside, socket_path

    if config is None:
        return DEFAULT_PATH
    from compd.config import load_config

    cfg = load_config(config)
    if cfg.top.adapt is None:
        raise BadInput(
            "has no adapt section, so its daemon takes no probes (add `adapt: {}`, or"
            " `adapt: {apply: false}` to estimate without applying)",
            file=config,
            path="adapt",
        )
    from compd.service.status import daemon_status_path

    return str(socket_path(cfg, env={}) or sock_beside(daemon_status_path(cfg)))


def args_run(sub: Any) -> None:
    """`compd run`'s arguments."""
    s = sub.add_parser(
        "run",
        help="run the compensation loop",
        description="Run the compensation loop of CONFIG until SIGTERM or SIGINT (then emit the safe output); SIGHUP"
        " reloads the config.",
        epilog="example:\n  compd run configs/demo.yaml --duration 60"
        "\n  compd run /etc/compd/compd.yaml --observe --log-level debug",
    )
    s.add_argument("config")
    s.add_argument("--duration", type=positive, default=None, metavar="S", help="stop after S seconds (> 0)")
    s.add_argument("--json", default=None, metavar="FILE", help="write the run summary as JSON")
    s.add_argument("--observe", action="store_true", help="observe mode: full loop, output held disabled")
    s.add_argument("--log-level", default=None, choices=("debug", "info", "warning", "error"), dest="log_level")


@command("run", args_run)
def cmd_run(args: argparse.Namespace) -> int:
    from compd.daemon.run import run_with_reload

    check_output(args.json, "--json")
    result = run_with_reload(args.config, args.duration, args.observe, args.log_level)
    if result is None:  # SIGTERM or SIGINT while it started, before it opened anything
        print("compd: stopped before the loop started: nothing was opened", file=sys.stderr)
        return 0
    comp = result["compensation"]
    loop = result["loop"]
    if result.get("observe"):
        print("compd: observe mode: the output was held disabled (no correction reached the machine)")
    from compd.cycle.loop import HIST_US
    from compd.io.histogram import percentile_text

    late, comp_us = loop["lateness_us"]["p99"], loop["cycle_compute_us"]["p99"]
    print(
        f"compd: {loop['cycles']} cycles, {loop['misses']} missed, lateness p99"
        f" {percentile_text(late, late >= HIST_US, '.0f')}, compute p99"
        f" {percentile_text(comp_us, comp_us >= HIST_US, '.0f')}"
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
        print(
            "compd: the safe output did not reach the sink's device: the last correction may still be applied",
            file=sys.stderr,
        )
        return 1
    return 0


def args_check_config(sub: Any) -> None:
    """`compd check-config`'s arguments."""
    s = sub.add_parser(
        "check-config",
        help="validate a config; prints ok or exits 2",
        description="Validate a config and its wiring without opening a device: prints ok, or one line naming the"
        " file, line and key (exit 2).",
        epilog="example:\n  compd check-config configs/demo.yaml",
    )
    s.add_argument("config")


@command("check-config", args_check_config)
def cmd_check_config(args: argparse.Namespace) -> int:
    from compd.config import load_config
    from compd.daemon.host import check_status_folder, check_status_free
    from compd.plant.spec import check_config
    from compd.service.control import check_socket_path

    cfg = load_config(args.config)
    check_config(cfg)  # the wiring, by building the pipeline (opens no device)
    check_status_folder(cfg)  # the status file can be written where it goes
    check_status_free(cfg)  # no other running compd writes its status file
    check_socket_path(cfg)  # the probe socket can be bound where it goes
    print("ok")
    return 0


def args_status(sub: Any) -> None:
    """`compd status`'s arguments."""
    s = sub.add_parser(
        "status",
        help="the live state of a running daemon",
        description="Show the live state of a running daemon: per axis the model (file, fit date, coefficients, T0),"
        " correction and state, per signal value and quality; exit 1 when none runs.",
        epilog="example:\n  compd status --config /etc/compd/compd.yaml"
        "\n  compd status --status /run/compd/status.json --watch --interval-s 1",
    )
    s.add_argument("--json", action="store_true", help="print the status snapshot as JSON")
    s.add_argument(
        "--watch",
        action="store_true",
        help="redraw every --interval-s until Ctrl-C (rich tables if installed); waits while no daemon runs",
    )
    s.add_argument(
        "--interval-s",
        type=positive,
        default=1.0,
        dest="interval_s",
        metavar="S",
        help="--watch: seconds between redraws (default 1)",
    )
    where = s.add_mutually_exclusive_group()
    where.add_argument("--config", default=None, help="the daemon's config (finds its status file)")
    where.add_argument("--status", default=None, metavar="PATH", help="the status file")


@command("status", args_status)
def cmd_status(args: argparse.Namespace) -> int:
    from compd.cycle.statusblock import DEFAULT_PATH
    from compd.service.status import liveness, read_status, render

    if args.status:
        path = args.status
    elif args.config:
        from compd.config import load_config
        from compd.service.status import daemon_status_path

        path = str(daemon_status_path(load_config(args.config)))
    else:
        path = DEFAULT_PATH
    if args.watch:
        from compd.service.watch import watch

        if args.json:
            raise BadInput(
                "--watch shows the live view; --json prints the snapshot once (give one of them)", path="--watch"
            )
        return watch(path, args.interval_s)
    data = read_status(path)
    try:
        alive, why = liveness(data)
        text = (
            json.dumps({**data, "alive": alive, "liveness": why}, indent=1) if args.json else render(data, alive, why)
        )
    except (TypeError, ValueError, AttributeError, KeyError) as e:  # a field deeper down of the wrong type
        raise BadInput(f"not a compd status file: {type(e).__name__}: {e}", file=path) from None
    print(text)
    if not alive:
        print(f"compd: {path}: {why}", file=sys.stderr)
    return 0 if alive else 1


def args_probe(sub: Any) -> None:
    """`compd probe`'s arguments."""
    s = sub.add_parser(
        "probe",
        help="hand one probe measurement to the running daemon",
        description="Hand one probe measurement (the axis's thermal error measured on the machine) to the running"
        " daemon of CONFIG; exit 1 when none runs.",
        epilog="example:\n  compd probe --axis z --error-um 12.5 --config /etc/compd/compd.yaml",
    )
    s.add_argument("--axis", required=True, metavar="AX", help="the axis (a model output)")
    s.add_argument(
        "--error-um",
        required=True,
        type=finite,
        dest="error_um",
        metavar="E",
        help="the axis's whole thermal error measured on the machine, um, within ±10000 (see --residual)",
    )
    s.add_argument(
        "--position-mm", type=finite, default=None, dest="position_mm", metavar="P", help="where the probe measured"
    )
    s.add_argument(
        "--sigma-um",
        type=positive,
        default=None,
        dest="sigma_um",
        metavar="S",
        help="the measurement's sigma, 0.001 to 1000 um (default: adapt.sigma_um)",
    )
    s.add_argument(
        "--residual",
        action="store_true",
        help="E is the deviation that remains on the compensated machine (the daemon adds back"
        " the correction applied at that moment)",
    )
    s.add_argument("--config", default=None, help="the daemon's config (finds its probe socket)")


def shown(value: Any, spec: str = ".2f") -> str:
    """A value of the daemon's answer as text: a number formatted with `spec`, a string as it is,
    anything else (null, true, a list) as JSON: whatever the answer holds prints."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return format(value, spec)
    return value if isinstance(value, str) else json.dumps(value)


@command("probe", args_probe)
def cmd_probe(args: argparse.Namespace) -> int:
    from compd.core.probe import probe_problem
    from compd.service.control import NoDaemon, send_probe

    bad = probe_problem(args.error_um, args.sigma_um, args.position_mm)
    if bad is not None:  # refused here as the daemon would refuse it
        raise BadInput(bad[1], path="--" + bad[0].replace("_", "-"))
    path = probe_socket(args.config)
    request = {
        "op": "probe",
        "axis": args.axis,
        "error_um": args.error_um,
        "position_mm": args.position_mm,
        "sigma_um": args.sigma_um,
        "residual": args.residual,
    }
    try:
        answer = send_probe(path, request)
    except NoDaemon as e:
        print(f"compd: {e}", file=sys.stderr)
        return 1
    if not answer.get("ok"):
        error = answer.get("error", "refused")
        why = error if isinstance(error, str) else json.dumps(error)
        raise BadInput(
            f"the daemon refused the probe: {why}", path="--axis" if why.startswith("unknown axis") else None
        )
    what = "deviation" if args.residual else "error"
    head = f"compd: probe {args.axis} {what} {args.error_um:g} um"
    outcome = answer.get("outcome")
    said = {"ok", "outcome", "axis"}  # what the line says; every other key of the answer follows it
    if outcome in ("accepted", "rejected"):
        why = "" if answer.get("reason") is None else f" ({answer['reason']})"
        line = (
            f"{head} {outcome} at t={shown(answer.get('t_s'), '.1f')} s{why}: thermal error"
            f" {shown(answer.get('error_um'))} um, innovation {shown(answer.get('innovation_um'))} um"
            f" (sigma {shown(answer.get('innovation_sigma_um'))} um), offset now {shown(answer.get('offset_um'))} um"
        )
        said |= {"t_s", "reason", "error_um", "innovation_um", "innovation_sigma_um", "offset_um"}
    elif outcome == "queued":
        line = f"{head} queued (the loop has not taken it yet; see the daemon's log)"
    else:  # no_prediction, no_correction_known: handed over but not used
        line = f"{head} not used: {shown(outcome)}"
    rest = [f"{k}={shown(v, '')}" for k, v in answer.items() if k not in said]
    print(f"{line}; {' '.join(rest)}" if rest else line)
    return 0


def args_arm_model(sub: Any) -> None:
    """`compd arm-model`'s arguments."""
    s = sub.add_parser(
        "arm-model",
        help="let the running daemon apply the next model from the plant",
        description="Arm the running daemon of CONFIG to apply the next model published to its Sparkplug command"
        " topic (once, within --seconds); needs telemetry.remote_models.allow. Exit 1 when no daemon runs.",
        epilog="example:\n  compd arm-model /etc/compd/compd.yaml --seconds 300",
    )
    s.add_argument("config")
    s.add_argument(
        "--seconds",
        type=positive,
        default=None,
        metavar="S",
        help="how long it stays armed (default: telemetry.remote_models.arm_window_s)",
    )


@command("arm-model", args_arm_model)
def cmd_arm_model(args: argparse.Namespace) -> int:
    from compd.config import load_config
    from compd.service.control import NoDaemon, send_probe, sock_beside, socket_path
    from compd.service.status import daemon_status_path

    cfg = load_config(args.config)
    tel = cfg.top.telemetry
    if tel is None or not tel.remote_models.allow:
        raise BadInput(
            "its daemon takes no remote models (set telemetry.remote_models.allow: true)",
            file=args.config,
            path="telemetry.remote_models.allow",
        )
    path = str(socket_path(cfg, env={}) or sock_beside(daemon_status_path(cfg)))
    try:
        answer = send_probe(path, {"op": "arm_model", "window_s": args.seconds})
    except NoDaemon as e:
        print(f"compd: {e}", file=sys.stderr)
        return 1
    if not answer.get("ok"):
        raise BadInput(f"the daemon refused: {answer.get('error', 'refused')}")
    print(
        f"compd: armed for {shown(answer.get('armed_s'), '.0f')} s: the next model from the command topic is"
        f" applied (once) if it validates (pid {shown(answer.get('pid'), '')})"
    )
    return 0


def args_promote(sub: Any) -> None:
    """`compd promote`'s arguments."""
    s = sub.add_parser(
        "promote",
        help="make the config's shadow model the model, through a validated reload",
        description="Make CONFIG's shadow section its model. First says what it is about to make the"
        " model: the shadow's kind, file and sha256, where it came from, and what it and the active"
        " model predict now (the running daemon's status). The shadow is checked as a model sent to be"
        " applied is (check-config's checks, the model's axes, the guard's clamp over its inputs'"
        " fitted range) and must have been scored by the daemon running CONFIG on at least"
        " --min-probes probes per axis, not worse than the active model, unless --force. Then the"
        " config's text is edited (the old model kept as comment lines, the file as it was kept as"
        " CONFIG.<stamp>.bak) and the daemon reloads; promote waits until its status shows the"
        " promoted model. Exit 2 when refused; exit 1 when the reload did not take it: CONFIG is then"
        " put back as it was and the promoted text kept as CONFIG.promoted-rejected-<stamp>.",
        epilog="example:\n  compd promote /etc/compd/compd.yaml\n  compd promote cell.yaml --dry-run",
    )
    s.add_argument("config")
    s.add_argument(
        "--force",
        action="store_true",
        help="promote a shadow without enough probes, scored worse, or with no daemon to score it"
        " (the guard's clamp is checked all the same)",
    )
    s.add_argument(
        "--min-probes",
        type=count,
        default=None,
        dest="min_probes",
        metavar="N",
        help="probes per axis the daemon must have scored the shadow on (default 3)",
    )
    s.add_argument(
        "--dry-run",
        action="store_true",
        dest="dry_run",
        help="check, print the new config (what it says on stderr), change nothing",
    )
    s.add_argument(
        "--no-reload",
        action="store_true",
        dest="no_reload",
        help="edit the config only: the running daemon takes it at its next reload or start, unverified",
    )
    s.add_argument(
        "--wait-s",
        type=positive,
        default=60.0,
        dest="wait_s",
        metavar="S",
        help="how long to wait for the daemon's reload (default 60)",
    )


@command("promote", args_promote)
def cmd_promote(args: argparse.Namespace) -> int:
    from compd.commissioning.promote import MIN_PROBES, promote

    said = sys.stderr if args.dry_run else sys.stdout  # a dry run's stdout is the new config alone

    def say(line: str) -> None:
        print(f"compd promote: {line}", file=said, flush=True)

    r = promote(
        args.config,
        force=args.force,
        reload=not args.no_reload,
        wait_s=args.wait_s,
        dry_run=args.dry_run,
        min_probes=args.min_probes or MIN_PROBES,
        say=say,
    )
    if args.dry_run:
        sys.stdout.write(r["text"])
        return 0
    what = f"{r['model']}" + (f" ({r['model_file']})" if r.get("model_file") else "")
    if r["reloaded"] is False:
        print(
            f"compd promote: the daemon (pid {r['pid']}) did not show the promoted model within {args.wait_s:g} s"
            f" (see its log: reload_rejected or reload_failed): {args.config} is back as it was, the promoted text is"
            f" kept as {r['restored']}, and the daemon was asked to reload the config as it is",
            file=sys.stderr,
        )
        return 1
    print(f"compd promote: {args.config}: the shadow is the model now: {what}; the file as it was: {r['backup']}")
    if r["reloaded"] is None:  # nothing has loaded the promoted file yet: said, so that nobody takes it as checked
        if args.no_reload:
            print(
                "compd promote: --no-reload: the file is promoted unverified (the daemon has not loaded it): it"
                " takes the model at its next reload or start"
            )
        else:
            print(
                "compd promote: no daemon runs this config: the file is promoted unverified (no daemon has loaded"
                " it): it takes the model at its next start"
            )
        return 0
    print(f"compd promote: the daemon (pid {r['pid']}) reloaded and runs the promoted model")
    return 0


def args_opcua_cert(sub: Any) -> None:
    """`compd opcua-cert`'s arguments."""
    s = sub.add_parser(
        "opcua-cert",
        help="write a self-signed certificate and key for the OPC UA server",
        description="Write a self-signed OPC UA application certificate (RSA 2048, SHA-256, the application URI and"
        " hosts in its SubjectAltName) and its key (0600) for the opcua section; never overwrites.",
        epilog="example:\n  compd opcua-cert --cert opcua/server.pem --key opcua/server.key --host cell3-compd"
        " --host 10.0.3.17",
    )
    s.add_argument("--cert", required=True, metavar="FILE", help="the certificate to write (PEM)")
    s.add_argument("--key", required=True, metavar="FILE", help="its private key to write (PEM, 0600)")
    s.add_argument("--uri", default="urn:compd:server", help="the application URI (default urn:compd:server)")
    s.add_argument("--name", default="compd", help="the certificate's common name (default compd)")
    s.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="HOST",
        help="a DNS name or IP address clients use to reach it (repeat; default this host's name and 127.0.0.1)",
    )


@command("opcua-cert", args_opcua_cert)
def cmd_opcua_cert(args: argparse.Namespace) -> int:

    try:
        from compd.plant.material import generate_certificate
    except ImportError:
        from compd.core.registry import install_hint

        raise BadInput(f"needs the plant extra: {install_hint('plant')}") from None
    for path, key in ((args.cert, "--cert"), (args.key, "--key")):
        folder = Path(path).parent
        if not folder.exists():  # a folder of its own for the pair: readable by its owner only
            try:
                folder.mkdir(mode=0o700, parents=True)
            except OSError as e:
                raise BadInput(f"cannot make the folder {folder}: {e.strerror or e}", path=key) from None
        check_output(path, key)
        if Path(path).exists():
            raise BadInput(f"{path} exists: compd never overwrites a certificate or a key", path=key)
    generate_certificate(
        Path(args.cert),
        Path(args.key),
        common_name=args.name,
        application_uri=args.uri,
        hosts=args.host or [socket.gethostname(), "127.0.0.1"],
    )
    print(f"compd: wrote {args.cert} and {args.key} (key 0600) for {args.uri}")
    return 0
