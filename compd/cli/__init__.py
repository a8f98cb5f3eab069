"""The `compd` command line: thin — parse, call, print.

Each command lives with its arguments in this package's modules.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from compd.cli import commissioning, daemon, plant, tools  # noqa: F401  (their commands register themselves)
from compd.cli.args import ARGUMENTS, COMMANDS, Parser, writing
from compd.core.errors import BadInput
from compd.core.registry import NOT_INSTALLED, commissioning_missing

__all__ = ["build_parser", "main", "writing"]

ORDER = [
    "run",
    "status",
    "probe",
    "arm-model",
    "promote",
    "opcua-cert",
    "sparkplug-watch",
    "docs",
    "check-config",
    "replay",
    "output-test",
    "plot",
    "report",
    "encode",
    "decode",
    "testplan",
    "fit",
    "predict",
    "score",
    "xi",
    "bench",
]  # as `compd --help` lists them


def build_parser() -> Parser:
    from compd import version

    p = Parser(
        prog="compd",
        description="Real-time thermal-error compensation for CNC machine tools.",
        epilog="example:\n  compd check-config configs/demo.yaml\n  compd run configs/demo.yaml --observe\n"
        "  compd status --config configs/demo.yaml\n\n`compd COMMAND --help` describes a command.",
    )
    p.add_argument("--version", action="version", version=f"compd {version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for name in ORDER:
        ARGUMENTS[name](sub)
    return p


FIT_COMMANDS = ("fit",)


def one_blas_thread() -> None:
    """A fit's linear algebra on one BLAS thread (unless the environment says otherwise), set before
    numpy loads: its matrices are small (rows × a few dozen columns), and on a shared box OpenBLAS's
    threads spin waiting for each other (measured: a fit's Gram products 9 s of CPU on a loaded
    2-core box, 0.05 s on one thread)."""
    import os

    if "numpy" not in sys.modules:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    # argparse exits 2 on bad arguments with a usage message: bad input is exit 2.
    args = parser.parse_args(argv)
    if args.command in FIT_COMMANDS:
        one_blas_thread()
    try:
        return COMMANDS[args.command](args)
    except BadInput as e:
        print(f"compd: {e}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as e:
        if not commissioning_missing(e):
            return internal_error(e)
        # the Debian daemon package alone: the command is the other package's (a lazy import of it failed)
        print(f"compd {args.command}: {NOT_INSTALLED}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        return 0
    except Exception as e:
        return internal_error(e)


def internal_error(e: Exception) -> int:
    """Anything but bad input: one line, exit 1 (the traceback with COMPD_DEBUG=1)."""
    import os

    if os.environ.get("COMPD_DEBUG"):
        raise e
    print(f"compd: internal error: {type(e).__name__}: {e}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
