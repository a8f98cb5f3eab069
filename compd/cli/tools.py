"""The word, the docs and the bench: `compd encode`, `decode`, `docs`, `bench`; each one's arguments beside it."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from typing import Any

from compd.cli.args import (
    check_output,
    command,
    finite,
    non_negative,
    positive,
    writing,
)
from compd.core.errors import BadInput

log = logging.getLogger("compd")


def _parse_word(text: str) -> int:
    try:
        word = int(text, 0)
    except ValueError:
        raise BadInput(f"not a word: {text!r} (give e.g. 0xC543)", path="WORD") from None
    if not 0 <= word <= 0xFFFF:
        raise BadInput(f"a word is 16 bits (0x0000..0xFFFF), got {text}", path="WORD")
    return word


def installed_command(name: str, needs: str) -> Callable[[argparse.Namespace], int]:
    """The command another installed package provides (entry point group `compd.commands`),
    or BadInput (exit 2) naming what is missing."""
    from compd.core.registry import entry_point, load_entry_point

    ep = entry_point("compd.commands", name)
    if ep is None:
        raise BadInput(
            f"`compd {name}` {needs}, which is not installed (no '{name}' in entry point group"
            " compd.commands): install compd from its source tree, with the rig, to run it"
        )
    return load_entry_point(ep, f"`compd {name}`")


def args_encode(sub: Any) -> None:
    """`compd encode`'s arguments."""
    s = sub.add_parser(
        "encode",
        help="the 16-bit word for two corrections (µm)",
        description="Print the 16-bit compensation word for two corrections C1, C2 (µm), with what each byte means.",
        epilog="example:\n  compd encode 12 -3.5",
    )
    s.add_argument("c1_um", type=finite, metavar="C1_UM")
    s.add_argument("c2_um", type=finite, metavar="C2_UM")
    s.add_argument("--lsb-um", type=positive, default=1.0, dest="lsb_um")
    s.add_argument("--deadband-um", type=non_negative, default=1.0, dest="deadband_um")


@command("encode", args_encode)
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


def args_decode(sub: Any) -> None:
    """`compd decode`'s arguments."""
    s = sub.add_parser(
        "decode",
        help="direction, enable and magnitude of both axes of a word",
        description="Print direction, enable and magnitude of both axes of a 16-bit compensation word.",
        epilog="example:\n  compd decode 0xC543",
    )
    s.add_argument("word", metavar="WORD")
    s.add_argument("--lsb-um", type=positive, default=1.0, dest="lsb_um")


@command("decode", args_decode)
def cmd_decode(args: argparse.Namespace) -> int:
    from compd.codec import decode

    word = _parse_word(args.word)
    for name, code in zip(("X1", "X2"), decode(word), strict=True):
        sign = "+" if code.direction > 0 else "-"
        state = "enabled" if code.enable else "disabled"
        value = code.direction * code.magnitude * args.lsb_um if code.enable else 0.0
        print(
            f"{name}: direction {sign} enable {int(code.enable)} ({state}) magnitude {code.magnitude} -> {value:+g} um"
        )
    return 0


def args_docs(sub: Any) -> None:
    """`compd docs`'s arguments."""
    s = sub.add_parser(
        "docs",
        help="generate docs/configuration.md from the config schema",
        description="Generate the configuration reference (docs/configuration.md) from the config schema, or with"
        " --metrics the metrics reference (docs/metrics.md); --check tells whether FILE is up to date.",
        epilog="example:\n  compd docs --out docs/configuration.md\n  compd docs --out docs/configuration.md --check"
        "\n  compd docs --metrics --out docs/metrics.md",
    )
    s.add_argument("--out", default=None, metavar="FILE", help="write here (default: stdout)")
    s.add_argument("--check", action="store_true", help="exit 1 if FILE differs from a fresh generation")
    s.add_argument(
        "--metrics", action="store_true", help="the metrics reference (docs/metrics.md) instead of the configuration's"
    )


@command("docs", args_docs)
def cmd_docs(args: argparse.Namespace) -> int:
    from compd.commissioning.docgen import generate

    if args.metrics:
        from compd.service.metrics import metrics_markdown

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


def args_bench(sub: Any) -> None:
    """`compd bench`'s arguments."""
    s = sub.add_parser(
        "bench",
        help="time the 2 ms cycle against real Modbus devices, beside a bare and a naive loop",
        description="Time the 2 ms cycle against Modbus devices served by the test rig, beside a bare"
        " sleep-and-spin loop (the machine's limit) and a naive loop (needs the rig installed).",
        epilog="example:\n  compd bench --cycles 20000 --json bench.json",
    )
    s.add_argument("--cycles", type=int, default=100_000, metavar="N", help="cycles of compd's loop")
    s.add_argument("--json", default=None, metavar="FILE", help="write the result as JSON (keys: docs/formats.md)")
    s.add_argument("--scheduler", choices=("other", "fifo"), default="other", help="loop.realtime.scheduler")
    s.add_argument("--period-ms", type=positive, default=2.0, dest="period_ms")
    s.add_argument(
        "--load",
        type=int,
        default=0,
        metavar="N",
        help="start N CPU-bound processes beside the loops for the run (default 0)",
    )
    s.add_argument(
        "--io",
        choices=("process", "thread"),
        default="process",
        help="loop.io: device I/O and the service in processes of their own (default) or threads of the loop's process",
    )
    s.add_argument(
        "--late-us",
        type=positive,
        default=200.0,
        dest="late_us",
        metavar="US",
        help="cycles later than this are matched with the other threads' work (default 200)",
    )
    s.add_argument(
        "--naive-cycles",
        type=int,
        default=None,
        dest="naive_cycles",
        help="cycles of the hand-written loop (default min(N, 5000))",
    )
    s.add_argument(
        "--trace",
        default=None,
        metavar="FILE",
        help="run compd's loop under perf and write why each late or slow cycle was (needs perf; short runs)",
    )
    s.add_argument(
        "--bare-cycles",
        type=int,
        default=None,
        dest="bare_cycles",
        metavar="N",
        help="cycles of the bare sleep-and-spin loop, the machine's limit (default: as --cycles; 0: none)",
    )


@command("bench", args_bench)
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
