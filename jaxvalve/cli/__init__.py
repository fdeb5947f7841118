"""Command line: ``jaxvalve <subcommand>``; one module per subcommand.

Exit codes: 0 done, 2 bad input (`JaxvalveError`, its message naming the parameter and its
valid range), 3 a solve did not converge (`ConvergenceError`, with its residual)."""
from __future__ import annotations

import argparse
import sys

from . import membrane, optimize, simulate, sweep

SUBCOMMANDS = {"membrane": membrane, "optimize": optimize, "simulate": simulate,
               "sweep": sweep}


def enable_compilation_cache():
    """Keep XLA executables between runs in ``$JAXVALVE_CACHE_DIR`` (default
    ``~/.cache/jaxvalve/xla``; set it to ``off`` to disable): a second run of the same
    scene shape then skips most of the compilation."""
    import os
    from pathlib import Path

    path = os.environ.get("JAXVALVE_CACHE_DIR", str(Path.home() / ".cache" / "jaxvalve" / "xla"))
    if path.lower() in ("", "off", "0", "none"):
        return None
    import jax
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path


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
    enable_compilation_cache()
    from ..errors import ConvergenceError, JaxvalveError
    try:
        return SUBCOMMANDS[args.command].run(args)
    except JaxvalveError as e:          # bad input: the message names the parameter
        print(f"jaxvalve {args.command}: error: {e}", file=sys.stderr)
        return 2
    except ConvergenceError as e:       # a solve that must converge did not
        print(f"jaxvalve {args.command}: error: {e}", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
