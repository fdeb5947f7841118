"""Closure accuracy against run time: solver tolerance sweep and mesh refinement.

    python benchmarks/accuracy.py [--h 1.5] [--meshes 2.0,1.5,1.2,0.88] [--model stvk]

1. Tolerance: the valve is closed at 3 mmHg (to 1e-8), then at 80 mmHg from there with
   FIRE at rtol = 1e-2 ... 1e-6; each row gives steps, time after compilation and the
   change of h_E(80), h_C-C, h_avr and NCCA from the 1e-8 solve.
2. Mesh: the default `simulate` at each mesh size h; metrics and times.  Differences from
   the finest mesh show the discretisation error.
"""
from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jaxvalve import Scene, simulate
from jaxvalve import valve as V
from jaxvalve.leaflet_mesh import mesh_leaflet
from jaxvalve.scene import VALVE_DT_MAX
from jaxvalve.simulation import measure
from jaxvalve.solvers import FIRE


def _close(valve, sc, p, x0, rtol):
    solver = FIRE(rtol=rtol, max_steps=200_000, dt_max=VALVE_DT_MAX)   # as `Scene`
    kw = dict(solver=solver, contact=sc.contact_law(), bending=sc.bending_law(), x0=x0,
              throw=False)
    V.close(valve, sc.material(), p, **kw)          # compile
    t0 = time.perf_counter()
    sol = V.close(valve, sc.material(), p, **kw)
    jax.block_until_ready(sol.x)
    return sol, time.perf_counter() - t0


def _row(m):
    return np.array([m.h_e, m.h_cc, m.h_avr_valve, 100 * m.ncca_valve])


def tolerance_sweep(h, model):
    sc = Scene(h=h, model=model)
    valve = V.build_valve(sc.load_root(), mesh_leaflet(sc.template(), h))
    s3, _ = _close(valve, sc, sc.he_pressure, valve.x_start, 1e-8)
    x3 = np.asarray(s3.x)
    ref, _ = _close(valve, sc, sc.pressure, x3, 1e-8)
    mref = _row(measure(valve, np.asarray(ref.x), sc.g_c))
    print(f"\nTolerance sweep, {model}, h = {h} mm ({len(valve.triangles)} triangles), 80 mmHg "
          "from the 3 mmHg state; errors vs the 1e-8 solve (mm, NCCA points)")
    print(f"{'rtol':>7s} {'steps':>6s} {'time s':>7s} {'dh_E(80)':>9s} {'dh_C-C':>8s} "
          f"{'dh_avr':>8s} {'dNCCA':>7s}")
    for rtol in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8):
        sol, t = _close(valve, sc, sc.pressure, x3, rtol)
        err = _row(measure(valve, np.asarray(sol.x), sc.g_c)) - mref
        print(f"{rtol:7.0e} {int(sol.stats.steps):6d} {t:7.2f} " +
              " ".join(f"{e:+8.4f}" for e in err) + ("" if sol.converged else "  NOT CONVERGED"),
              flush=True)


def mesh_sweep(meshes, model):
    print(f"\nMesh refinement, {model} (default simulate: 3 then 80 mmHg, rtol 1e-4)")
    print(f"{'h mm':>5s} {'tris':>5s} {'h_E':>6s} {'h_C-C':>6s} {'h_avr':>6s} {'NCCA%':>6s} "
          f"{'h':>6s} {'h_c':>6s} {'steps':>11s} {'solve s':>8s}")
    for h in meshes:
        sc = Scene(h=h, model=model)
        first = simulate(sc, throw=False)
        res = simulate(sc, throw=False, valve=first.valve)
        s = res.summary()
        print(f"{h:5.2f} {len(res.valve.leaflet.triangles):5d} {s['h_E']:6.2f} {s['h_CC']:6.2f} "
              f"{s['h_avr']:6.2f} {s['NCCA_pct']:6.1f} {s['h']:6.2f} {s['h_c']:6.2f} "
              f"{'/'.join(str(r.steps) for r in res.solves):>11s} "
              f"{sum(r.wall_s for r in res.solves):8.2f}" +
              ("" if res.converged else "  NOT CONVERGED"), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size of the tolerance sweep")
    ap.add_argument("--meshes", default="2.0,1.5,1.2,0.88")
    ap.add_argument("--model", default="stvk")
    args = ap.parse_args(argv)
    tolerance_sweep(args.h, args.model)
    mesh_sweep([float(v) for v in args.meshes.split(",")], args.model)


if __name__ == "__main__":
    main()
