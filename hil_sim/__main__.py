"""`python -m hil_sim COMMAND`: a thin dispatcher; each command lives in its own module."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from compd.errors import BadInput


def _serve(args: argparse.Namespace) -> int:
    from hil_sim.serve import main as serve_main

    return serve_main(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m hil_sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    from hil_sim import logcmd

    logcmd.add_parser(sub)
    s = sub.add_parser("serve", help="start the devices a YAML file describes, until Ctrl-C")
    s.add_argument("--config", required=True, metavar="FILE")
    s.set_defaults(func=_serve)
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
