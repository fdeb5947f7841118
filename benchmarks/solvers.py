"""Solver benchmark: the paper's Algorithm 2.1 against FIRE and Newton-Krylov.

A clamped circular membrane (R = 5 mm, H = 0.3 mm, StVK E = 1 MPa, nu = 0.45) of about 4000
triangles under a follower pressure of 80 mmHg.  Every solver runs to the same relative
force residual (default 1e-6); Algorithm 2.1 is also run to its own stopping rule.  Prints
iterations, ms per iteration, wall time after compilation, compile time and the speed-up
of each solver over Algorithm 2.1, all measured in one run.

    python benchmarks/solvers.py [--rings 26] [--rtol 1e-6] [--repeat 3]
"""
from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen  # noqa: E402
from jaxvalve.mechanics.materials import StVenantKirchhoff  # noqa: E402
from jaxvalve.mechanics.problem import Params, make_problem, mmhg  # noqa: E402
from jaxvalve.solvers import FIRE, FixedPoint, NewtonKrylov  # noqa: E402


def timed(prob, params, x0, solver, repeat):
    t0 = time.perf_counter()
    sol = equilibrium.solve(prob, params, x0, solver, throw=False)
    sol.x.block_until_ready()
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        sol = equilibrium.solve(prob, params, x0, solver, throw=False)
        sol.x.block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return sol, best, max(first - best, 0.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rings", type=int, default=26, help="disk rings (6 n^2 triangles)")
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    p, t, b = meshgen.disk(5.0, a.rings)
    prob, ref = make_problem(p, t, fixed=b)
    params = Params(ref=ref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.3,
                    pressure=mmhg(80.0))
    x0 = jnp.asarray(meshgen.lift(p))
    print(f"clamped disk: {len(t)} triangles, {int(prob.free.sum())} free nodes, "
          f"StVK E=1 MPa nu=0.45 H=0.3 mm, P=80 mmHg, target residual {a.rtol:g}, "
          f"{jax.device_count()} {jax.devices()[0].platform} device(s)")
    runs = [("Alg 2.1 (paper stop)", FixedPoint(max_steps=500_000)),
            ("Alg 2.1", FixedPoint(rtol=a.rtol, max_steps=500_000)),
            ("FIRE", FIRE(rtol=a.rtol)),
            ("Newton-Krylov", NewtonKrylov(rtol=a.rtol))]
    rows = []
    for name, solver in runs:
        sol, wall, comp = timed(prob, params, x0, solver, a.repeat if "Alg" not in name else 1)
        rows.append((name, sol, wall, comp))
    ref_wall = rows[1][2]
    zc = float(rows[-1][1].x[0, 2])
    print(f"{'solver':22s} {'conv':>5s} {'iters':>7s} {'Hv':>5s} {'ms/iter':>8s} {'wall s':>8s} "
          f"{'compile s':>9s} {'residual':>9s} {'w0 err':>8s} {'speed-up':>8s}")
    for name, sol, wall, comp in rows:
        it = int(sol.stats.steps)
        print(f"{name:22s} {str(sol.converged):>5s} {it:7d} {int(sol.stats.hvps):5d} "
              f"{1e3 * wall / max(it, 1):8.3f} {wall:8.3f} {comp:9.2f} "
              f"{float(sol.stats.residual):9.2e} {abs(float(sol.x[0, 2]) - zc):8.1e} "
              f"{ref_wall / wall:8.1f}")
    print(f"Newton-Krylov vs Alg 2.1 at residual {a.rtol:g}: {ref_wall / rows[-1][2]:.1f}x faster; "
          f"forward solve {rows[-1][2]:.3f} s after compilation")


if __name__ == "__main__":
    main()
