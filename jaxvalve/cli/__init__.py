"""Command line: ``jaxvalve <subcommand>``; one module per subcommand.

Exit codes: 0 done, 2 bad input (`JaxvalveError`, its message naming the parameter and its
valid range), 3 a solve did not converge (`ConvergenceError`, with its residual)."""
from __future__ import annotations

import argparse
import sys

from . import membrane, optimize, phantom, segment, simulate, sweep

SUBCOMMANDS = {"membrane": membrane, "optimize": optimize, "phantom": phantom,
               "segment": segment, "simulate": simulate, "sweep": sweep}


def enable_compilation_cache():
    """Keep XLA executables between runs in ``$JAXVALVE_CACHE_DIR`` (default
    ``~/.cache/jaxvalve/xla``; set it to ``off`` to disable): a second run of the same
    scene shape then skips most of the compilation.  Every program is kept, however quickly
    it compiled: with JAX's threshold at 0.5 s a warm `jaxvalve optimize` compiled 2.6 s of
    small programs again and took 19.6-20.1 s against 18.3-19.2 s with every program
    kept (three warm runs each, alternating; the cache 3.7 MB against 2.5 MB)."""
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
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


def build_parser() -> argparse.ArgumentParser:
    """The `jaxvalve` command line: one subparser per module of `SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="jaxvalve",
        description="Differentiable membrane mechanics for aortic valve closure (JAX).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in SUBCOMMANDS.values():
        mod.add_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
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


#: stderr lines `run` drops: XLA's CPU loader of cached executables warns on every cache
#: hit that the cached program's target features differ from the host's, because it
#: counts LLVM tuning preferences (+prefer-no-gather, +prefer-no-scatter) as CPU features
#: (openxla/xla#44565); the entry is loaded all the same (the benchmark valve at
#: h = 3 mm compiles in 2.9 s from a warm cache, 11.5 s without it), on the machine that
#: wrote it.  Both markers must be on the line.
SPURIOUS = (b"cpu_aot_loader.cc", b"Target machine feature +prefer-no-")


def _filter_stderr():
    """Pass everything written to file descriptor 2 (Python's and XLA's C++ logs alike)
    through a thread that drops the `SPURIOUS` lines.  Returns a function that restores
    the real stderr and waits for the thread to write out what is left.  Output still in
    the pipe when the process dies by a signal is lost."""
    import os
    import threading

    sys.stderr.flush()
    try:
        r, w = os.pipe()
        real, keep = os.dup(2), os.dup(2)
        os.dup2(w, 2)
        os.close(w)
    except OSError:               # no stderr to filter (closed, or no such descriptor)
        return lambda: None

    def pump():
        with os.fdopen(r, "rb") as src, os.fdopen(real, "wb", buffering=0) as dst:
            for line in src:
                if not all(m in line for m in SPURIOUS):
                    dst.write(line)

    t = threading.Thread(target=pump, name="jaxvalve-stderr", daemon=True)
    t.start()

    def restore():
        sys.stderr.flush()
        os.dup2(keep, 2)          # closes the pipe's last write end: the pump sees EOF
        os.close(keep)
        t.join(timeout=5.0)
    return restore


def run() -> None:
    """The ``jaxvalve`` console command: `main` with XLA's spurious cache-loader warnings
    (`SPURIOUS`) dropped from stderr."""
    restore = _filter_stderr()
    try:
        code = main()
    finally:
        restore()
    sys.exit(code)


if __name__ == "__main__":
    run()
