"""The `compd` command line (CONTRACT.md): thin — parse, call, print."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from collections.abc import Callable, Sequence

from compd.errors import BadInput

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}


def command(name: str) -> Callable[[Callable[[argparse.Namespace], int]], Callable[[argparse.Namespace], int]]:
    def deco(fn: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
        COMMANDS[name] = fn
        return fn

    return deco


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
    from compd.app import App
    from compd.config import load_config

    cfg = load_config(args.config)
    app = App(cfg, out=sys.stderr)  # wiring is checked by building the pipeline (opens no device)
    if app.logger is not None:  # App opens the data log when built: stop its writer thread
        app.logger.close()
    print("ok")
    return 0


@command("run")
def cmd_run(args: argparse.Namespace) -> int:
    from compd.app import App
    from compd.config import load_config
    from compd.logsetup import setup_logging

    cfg = load_config(args.config)
    setup_logging(args.log_level or cfg.top.logging.level)
    app = App(cfg, duration_s=args.duration, observe=True if args.observe else None)

    def on_signal(signum: int, frame: object) -> None:
        app.loop.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    result = app.run()
    comp = result["compensation"]
    loop = result["loop"]
    if result.get("observe"):
        print("compd: observe mode: the output was held disabled (no correction reached the machine)")
    print(
        f"compd: {loop['cycles']} cycles, {loop['misses']} missed, lateness p99"
        f" {loop['lateness_us']['p99']:.0f} us, compute p99 {loop['cycle_compute_us']['p99']:.0f} us"
    )
    for axis, r in comp.items():
        print(
            f"axis {axis}: RMS error without compensation {r['rms_before_um']:.2f} um,"
            f" with {r['rms_after_um']:.2f} um; max {r['max_abs_before_um']:.2f} ->"
            f" {r['max_abs_after_um']:.2f} um; reduction {r['reduction_pct']:.1f} %"
        )
    if result["log_error"]:
        print(f"compd: {result['log_error']}", file=sys.stderr)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(result, fh, indent=2)
    return 0


@command("status")
def cmd_status(args: argparse.Namespace) -> int:
    from compd.status import DEFAULT_PATH, liveness, read_status, render

    if args.status:
        path = args.status
    elif args.config:
        from pathlib import Path

        from compd.config import load_config
        from compd.service import status_path

        found = status_path(load_config(args.config), env={})
        # no status.path: where the systemd units put it (RuntimeDirectory=compd or compd/%i)
        stem = Path(args.config).stem
        path = str(found) if found else DEFAULT_PATH if stem == "compd" else f"/run/compd/{stem}/status.json"
    else:
        path = DEFAULT_PATH
    data = read_status(path)
    alive, why = liveness(data)
    if args.json:
        print(json.dumps({**data, "alive": alive, "liveness": why}, indent=1))
    else:
        print(render(data, alive, why))
    if not alive:
        print(f"compd: {path}: {why}", file=sys.stderr)
    return 0 if alive else 1


@command("docs")
def cmd_docs(args: argparse.Namespace) -> int:
    from compd.docgen import generate

    text = generate()
    if args.check:
        if args.out is None:
            raise BadInput("--check needs --out FILE")
        try:
            with open(args.out, encoding="utf-8") as fh:
                same = fh.read() == text
        except OSError as e:
            raise BadInput(f"cannot read: {e.strerror}", file=args.out) from None
        if not same:
            print(f"compd: {args.out} is out of date: run compd docs --out {args.out}", file=sys.stderr)
            return 1
        return 0
    if args.out is None:
        sys.stdout.write(text)
    else:
        with open(args.out, "w", encoding="utf-8") as fh:
            fh.write(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="compd", description="Real-time thermal-error compensation for CNC machine tools."
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("run", help="run the compensation loop")
    s.add_argument("config")
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    s.add_argument("--json", default=None, metavar="FILE", help="write the run summary as JSON")
    s.add_argument(
        "--observe", action="store_true", help="observe mode: full loop, output held disabled"
    )
    s.add_argument(
        "--log-level", default=None, choices=("debug", "info", "warning", "error"), dest="log_level"
    )

    s = sub.add_parser("status", help="the live state of a running daemon")
    s.add_argument("--json", action="store_true", help="print the status snapshot as JSON")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--config", default=None, help="the daemon's config (finds its status file)")
    where.add_argument("--status", default=None, metavar="PATH", help="the status file")

    s = sub.add_parser("docs", help="generate docs/configuration.md from the config schema")
    s.add_argument("--out", default=None, metavar="FILE", help="write here (default: stdout)")
    s.add_argument("--check", action="store_true", help="exit 1 if FILE differs from a fresh generation")

    s = sub.add_parser("check-config", help="validate a config; prints ok or exits 2")
    s.add_argument("config")

    s = sub.add_parser("encode", help="the 16-bit word for two corrections (µm)")
    s.add_argument("c1_um", type=float, metavar="C1_UM")
    s.add_argument("c2_um", type=float, metavar="C2_UM")
    s.add_argument("--lsb-um", type=float, default=1.0, dest="lsb_um")
    s.add_argument("--deadband-um", type=float, default=1.0, dest="deadband_um")

    s = sub.add_parser("decode", help="direction, enable and magnitude of both axes of a word")
    s.add_argument("word", metavar="WORD")
    s.add_argument("--lsb-um", type=float, default=1.0, dest="lsb_um")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    # argparse exits 2 on bad arguments with a usage message, as CONTRACT wants.
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
