"""Benchmark valve closure at 80 mmHg: residual reached, steps and wall time per model.

    python benchmarks/closure.py [--h 2.0] [--steps 20000] [--models stvk,gent]

Builds the benchmark valve (`Scene()` with the given h), starts from the harmonic
placement and runs the chosen solver with the scene's contact (smooth, one-sided, soft
minimum) and bending.  It prints what
the solve reached, converged or not; it is the diagnostic for issue 3's closure target.
"""
from __future__ import annotations

import argparse
import time

import jax
import numpy as np

import jaxvalve  # noqa: F401  (float64)
from jaxvalve import valve as V
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.scene import Scene


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=2.0)
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--solver", default="fire", choices=["fire", "newton", "paper"])
    ap.add_argument("--models", default="mass-spring,stvk,neo-hookean,gent")
    ap.add_argument("--bending", type=float, default=1.0,
                    help="bending stiffness as a multiple of the plate modulus (default 1; "
                    "0 = pure membrane)")
    args = ap.parse_args(argv)
    print(f"{'model':12s} {'tris':>6s} {'result':>18s} {'steps':>7s} {'residual':>9s} "
          f"{'first s':>8s} {'again s':>8s}")
    for model in args.models.split(","):
        sc = Scene(model=model, h=args.h, solver=args.solver, max_steps=args.steps,
                   bending=args.bending)
        valve = V.build_valve(sc.load_root(), mesh_leaflet(sc.template(), sc.h))
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            sol = V.close(valve, sc.material(), sc.pressure, solver=sc.make_solver(),
                          contact=sc.contact_law(), throw=False,
                          bending=sc.bending_law())
            jax.block_until_ready(sol.x)
            times.append(time.perf_counter() - t0)
        from jaxvalve.solvers import RESULTS
        print(f"{model:12s} {len(valve.triangles):6d} {RESULTS(int(sol.result)).name:>18s} "
              f"{int(sol.stats.steps):7d} {float(sol.stats.residual):9.2e} {times[0]:8.2f} "
              f"{times[1]:8.2f}", flush=True)
        assert np.all(np.isfinite(np.asarray(sol.x)))


if __name__ == "__main__":
    main()
