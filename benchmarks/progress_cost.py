"""What live progress costs: the beacons of `jaxvalve.progress` in a compiled FIRE loop.

The benchmark valve (StVK, FIRE on the smooth law, both loads) is closed in one process
with the beacons (the default: the loop run from the host in stretches of
`progress.BEACON_EVERY` steps, a beacon after each, `equilibrium._solve_stretches`) and
without them (the whole loop as one program, `equilibrium._solve_compiled`, with
`solvers.base._send_beacon` replaced by a no-op before it is traced: no callback and no
stretches).  Each variant is
compiled afresh (`jax.clear_caches()`), then timed ``--repeats`` times after compilation,
alternating the variants, and the table gives the median solve time (both loads) of each
and the overhead in per cent.  The target: under 5 %.  A heartbeat thread runs during the
beacon runs, as in the CLI, printing into a buffer.

    python benchmarks/progress_cost.py [--h 1.5] [--repeats 5] [--out benchmarks/results/progress_cost.txt]
"""
from __future__ import annotations

import argparse
import io
import statistics
import sys
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve import progress  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.solvers import base, equilibrium  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402
from closure_speed import Tee  # noqa: E402  (this folder is on the path of a script)

REAL = base._send_beacon
STRETCHES = equilibrium._solve_stretches


def variant(on: bool):
    base._send_beacon = REAL if on else (lambda *a, **k: None)
    equilibrium._solve_stretches = STRETCHES if on else equilibrium._solve_compiled
    jax.clear_caches()


def closure(scene, valve, on):
    before = progress.latest()["serial"]
    sink = io.StringIO()
    with progress.Heartbeat(lambda m: print(m, file=sink), every=2.0) as hb:
        res = simulate(scene, valve=valve, progress=hb.say, throw=False)
    beacons = progress.latest()["serial"] - before
    steps = sum(int(s.steps) for s in res.solves)
    return (sum(s.solve_s for s in res.solves), sum(s.compile_s for s in res.solves),
            steps, beacons, res.converged, res.summary())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be a positive integer; got {args.repeats}")
    out = Tee()
    jax.config.update("jax_enable_x64", True)
    out(f"# progress beacons: cost in a compiled FIRE closure (h = {args.h} mm)")
    out(f"# {platform_summary()}")
    out(f"# BEACON_EVERY = {progress.BEACON_EVERY} steps")
    scene = Scene(h=args.h, fallback=False)
    valve = build_scene_valve(scene)
    times = {True: [], False: []}
    info = {}
    for on in (True, False):                     # compile each variant once, untimed
        variant(on)
        info[on] = closure(scene, valve, on)
        out(f"compiled {'with' if on else 'without'} beacons: {info[on][1]:.1f} s compile, "
            f"{info[on][2]} steps, {info[on][3]} beacons, converged {info[on][4]}")
    for _ in range(args.repeats):
        for on in (True, False):
            variant(on)
            s, c, steps, beacons, conv, summ = closure(scene, valve, on)
            times[on].append(s)
            assert summ == info[on][5], "the beacons must not change the numbers"
    variant(True)
    med = {on: statistics.median(v) for on, v in times.items()}
    out("| variant | median solve s (both loads) | runs |")
    out("|---|---|---|")
    for on in (True, False):
        out(f"| {'beacons' if on else 'no beacons'} | {med[on]:.3f} | "
            + ", ".join(f"{t:.3f}" for t in times[on]) + " |")
    same = info[True][5] == info[False][5]
    out(f"metrics identical with and without beacons: {same}")
    out(f"beacon overhead: {100 * (med[True] / med[False] - 1):+.1f} % "
        f"({info[True][3]} beacons over {info[True][2]} steps)")
    out.write(args.out)


if __name__ == "__main__":
    main()
