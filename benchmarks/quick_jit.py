"""Compile and run time of the optimiser's short-running programs: plain `jax.jit` against
`jaxvalve.quick_jit` (XLA's older CPU fusion emitters).

    python benchmarks/quick_jit.py [--h 0.88] [--runs 5]

One process, the compilation cache off.  The start template of `jaxvalve optimize` is
closed once (FIRE, rtol 1e-6); then each program is compiled both ways from the same
lowered module and run ``--runs`` times on the closed state:

* metrics+partials: `Evaluator._direct_jit`, the smooth metrics, the objective and its
  partial derivatives (once per forward evaluation);
* residual_vjp: `adjoint.residual_vjp`, the adjoint's K^T product (~50 per gradient);
* blocks: `tangent._blocks`, the assembled stiffness's element blocks (once per gradient);
* design_pullback: the template's part of the gradient (once per gradient); it gains
  nothing, so the optimiser compiles it with the plain `jax.jit`.

Prints compile s, run ms (median) and the largest difference of the outputs (NaN entries,
if any, must agree), then the
compile-time sums and the run time one optimisation would add (calls per program as in
the default run: 6 forward evaluations, 5 gradients with ~50 K^T products each).
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

# benchmarks/optimize.py would shadow the optimize package
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from jaxvalve.solvers import tangent  # noqa: E402

from jaxvalve.solvers import adjoint
from jaxvalve.quick_jit import QUICK_CPU_OPTIONS  # noqa: E402
from optimize import Objective  # noqa: E402
from optimize.evaluate import Evaluator  # noqa: E402

CALLS = {"metrics+partials": 6, "residual_vjp": 5 * 50, "blocks": 5, "design_pullback": 5}


def measure(fun, args, runs):
    rows = {}
    for kind, opts in (("plain", None), ("quick", QUICK_CPU_OPTIONS)):
        lowered = jax.jit(fun).lower(*args)
        t0 = time.perf_counter()
        c = lowered.compile(opts) if opts else lowered.compile()
        comp = time.perf_counter() - t0
        out = jax.block_until_ready(c(*args))
        ts = []
        for _ in range(runs):
            t0 = time.perf_counter()
            jax.block_until_ready(c(*args))
            ts.append(time.perf_counter() - t0)
        flat = [np.ravel(np.asarray(v)) for v in jax.tree_util.tree_leaves(out)]
        rows[kind] = (comp, statistics.median(ts), np.concatenate(flat))
    p, q = rows["plain"][2], rows["quick"][2]
    if not np.array_equal(np.isnan(p), np.isnan(q)):
        raise SystemExit("the two compilations give NaN in different places")
    diff = float(np.max(np.abs(p - q), initial=0.0, where=~np.isnan(p)))
    return rows["plain"][:2], rows["quick"][:2], diff


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=0.88)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args(argv)
    sc = Scene(h=a.h, rtol=1e-6)
    ev = Evaluator(sc, dataclasses.replace(Objective(), area_ref=sc.template().area))
    rab = np.array([sc.r, sc.a, sc.b])
    e = ev.forward(rab)
    if not e.converged:
        raise SystemExit(f"the start does not close: {e.reason}")
    x0, sol = e.states["closed"]
    params = ev.base["closed"].replace(ref=ev._ref_jit(ev.theta(rab)))
    params = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), params)
    prob = ev.valve.problem
    mu = jnp.asarray(np.random.default_rng(0).normal(size=sol.x.shape))
    hn, ht = tangent._hinge_args(prob)
    cases = {
        "metrics+partials": (ev._direct_jit._plain,
                             (jnp.asarray(rab), {"closed": sol.x}, e.states, e.plans,
                              jnp.asarray(ev.area_ref))),
        "residual_vjp": (adjoint._residual_vjp._plain, (sol.x, prob, params, sol.nbrs, mu)),
        "blocks": (tangent._blocks._plain, (sol.x, prob, params, sol.nbrs, hn, ht)),
        "design_pullback": (ev._design_pullback,
                            (jnp.asarray(rab), sol.x, params.ref, mu)),
    }
    print(f"h = {a.h} mm, {prob.n_nodes} nodes; plain jax.jit against quick_jit "
          f"({QUICK_CPU_OPTIONS}); run: median of {a.runs}")
    print(f"{'program':18s} {'compile s':>9s} {'quick':>7s} {'ratio':>6s} {'run ms':>8s} "
          f"{'quick':>8s} {'max |diff|':>10s}")
    tot = np.zeros(4)
    for name, (fun, args) in cases.items():
        (cp, rp), (cq, rq), d = measure(fun, args, a.runs)
        tot += [cp, cq, CALLS[name] * rp, CALLS[name] * rq]
        print(f"{name:18s} {cp:9.2f} {cq:7.2f} {cp / cq:6.2f} {1e3 * rp:8.2f} "
              f"{1e3 * rq:8.2f} {d:10.1e}")
    print(f"compile: {tot[0]:.2f} s plain, {tot[1]:.2f} s quick ({tot[0] / tot[1]:.2f}x); "
          f"run time of one default optimisation's calls: {tot[2]:.2f} s plain, "
          f"{tot[3]:.2f} s quick; net saving {tot[0] + tot[2] - tot[1] - tot[3]:.2f} s")


if __name__ == "__main__":
    main()
