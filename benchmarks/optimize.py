"""Do gradients pay?  The template optimisation (L-BFGS with adjoint gradients) against a
derivative-free baseline (scipy Nelder-Mead) on the same objective, on the benchmark root.

    python benchmarks/optimize.py [--h 1.5] [--maxfev 150] [--gtol 1e-5] [--ftol 1e-8]
                                  [--cold]

Each method has its own `Evaluator` (the same compiled closures, warm starts from the last
accepted point).  A gradient is counted as its measured cost in forward closures: the time
of one gradient (the adjoint and its pullback; each forward evaluation already computes
the objective's partials at fixed states) divided by the time of one closure after a
1e-3 mm step (warm-started, or from the placement with --cold), both measured here at the
start after compilation.  --cold closes every design from the placement, so that the
objective is a function of (r, a, b) alone; warm starts are about 3x cheaper but can follow
a branch of closed states the open valve does not reach, so each method's value then
depends on its path.  The check at the end closes both final designs from the placement.
Prints a table and the ratio of forward-solve equivalents each method needed to reach
Nelder-Mead's final objective.
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

from optimize import Evaluator, Objective, default_scene, optimize_template


NAME = "L-BFGS + adjoint"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--h", type=float, default=1.5)
    ap.add_argument("--maxfev", type=int, default=150)
    ap.add_argument("--gtol", type=float, default=1e-5,
                    help="gradient loops: stop at this projected gradient norm (objective / mm)")
    ap.add_argument("--ftol", type=float, default=1e-8,
                    help="gradient loops: stop when an iteration decreases f by less than this")
    ap.add_argument("--max-iter", type=int, default=60)
    ap.add_argument("--cold", action="store_true",
                    help="close every design from the placement (no warm starts): the "
                         "objective is then a function of (r, a, b) alone")
    args = ap.parse_args(argv)
    scene = default_scene().replace(h=args.h)
    obj = Objective(area_ref=scene.template().area)
    start = np.array([scene.r, scene.a, scene.b])
    ev = Evaluator(scene, obj, warm_start=not args.cold)
    t0 = time.perf_counter()
    res = optimize_template(scene, obj, evaluator=ev, figures=False, gtol=args.gtol,
                            ftol=args.ftol, max_iter=args.max_iter,
                            warm_start=not args.cold,
                            verify=False)     # the path check is printed below
    wall = time.perf_counter() - t0
    # cost of a gradient in forward closures, at the start (compiled by now): a closure
    # from the placement, one after a 1e-3 mm step (warm unless --cold), and a gradient
    # (the forward evaluations already hold the objective's partials at fixed states)
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
    tc, tf, tg = min(tc), min(tf), min(tg)
    ratio = tg / tf
    eq = [r["forward"] + ratio * r["gradient"] for r in res.records]
    # Nelder-Mead on the same objective (infeasible or non-converged: +inf)
    ev2 = Evaluator(scene, obj, warm_start=not args.cold)
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
    n_nm = int(np.argmax(best <= f_nm * (1 + 1e-9))) + 1
    print(f"benchmark root, h = {args.h} mm, StVK, 80 mmHg, default targets "
          f"(h_c >= 4, h = 8, size weight 0.1), rtol 1e-6; gradient loops gtol {args.gtol:g}, "
          f"ftol {args.ftol:g}; closures "
          + ("from the placement (--cold)" if args.cold else "warm-started"))
    print(f"{NAME}: one gradient = {tg:.3f} s = {tg / tc:.2f} cold closures ({tc:.3f} s, "
          f"from the placement) = {ratio:.2f} {'cold' if args.cold else 'warm'} closures "
          f"after a 1e-3 mm step ({tf:.3f} s); counted as {ratio:.2f} forward solves")
    print("| method | iterations | forward | gradients | forward equivalents | wall s "
          "(incl. compile) | final objective | r | a | b |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    r = res.records[-1]
    print(f"| {NAME} | {r['iteration']} | {res.counts['forward']} | {res.counts['gradient']} "
          f"| {eq[-1]:.1f} | {wall:.1f} ({res.compile_s:.1f}) | {res.value:.6f} | "
          f"{r['r']:.3f} | {r['a']:.3f} | {r['b']:.3f} |")
    print(f"| Nelder-Mead | {nm.nit} | {nm.nfev} | 0 | {nm.nfev} | {t_nm:.1f} | {f_nm:.6f} | "
          f"{nm.x[0]:.3f} | {nm.x[1]:.3f} | {nm.x[2]:.3f} |")
    hit = [q for q, r in zip(eq, res.records) if r["objective"] <= f_nm * (1 + 1e-9)]
    if hit:
        print(f"to reach Nelder-Mead's final objective {f_nm:.6f}: {NAME} {hit[0]:.1f} "
              f"forward equivalents, Nelder-Mead {n_nm}: ratio {n_nm / hit[0]:.1f}x "
              f"(target >= 3x)")
    else:
        print(f"{NAME} did not reach Nelder-Mead's final objective {f_nm:.6f} "
              f"(its best {res.value:.6f})")
        f_lb = res.value
        if np.any(best <= f_lb * (1 + 1e-9)):
            n_lb = int(np.argmax(best <= f_lb * (1 + 1e-9))) + 1
            q = next(q for q, r in zip(eq, res.records) if r["objective"] <= f_lb * (1 + 1e-9))
            print(f"  to reach its final objective {f_lb:.6f}: {q:.1f} forward "
                  f"equivalents, Nelder-Mead {n_lb}: ratio {n_lb / q:.1f}x")
    print(f"stopped: {NAME}: {res.reason}")
    print(f"stopped: Nelder-Mead: {nm.message}")
    # the whole race: forward equivalents each needed to come within x % of the best
    # objective either found
    f_best = min(f_nm, res.value)
    lb = np.array([r["objective"] for r in res.records])
    print(f"| within x % of the best objective ({f_best:.6f}) | {NAME} fwd. eq. | ratio | "
          "Nelder-Mead |")
    print("|---|---|---|---|")
    for pct in (50, 10, 2, 1, 0.5, 0.2, 0.1, 0.05):
        lvl = f_best * (1 + pct / 100)
        b = int(np.argmax(best <= lvl)) + 1 if np.any(best <= lvl) else None
        a = float(np.asarray(eq)[np.argmax(lb <= lvl)]) if np.any(lb <= lvl) else None
        print(f"| {pct:g} | {'-' if a is None else f'{a:.1f}'} | "
              f"{f'{b / a:.1f}x' if a and b else '-'} | {'-' if b is None else b} |")
    # path dependence: the final design, and the first with which the run reached
    # Nelder-Mead's final objective, closed from the run's final state, the start
    # template's closed state, Nelder-Mead's final state and the placement
    designs = [("final", res.rab)]
    first = next((r for r in res.records if r["objective"] <= f_nm * (1 + 1e-9)), None)
    if first is not None and first is not res.records[-1]:
        designs.append((f"iteration {first['iteration']}",
                        np.array([first["r"], first["a"], first["b"]])))
    ev.warm_start = True        # --cold: the check itself must use the warm starts
    own_nm = last[0] if last[0] is not None and last[0].converged else None
    designs.append(("Nelder-Mead's final", np.asarray(nm.x)))
    placed = {}
    for label, rab in designs:
        mine = label.startswith("Nelder")
        own = own_nm if mine else ev.forward(rab, res.evaluation)
        vals = []
        for seed in (own, ev.forward(start), ev.forward(np.asarray(nm.x)), None):
            e = ev.forward(rab, seed if seed is None or seed.converged else None)
            vals.append(e.value if e.converged else float("nan"))
        placed[label] = vals[-1]
        where = ", ".join(f"{v:.3f}" for v in rab)
        who = label if mine else f"{NAME}'s {label}"
        print(f"objective at {who} design "
              f"({where}), closed from the run's final state, the start's, Nelder-Mead's "
              f"final state and the placement: {', '.join(f'{v:.6f}' for v in vals)} "
              f"(spread {np.nanmax(vals) - np.nanmin(vals):.1e})")
    # the two final designs on the objective of (r, a, b) alone: closed from the placement
    f_lb0, f_nm0 = placed["final"], placed["Nelder-Mead's final"]
    print(f"final designs closed from the placement (the objective of (r, a, b) alone): "
          f"{NAME} {f_lb0:.6f} (its run: {res.value:.6f}), Nelder-Mead {f_nm0:.6f} (its "
          f"run: {f_nm:.6f}); lower: {NAME if f_lb0 <= f_nm0 else 'Nelder-Mead'}")
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    with open(out / f"optimize_history{'_cold' if args.cold else ''}.csv", "w") as fh:
        fh.write("method,forward_equivalents,objective\n")
        for q, r in zip(eq, res.records):
            fh.write(f"lbfgs,{q:.3f},{r['objective']:.9g}\n")
        for i, v in enumerate(hist):
            fh.write(f"nelder-mead,{i + 1},{v:.9g}\n")


if __name__ == "__main__":
    main()
