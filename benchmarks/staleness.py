"""How stale the contact pair lists are when a FIRE step evaluates its force.

    python benchmarks/staleness.py [--h 1.5,0.88] [--model stvk]

`solvers.base.iterate` brings the pair lists up to date at the start of every loop
iteration; a FIRE step then moves the nodes (by at most skin / 2) and evaluates the force
at the new positions with those lists.  The Verlet list holds every pair within g0 while
no node has moved more than skin / 2 since its build, and the pruned soft-min list while
no node has moved more than margin / 4 since its own (`contact.soft_pairs`); a step that
starts just inside these bounds can end outside them.  This script closes the benchmark
valve as `simulate` does (the scene's 3 mmHg closure, then 80 mmHg from its state) with a
FIRE that also records, at every force evaluation, the largest node displacement since
each list's build, and prints how many force evaluations were past each bound, by how
much, and the steps and metrics.  A pair can only be missed when a node and a triangle
together close in by more than the skin (Verlet) or margin / 2 (pruned), so a count
above zero says such a force may have lacked a pair for that one step; the next iteration
rebuilds the list.
"""
from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import jaxvalve  # noqa: F401  (float64)
from jaxvalve import valve as V
from jaxvalve.contact.soft_pairs import SoftPairs
from jaxvalve.scene import Scene
from jaxvalve.simulation import build_scene_valve
from jaxvalve.solvers import FIRE, RESULTS

RECORD = []


def _record(*a):
    RECORD.append(tuple(float(v) for v in a))


@dataclasses.dataclass(frozen=True)
class RecordingFIRE(FIRE):
    """FIRE that reports, after each step, the displacements since the lists' builds."""

    def step(self, system, y, args, s):
        y1, s1 = super().step(system, y, args, s)
        nb = args["nbrs"]
        base = nb.base if isinstance(nb, SoftPairs) else nb
        d_v = jnp.sqrt(jnp.max(jnp.sum((y1 - base.x_build) ** 2, -1)))
        d_s = (jnp.sqrt(jnp.max(jnp.sum((y1 - nb.x_build) ** 2, -1)))
               if isinstance(nb, SoftPairs) else jnp.asarray(0.0, y.dtype))
        margin = nb.margin if isinstance(nb, SoftPairs) else jnp.asarray(jnp.inf, y.dtype)
        jax.debug.callback(_record, d_v, 0.5 * args["skin"], d_s, 0.25 * margin)
        return y1, s1


def run(h, model):
    sc = Scene(h=h, model=model)
    valve = build_scene_valve(sc)
    base = sc.make_solver()
    solver = RecordingFIRE(**{f.name: getattr(base, f.name) for f in dataclasses.fields(FIRE)})
    x = valve.x_start
    rows = []
    for p in (sc.he_pressure, sc.pressure):
        RECORD.clear()
        sol = V.close(valve, sc.material(), p, solver=solver, contact=sc.contact_law(),
                      thickness=sc.thickness, bending=sc.bending_law(), x0=x, throw=False)
        jax.block_until_ready(sol.x)
        r = np.asarray(RECORD)
        past_v = r[:, 0] > r[:, 1]
        past_s = r[:, 2] > r[:, 3]
        rows.append((h, valve.skin, p, RESULTS(int(sol.result)).name, int(sol.stats.steps),
                     len(r), int(past_v.sum()), float(r[:, 0].max()), float(r[0, 1]),
                     int(past_s.sum()), float(r[:, 2].max()), float(r[0, 3])))
        x = np.asarray(sol.x)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", default="1.5,0.88")
    ap.add_argument("--model", default="stvk")
    a = ap.parse_args(argv)
    print(f"{'h mm':>5s} {'skin':>5s} {'mmHg':>5s} {'result':>12s} {'steps':>6s} "
          f"{'forces':>6s} | {'past skin/2':>11s} {'max move':>8s} {'bound':>6s} | "
          f"{'past margin/4':>13s} {'max move':>8s} {'bound':>6s}")
    for h in (float(v) for v in a.h.split(",") if v):
        for row in run(h, a.model):
            (hh, skin, p, res, steps, n, pv, mv, bv, ps, ms, bs) = row
            print(f"{hh:5g} {skin:5.2f} {p:5g} {res:>12s} {steps:6d} {n:6d} | {pv:11d} "
                  f"{mv:8.3f} {bv:6.3f} | {ps:13d} {ms:8.3f} {bs:6.3f}", flush=True)


if __name__ == "__main__":
    main()
