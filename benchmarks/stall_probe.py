"""Why a closure stalls: the force's continuity at the state where FIRE stopped.

Closes each cell of the paper's Table 4 (mass-spring E1 x E2, E3 = 1.2 MPa, benchmark
root and template) with the default path (one-sided soft-min penalty, FIRE), and where
the 80 mmHg closure did not converge, probes the state it stopped at (`jaxvalve.solvers.stall`,
which `simulate` also runs on a closure stopped at its step cap): each node moves along
the residual force by ``t`` times that node's share (the node with the largest force
moves t mm), and the change of each force term (elastic, bending, contact) is printed
against the residual force |F|.  A change far above (stiffness x t) at
t = 1e-7 mm is a jump: the force is discontinuous there, and no solver can bring the
residual below the jump.  Also printed: the node with the largest contact jump and
whether it lies behind the face of another leaflet's nearest triangle (the one-sided
law's side) for the node where the contact force changed most, the smallest triangle
area and the sharpest fold.

    python benchmarks/stall_probe.py [--h 1.5] [--t 1e-7] [--max-steps 50000]
        [--out benchmarks/results/stall_probe.txt]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax.numpy as jnp  # noqa: E402

from closure_speed import Tee  # noqa: E402  (this folder is on the path of a script)
from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.mechanics.bending import hinges  # noqa: E402
from jaxvalve.cli.sweep import TABLE4_E1, TABLE4_E2, TABLE4_E3  # noqa: E402
from jaxvalve.contact.geometry import point_triangle_distance_soa  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.solvers.stall import probe  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402


def nearest_side(valve, x, node):
    """(distance mm, True if behind the face) of ``node`` to the nearest triangle of each
    other leaflet, by brute force."""
    tri = np.asarray(valve.problem.triangles)
    body = np.asarray(valve.problem.body)
    out = []
    for b in sorted(set(body.tolist()) - {int(body[node])}):
        ts = tri[body[tri[:, 0]] == b]
        p = tuple(np.full(len(ts), x[node, k]) for k in range(3))
        abc = [tuple(x[ts[:, j], k] for k in range(3)) for j in range(3)]
        d, _, _, side = point_triangle_distance_soa(p, *abc, side=True)
        i = int(np.argmin(np.asarray(d)))
        out.append((float(np.asarray(d)[i]), bool(np.asarray(side)[i] < 0)))
    return out


def geometry(valve, x):
    """(smallest triangle area / median, sharpest fold between neighbours in degrees)."""
    tri = np.asarray(valve.problem.triangles)
    N = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    area = 0.5 * np.linalg.norm(N, axis=1)
    n = N / np.maximum(np.linalg.norm(N, axis=1), 1e-300)[:, None]
    hg = hinges(tri)
    cos = np.clip(np.sum(n[hg[:, 4]] * n[hg[:, 5]], 1), -1.0, 1.0)
    return area.min() / np.median(area), float(np.degrees(np.arccos(cos)).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--t", type=float, default=1e-7, help="probe move of the largest node, mm")
    ap.add_argument("--max-steps", type=int, default=50_000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    say = Tee()
    say(f"Table 4 at 80 mmHg, default path (one-sided soft-min penalty, FIRE), h = {args.h} "
        f"mm, probe t = {args.t:g} mm; {platform_summary()}")
    say("| E1 MPa | E2 MPa | result 80 | residual | abs F N | jump elastic N | jump bending N "
        "| jump contact N | contact node: gap mm, behind? | min area / median | max fold deg "
        "| wall s |")
    say("|---|---|---|---|---|---|---|---|---|---|---|---|")
    valve = None
    for e1 in TABLE4_E1:
        for e2 in TABLE4_E2:
            sc = Scene(model="mass-spring", E1=e1, E2=e2, E3=TABLE4_E3, h=args.h,
                       max_steps=args.max_steps)
            valve = build_scene_valve(sc) if valve is None else valve
            t0 = time.perf_counter()
            res = simulate(sc, valve=valve, throw=False)
            wall = time.perf_counter() - t0
            s80 = res.solves[-1]
            x = np.asarray(res.x)
            amin, fold = geometry(valve, x)
            row = f"| {e1:g} | {e2:g} | {s80.result} | {s80.residual:.2e} "
            if s80.converged:
                say(row + f"| | | | | | {amin:.2f} | {fold:.0f} | {wall:.0f} |")
                continue
            params = valve.params(sc.material(), sc.pressure, sc.contact_law(), sc.thickness,
                                  0.0, sc.bending_law())
            rep = probe(valve.problem, params, jnp.asarray(x), skin=valve.skin, step=args.t)
            sides = ", ".join(f"{d:.3f} {'behind' if b else 'front'}"
                              for d, b in nearest_side(valve, x, rep.node))
            say(row + f"| {rep.force:.2e} | {rep.jumps['elastic']:.1e} "
                f"| {rep.jumps['bending']:.1e} | {rep.jumps['contact']:.1e} "
                f"| node {rep.node}: {sides} | {amin:.2f} | {fold:.0f} | {wall:.0f} |")
    say.write(args.out)


if __name__ == "__main__":
    main()
