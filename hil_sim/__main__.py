"""`python -m hil_sim COMMAND`: a thin dispatcher; each command lives in its own module."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import NoReturn

from compd.core.errors import BadInput


def _serve(args: argparse.Namespace) -> int:
    from hil_sim.serve import main as serve_main

    return serve_main(args)


class OneLineParser(argparse.ArgumentParser):
    """argparse with compd's error form: one line on stderr, exit 2 (`--help` shows the usage)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {' '.join(message.split())}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m hil_sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    from hil_sim import family, logcmd

    logcmd.add_parser(sub)
    family.add_parser(sub)
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
