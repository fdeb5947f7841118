"""Do gradients pay?  The template optimisation (L-BFGS + adjoint gradients) against a
derivative-free baseline (scipy Nelder-Mead) on the same objective, on the benchmark root.

    python benchmarks/optimize.py [--h 1.5] [--maxfev 150] [--gtol 1e-5] [--ftol 1e-8]

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
    ap.add_argument("--gtol", type=float, default=1e-5,
                    help="L-BFGS: stop at this projected gradient norm (objective / mm)")
    ap.add_argument("--ftol", type=float, default=1e-8,
                    help="L-BFGS: stop when an iteration decreases f by less than this")
    ap.add_argument("--max-iter", type=int, default=60)
    args = ap.parse_args(argv)
    scene = Scene(h=args.h, rtol=1e-6, max_steps=5000)
    obj = Objective(area_ref=scene.template().area)
    ev = Evaluator(scene, obj)
    t0 = time.perf_counter()
    res = optimize_template(scene, obj, evaluator=ev, figures=False, gtol=args.gtol,
                            ftol=args.ftol, max_iter=args.max_iter)
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
          f"(h_c >= 4, h = 8, size weight 0.1), rtol 1e-6; L-BFGS gtol {args.gtol:g}, "
          f"ftol {args.ftol:g}")
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
    f_lb = res.value
    if np.any(best <= f_lb * (1 + 1e-9)):
        n_lb = int(np.argmax(best <= f_lb * (1 + 1e-9))) + 1
        q = next(q for q, r in zip(eq, res.records) if r["objective"] <= f_lb * (1 + 1e-9))
        print(f"to reach L-BFGS's final objective {f_lb:.6f}: L-BFGS {q:.1f} forward "
              f"equivalents, Nelder-Mead {n_lb}: ratio {n_lb / q:.1f}x")
    print(f"stopped: L-BFGS: {res.reason}; Nelder-Mead: {nm.message}")
    # the whole race: forward equivalents each needed to come within x % of the best
    # objective either found
    f_best = min(f_nm, res.value)
    lb = np.array([r["objective"] for r in res.records])
    print("| within x % of the best objective | L-BFGS fwd. eq. | Nelder-Mead fwd. eq. | ratio |")
    print("|---|---|---|---|")
    for pct in (50, 10, 2, 1, 0.5, 0.2, 0.1):
        lvl = f_best * (1 + pct / 100)
        a = float(np.asarray(eq)[np.argmax(lb <= lvl)]) if np.any(lb <= lvl) else None
        b = int(np.argmax(best <= lvl)) + 1 if np.any(best <= lvl) else None
        ratio = f"{b / a:.1f}x" if a and b else "-"
        print(f"| {pct:g} | {'-' if a is None else f'{a:.1f}'} | {'-' if b is None else b} "
              f"| {ratio} |")
    # the noise floor: L-BFGS's final design closed from other warm starts
    fin, vals = res.rab, []
    for seed in (res.evaluation, ev.forward(start), ev.forward(np.array([nm.x[0], nm.x[1],
                                                                          nm.x[2]]))):
        e = ev.forward(fin, seed if seed.converged else None)
        vals.append(e.value)
    print(f"objective at L-BFGS's final design, closed from three warm starts (its own, the "
          f"start's and Nelder-Mead's final state): {', '.join(f'{v:.6f}' for v in vals)} "
          f"(spread {np.ptp(vals):.1e})")
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    with open(out / "optimize_history.csv", "w") as fh:
        fh.write("method,forward_equivalents,objective\n")
        for q, r in zip(eq, res.records):
            fh.write(f"lbfgs,{q:.3f},{r['objective']:.9g}\n")
        for i, v in enumerate(hist):
            fh.write(f"nelder-mead,{i + 1},{v:.9g}\n")


if __name__ == "__main__":
    main()
