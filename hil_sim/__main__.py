"""`python -m hil_sim COMMAND`: a thin dispatcher; each command lives in its own module."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from compd.errors import BadInput


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m hil_sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    from hil_sim import logcmd

    logcmd.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except BadInput as e:
        print(f"hil_sim: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
