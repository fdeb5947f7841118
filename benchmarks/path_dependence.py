"""Does a design's closed state depend on where its closure starts?

    python benchmarks/path_dependence.py [--h 1.5]

The optimiser warm-starts each closure from the last accepted design's closed state.
This script closes one design three ways: from the placement (the open valve), from the
start template's closed state, and by continuation along a path of designs, each closure
warm-started from the one before.  The path is the one a trial Gauss-Newton optimiser
took this session from the benchmark template (12, 7.1, 15) toward r = 8 mm (its
iterates, rounded to 1e-3 mm; the optimiser was dropped).  Prints the objective (default
targets) and the metrics at every waypoint, both ways.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import numpy as np  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from optimize import Evaluator, Objective  # noqa: E402

PATH = np.array([
    (12.000, 7.100, 15.000), (11.875, 7.223, 14.993), (10.875, 7.932, 15.267),
    (9.875, 8.308, 15.901), (9.179, 9.308, 15.822), (8.890, 9.733, 15.851),
    (8.965, 9.622, 15.845), (8.961, 9.624, 15.846), (9.034, 9.124, 15.985),
    (9.031, 8.960, 16.045), (9.043, 8.419, 16.229), (9.007, 8.435, 16.242),
    (8.963, 7.935, 16.426), (8.876, 7.801, 16.511), (8.786, 7.701, 16.585),
    (8.768, 7.652, 16.612), (8.553, 7.152, 16.896), (8.544, 7.214, 16.870),
    (8.272, 6.714, 17.150), (8.135, 6.557, 17.244), (8.064, 6.541, 17.262),
    (8.015, 6.513, 17.281), (8.000, 6.507, 17.287)])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--h", type=float, default=1.5)
    args = ap.parse_args(argv)
    scene = Scene(h=args.h, rtol=1e-6, max_steps=20000)
    obj = Objective(area_ref=scene.template().area)
    ev = Evaluator(scene, obj)
    print(f"benchmark root, h = {args.h} mm, StVK, 80 mmHg, default targets, rtol 1e-6, at "
          f"most 20000 FIRE steps a closure")
    print("| waypoint | (r, a, b) mm | f along the path | f from the placement | f from the "
          "start's state | h along / placement | h_c along / placement |")
    print("|---|---|---|---|---|---|---|")
    start = ev.forward(PATH[0])
    prev = start
    for k, rab in enumerate(PATH):
        along = ev.forward(rab, prev) if k else start
        cold = ev.forward(rab, None)
        from_start = ev.forward(rab, start)
        if along.converged:
            prev = along

        def f(e):
            return f"{e.value:.6f}" if e.converged else "not converged"

        def m(key):
            return " / ".join(f"{e.metrics[key]:.3f}" if e.converged else "-"
                              for e in (along, cold))
        print(f"| {k} | ({rab[0]:.3f}, {rab[1]:.3f}, {rab[2]:.3f}) | {f(along)} | {f(cold)} "
              f"| {f(from_start)} | {m('h')} | {m('h_c')} |")


if __name__ == "__main__":
    main()
