"""Command line: ``jaxvalve <subcommand>``; one module per subcommand."""
from __future__ import annotations

import argparse
import sys

from . import membrane, simulate

SUBCOMMANDS = {"membrane": membrane, "simulate": simulate}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="jaxvalve",
        description="Differentiable membrane mechanics for aortic valve closure (JAX).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, mod in SUBCOMMANDS.items():
        mod.add_parser(sub)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    return SUBCOMMANDS[args.command].run(args)


if __name__ == "__main__":
    sys.exit(main())
