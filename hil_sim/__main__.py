"""`python -m hil_sim COMMAND`: a thin dispatcher to the subcommands' modules."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hil_sim", description="hardware-in-the-loop simulator")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    s = sub.add_parser("serve", help="start the devices a YAML file describes, until Ctrl-C")
    s.add_argument("--config", required=True, metavar="FILE")
    args = p.parse_args(argv)
    if args.command == "serve":
        from hil_sim.serve import main as serve_main

        return serve_main(args)
    return 2


if __name__ == "__main__":
    sys.exit(main())
