"""Adjoint gradients of the smooth coaptation metrics against central differences, on the
benchmark valve at the clinical load.

    python benchmarks/gradients.py [--h 1.5] [--rtol 1e-9] [--step 1e-3] [--max-steps 30000]

At several templates (the benchmark start, a tuned design, and a small template near the
start of coaptation), closes the valve at 3 mmHg (h_E) and 80 mmHg (h_CC, h_avr, NCCA, h,
h_c), takes d metric / d(r, a, b, E) by the LU adjoint (`Evaluator.sensitivities`), and
compares each entry with central differences of warm-started closures (step ``--step`` mm
for r, a, b and a relative ``--step`` for E).  Prints one table row per metric and point,
the worst relative error of each point (over the entries whose central difference exceeds
1e-2) and the time of the sensitivities against one warm closure.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

# this folder holds optimize.py, named like the `optimize` package: off the import path
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import numpy as np  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from optimize import Evaluator, Objective, Target  # noqa: E402

POINTS = {"benchmark start": (12.0, 7.1, 15.0), "tuned": (10.9, 6.32, 14.33),
          "onset of coaptation": (9.5, 5.0, 13.9)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--h", type=float, default=1.5)
    ap.add_argument("--rtol", type=float, default=1e-9)
    ap.add_argument("--max-steps", type=int, default=30_000)
    ap.add_argument("--step", type=float, default=1e-3)
    args = ap.parse_args(argv)
    scene = Scene(h=args.h, rtol=args.rtol, max_steps=args.max_steps)
    # every metric of both loads, so that both closures run
    obj = Objective(targets=(Target("h_E", lower=0.0), Target("h", lower=0.0)))
    ev = Evaluator(scene, obj)
    print(f"benchmark root, h = {args.h} mm, StVK E = {scene.E} MPa, 3 and 80 mmHg, "
          f"FIRE rtol {args.rtol:g}, central differences with step {args.step:g}")
    print("| point | metric | value | d/dr | FD | d/da | FD | d/db | FD | d/dE | FD |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    worst = {}
    warm = None
    for label, rab in POINTS.items():
        if warm is None:
            e0 = ev.forward(rab)
        else:               # walk there in small warm-started steps, as the optimiser does
            for f in np.linspace(0.1, 1.0, 10):
                e0 = ev.forward(warm.rab + f * (np.asarray(rab) - warm.rab), warm)
                if not e0.converged:
                    break
                warm = e0
        if not e0.converged:
            print(f"| {label} | closure did not converge: {e0.reason} |", flush=True)
            continue
        warm = e0
        ev.sensitivities(e0)                                   # compile
        t = time.perf_counter()
        sens = ev.sensitivities(e0)
        t_s = time.perf_counter() - t
        t = time.perf_counter()
        fd, failed = {}, []

        def central(name, p, m, h):
            failed.extend(e.reason for e in (p, m) if not e.converged)
            if p.converged and m.converged:
                fd[name] = {q: (p.metrics[q] - m.metrics[q]) / (2 * h) for q in sens}
        for k, name in enumerate("rab"):
            d = np.zeros(3)
            d[k] = args.step
            central(name, ev.forward(np.add(rab, d), e0), ev.forward(np.subtract(rab, d), e0),
                    args.step)
        E0 = float(ev.material.E)
        mats = [dataclasses.replace(ev.material, E=E0 * (1 + s * args.step)) for s in (1, -1)]
        central("E", *(ev.forward(rab, e0, material=mt) for mt in mats), args.step * E0)
        t_f = (time.perf_counter() - t) / 8                     # one warm closure (both loads)
        if failed:
            print(f"| {label} | a finite-difference closure did not converge: {failed[0]} |",
                  flush=True)
            continue
        errs = []
        for q, g in sens.items():
            cells = []
            for name in ("r", "a", "b", "E"):
                cells += [f"{g[name]:.5g}", f"{fd[name][q]:.5g}"]
                if abs(fd[name][q]) > 1e-2:
                    errs.append(abs(g[name] - fd[name][q]) / abs(fd[name][q]))
            print(f"| {label} {tuple(rab)} | {q} | {e0.metrics[q]:.4f} | " + " | ".join(cells)
                  + " |", flush=True)
        worst[label] = (max(errs), len(errs), t_s, t_f, len(sens))
    print()
    for label, (w, n, t_s, t_f, k) in worst.items():
        print(f"{label}: worst relative error {w:.1e} over {n} entries (target < 1e-3); "
              f"sensitivities of {k} metrics {t_s:.2f} s = {t_s / t_f:.1f} warm closures "
              f"({t_f:.2f} s for both loads)")


if __name__ == "__main__":
    main()
