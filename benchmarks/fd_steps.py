"""Finite differences in E at shrinking steps against the adjoint, with the contact set.

    python benchmarks/fd_steps.py [--point 12.5 7.5 15.5] [--h 1.5] [--rtol 1e-10]
        [--steps 3e-2,1e-2,1e-3,1e-4] [--metrics h_E,h_c,h_CC] [--contact barrier]

Closes the benchmark valve at one template (3 and 80 mmHg, from the placement, FIRE to
--rtol), takes d metric / dE by the adjoint (`Evaluator.sensitivities`), and for each
relative step s closes it again at E (1 + s) and E (1 - s), warm-started, and prints the
central, forward and backward differences next to the adjoint, and how many nodes
entered or left the contact layer (nearest other leaflet closer than g0 = 0.2 mm) at each
side.  The smooth contact energy is C1: its stiffness jumps by k where a node crosses g0,
so a metric is only piecewise smooth in E, and a step that moves nodes across g0 measures
a chord, not the derivative.  With ``--contact barrier`` (projected Newton on the IPC
barrier, d_hat = 0.2 mm) the contact energy is C2 where a pair enters its range and C1
only where a pair's closest feature changes type, and the adjoint is the barrier's
(`jaxvalve.solvers.adjoint`, the exact Jacobian's LU).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

# this folder holds optimize.py, named like the `optimize` package: off the import path
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import numpy as np  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from jaxvalve.coaptation.gaps import gap_field  # noqa: E402
from optimize import Evaluator, Objective, Target  # noqa: E402

G0 = 0.2  # mm: SmoothContact().gap, and the barrier's d_hat


def in_contact(ev, e):
    """{load: (N,) bool} nodes whose nearest other leaflet is closer than G0."""
    v = ev.valve
    return {load: np.min(gap_field(np.asarray(sol.x), v.triangles, v.body, cutoff=1.0),
                         axis=1) < G0
            for load, (_, sol) in e.states.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--point", type=float, nargs=3, default=(12.5, 7.5, 15.5),
                    metavar=("R", "A", "B"))
    ap.add_argument("--h", type=float, default=1.5)
    ap.add_argument("--rtol", type=float, default=1e-10)
    ap.add_argument("--max-steps", type=int, default=200_000)
    ap.add_argument("--steps", default="3e-2,1e-2,1e-3,1e-4")
    ap.add_argument("--metrics", default="h_E,h_c,h_CC")
    ap.add_argument("--contact", choices=("smooth", "barrier"), default="smooth",
                    help="smooth: FIRE on the smooth penalty; barrier: projected Newton")
    a = ap.parse_args(argv)
    solver = "fire" if a.contact == "smooth" else "newton"
    scene = Scene(h=a.h, rtol=a.rtol, max_steps=a.max_steps, contact=a.contact,
                  solver=solver)
    ev = Evaluator(scene, Objective(targets=(Target("h_E", lower=0.0), Target("h", lower=0.0))))
    rab = tuple(a.point)
    e0 = ev.forward(rab)
    if not e0.converged:
        print(f"the closure at {rab} did not converge: {e0.reason}")
        return 1
    sens = ev.sensitivities(e0)
    E0 = float(ev.material.E)
    c0 = in_contact(ev, e0)
    names = [m for m in a.metrics.split(",") if m]
    print(f"template {rab} mm, h = {a.h} mm, StVK E = {E0} MPa, {solver} on the "
          f"{a.contact} contact, rtol {a.rtol:g}; "
          f"nodes in contact (3, 80 mmHg): {', '.join(str(int(c.sum())) for c in c0.values())}")
    print("| step | nodes crossing g0 at +s, -s: 3; 80 mmHg | metric | adjoint | central | forward "
          "| backward | central rel. error |")
    print("|---|---|---|---|---|---|---|---|")
    for s in (float(v) for v in a.steps.split(",") if v):
        ep, em = (ev.forward(rab, e0, material=dataclasses.replace(ev.material,
                                                                  E=E0 * (1 + k * s)))
                  for k in (1, -1))
        if not (ep.converged and em.converged):
            print(f"| {s:g} | a closure did not converge: {ep.reason or em.reason} |")
            continue
        cp, cm = in_contact(ev, ep), in_contact(ev, em)
        moved = "; ".join(f"{int(np.sum(cp[l] != c0[l]))}, {int(np.sum(cm[l] != c0[l]))}"
                          for l in c0)
        for q in names:
            g = sens[q]["E"]
            c = (ep.metrics[q] - em.metrics[q]) / (2 * s * E0)
            f = (ep.metrics[q] - e0.metrics[q]) / (s * E0)
            b = (e0.metrics[q] - em.metrics[q]) / (s * E0)
            print(f"| {s:g} | {moved} | {q} | {g:.6f} | {c:.6f} | {f:.6f} | {b:.6f} | "
                  f"{abs(c - g) / abs(c):.1e} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
