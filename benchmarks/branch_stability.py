"""Stability along a soft valve's continuation path: where the branch a ramp follows folds.

Closes the stress suite's valve (template (b), h = 2 mm) at 3 mmHg as the default path
does (FIRE on the smooth law, then the barrier fallback), then solves with the barrier
Newton solver at each pressure of ``--P`` in turn, each from the last equilibrium reached
(the pressures of the default path's own ramp to 80 mmHg for StVK at 0.05 MPa).  For
each solve it prints the result, the Newton steps, the relative residual, the smallest
leaflet gap, the sharpest fold and the lowest real eigenvalue of the exact Jacobian -dF/dx
at the state reached (`barrier_newton.lowest_modes`, N/mm; the median diagonal of the
tangent is printed for scale): negative, a saddle (the valve would not rest there); near
zero, a nearly stiffness-free mode; and the share of the residual force along that mode
(|F . v| / (|F| |v|)): near 1, a solve stopped there is stuck on that mode.
``--push``: the solver's ``max_pushes`` (push off a saddle along its unstable mode and
solve on).

    python benchmarks/branch_stability.py [--model stvk] [--E 0.05] [--push 0]
        [--P 41.5 60.75 70.38 75.19 76.39 76.99 77.59 80] [--steps 300] [--out FILE]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from closure_speed import Tee  # noqa: E402  (this folder is on the path of a script)
from jaxvalve.valve import checks  # noqa: E402
from jaxvalve.valve.closure import _params  # noqa: E402
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet  # noqa: E402
from jaxvalve.scene import Scene  # noqa: E402
from jaxvalve.solvers import BarrierNewton, solve_barrier  # noqa: E402
from jaxvalve.solvers.barrier_newton import _Model, lowest_modes  # noqa: E402
from stress_suite import (HE_PRESSURE, STRESS_H, _first_stage, make_valve,  # noqa: E402
                          paper_templates)
from jaxvalve.xla_setup import platform_summary  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="stvk")
    ap.add_argument("--E", type=float, default=0.05, help="MPa")
    ap.add_argument("--P", type=float, nargs="+", help="mmHg, in turn",
                    default=[41.5, 60.75, 70.38, 75.19, 76.39, 76.99, 77.59, 80.0])
    ap.add_argument("--steps", type=int, default=300, help="Newton steps a solve")
    ap.add_argument("--push", type=int, default=0, help="BarrierNewton max_pushes")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = Tee()
    tpl = paper_templates()["b"][0]
    valve = make_valve(tpl, STRESS_H, mesh_leaflet(tpl, STRESS_H))
    scene = Scene(r=tpl.r, a=tpl.a, b=tpl.b, alpha=tpl.alpha, h=STRESS_H, model=args.model,
                  E=args.E, rtol=1e-4, max_steps=4000, pressure=max(args.P),
                  he_pressure=HE_PRESSURE)
    out(f"branch stability: {platform_summary()}; template b, h = {STRESS_H} mm, "
        f"{args.model}, E = {args.E} MPa, {args.steps} Newton steps a solve, "
        f"max_pushes {args.push}")
    t0 = time.perf_counter()
    first = _first_stage(valve, scene)
    out(f"{HE_PRESSURE:g} mmHg: {first.report.result}, residual {first.report.residual:.2e} "
        f"({time.perf_counter() - t0:.0f} s, default path)")
    if not first.converged:
        return out.finish(["the 3 mmHg closure failed: nothing to continue from"], args.out)
    barrier = scene.replace(contact="barrier", solver="newton")
    material = barrier.material()
    solver = BarrierNewton(rtol=scene.rtol, max_steps=args.steps, max_pushes=args.push)
    tri = np.asarray(valve.problem.triangles)
    x = np.asarray(first.x, np.float64)
    out("| P mmHg | result | steps | residual | min gap mm | max fold deg | lowest eig N/mm "
        "| median diag N/mm | residual share on its mode | s |")
    out("|---|---|---|---|---|---|---|---|---|---|")
    for p in args.P:
        t = time.perf_counter()
        params = _params(valve, barrier, material, p, None)
        sol, log = solve_barrier(valve.problem, params, x, solver, valve.barrier_topology)
        xs = np.asarray(sol.x)
        model = _Model(valve.problem, params, valve.barrier_topology)
        lam, v = lowest_modes(model, xs, sol.nbrs)
        _, F, _ = model.evaluate(xs, sol.nbrs)
        share = (np.nan if lam is None else
                 abs(np.sum(F * v)) / (np.linalg.norm(F) * np.linalg.norm(v)))
        diag = np.median(model.tangent(xs, sol.nbrs).diagonal())
        _, ang, _ = checks.fold_angles(tri, xs)
        out(f"| {p:g} | {sol.status} | {int(sol.stats.steps)} | "
            f"{float(sol.stats.residual):.2e} | {sol.nbrs.min_distance:.2e} | "
            f"{ang.max():.1f} | {'-' if lam is None else f'{lam:.2e}'} | {diag:.3f} | "
            f"{share:.2f} | {time.perf_counter() - t:.0f} |")
        if sol.converged:
            x = xs
    out.finish([f"total {time.perf_counter() - t0:.0f} s"], args.out)


if __name__ == "__main__":
    main()
