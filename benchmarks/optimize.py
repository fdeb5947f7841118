"""Do gradients pay?  The template optimisation (L-BFGS + adjoint gradients) against a
derivative-free baseline (scipy Nelder-Mead) on the same objective, on the benchmark root.

    python benchmarks/optimize.py [--h 1.5] [--maxfev 150]

Both use one `Evaluator` (the same compiled closures, warm starts from the last accepted
point).  A gradient is counted as its measured cost in forward closures: the time of one
value-and-gradient divided by the time of one warm-started forward closure, both measured
here at the final design after compilation.  Prints a table and the ratio of forward-solve
equivalents each method needed to reach Nelder-Mead's final objective.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# this file is named like the `optimize` package: take its folder off the import path
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from optimize import Evaluator, Objective, optimize_template


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--h", type=float, default=1.5)
    ap.add_argument("--maxfev", type=int, default=150)
    args = ap.parse_args(argv)
    scene = Scene(h=args.h, rtol=1e-6, max_steps=5000)
    obj = Objective(area_ref=scene.template().area)
    ev = Evaluator(scene, obj)
    t0 = time.perf_counter()
    res = optimize_template(scene, obj, evaluator=ev, figures=False)
    t_grad = time.perf_counter() - t0
    # cost of a gradient in forward closures, at the start (compiled by now): a cold
    # closure from the placement, a warm one after a 1e-3 mm step, and a value+gradient
    start = np.array([scene.r, scene.a, scene.b])
    tc, tf, tg = [], [], []
    for _ in range(2):
        s = time.perf_counter()
        e0 = ev.forward(start)
        tc.append(time.perf_counter() - s)
        s = time.perf_counter()
        ev.forward(start + 1e-3, e0)
        tf.append(time.perf_counter() - s)
        s = time.perf_counter()
        ev.gradient(e0)
        tg.append(time.perf_counter() - s)
    ratio = float(np.min(tg) / np.min(tf))
    # Nelder-Mead on the same objective (infeasible or non-converged: +inf)
    ev2 = Evaluator(scene, obj)
    hist, last = [], [None]

    def f(rab):
        if ev2.feasible(rab):
            hist.append(np.inf)
            return np.inf
        e = ev2.forward(rab, last[0])
        hist.append(e.value)
        if e.converged:
            last[0] = e
        return e.value

    t0 = time.perf_counter()
    nm = scipy.optimize.minimize(f, [scene.r, scene.a, scene.b], method="Nelder-Mead",
                                 bounds=list(obj.bounds.values()),
                                 options=dict(maxfev=args.maxfev, xatol=1e-3, fatol=1e-5,
                                              initial_simplex=None))
    t_nm = time.perf_counter() - t0
    best = np.minimum.accumulate(hist)
    f_nm = float(best[-1])
    # gradient run: forward equivalents when it first reached f_nm
    eq = [r["forward"] + ratio * r["gradient"] for r in res.records]
    hit = [q for q, r in zip(eq, res.records) if r["objective"] <= f_nm * (1 + 1e-9)]
    n_nm = int(np.argmax(best <= f_nm * (1 + 1e-9))) + 1
    print(f"benchmark root, h = {args.h} mm, StVK, 80 mmHg, default targets "
          f"(h_c >= 4, h = 8, size weight 0.1), rtol 1e-6")
    print(f"one value+gradient = {np.min(tg):.3f} s = {np.min(tg) / np.min(tc):.2f} cold "
          f"closures ({np.min(tc):.3f} s, from the placement) = {ratio:.2f} warm closures "
          f"({np.min(tf):.3f} s); gradients are counted as {ratio:.2f} forward solves")
    print("| method | iterations | forward | gradients | forward equivalents | wall s "
          "(incl. compile) | final objective | r | a | b |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    r = res.records[-1]
    print(f"| L-BFGS + adjoint | {r['iteration']} | {res.counts['forward']} | "
          f"{res.counts['gradient']} | {eq[-1]:.1f} | {t_grad:.1f} ({res.compile_s:.1f}) | "
          f"{res.value:.6f} | {r['r']:.3f} | {r['a']:.3f} | {r['b']:.3f} |")
    print(f"| Nelder-Mead | {nm.nit} | {nm.nfev} | 0 | {nm.nfev} | {t_nm:.1f} | {f_nm:.6f} | "
          f"{nm.x[0]:.3f} | {nm.x[1]:.3f} | {nm.x[2]:.3f} |")
    if hit:
        print(f"to reach Nelder-Mead's final objective {f_nm:.6f}: L-BFGS {hit[0]:.1f} "
              f"forward equivalents, Nelder-Mead {n_nm}: ratio {n_nm / hit[0]:.1f}x "
              f"(target >= 3x)")
    else:
        print(f"L-BFGS did not reach Nelder-Mead's final objective {f_nm:.6f} "
              f"(its best {res.value:.6f})")
    print(f"stopped: L-BFGS: {res.reason}; Nelder-Mead: {nm.message}")


if __name__ == "__main__":
    main()
