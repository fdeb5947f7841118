"""The broad phase by size class (`jaxvalve.geometry.broad_phase.ball_pairs`) against one
k-d tree query with the largest radius, on the barrier contact's two queries.

    python benchmarks/broad_phase.py [--h 2.0] [--repeats 20]

One process, the benchmark valve's placement (h mm), and the same with a runaway-like
blister: one free node of the first leaflet moved 15 mm out along the root's radius, so
that six triangles and their edges stretch to about 15 mm (a leaflet running away past
its inflation limit stretched edges to 10-15 mm on a 2 mm mesh).  Per state, the two
queries of `jaxvalve.contact.ipc_pairs.build_pairs` at the line search's widest cutoff
(d_hat + 2 dx_max = 2.2 mm): nodes against the triangles' bounding balls, and edges
against edges (their balls about the midpoints).  The baseline lists every pair within
cutoff + the largest radii (what `build_pairs` did before); each list is cut to the
pairs whose balls come within the cutoff (the first of build_pairs' tests on every
candidate), and the two must be equal.  Prints the candidates listed, the median time of
listing and cutting (alternating, ``--repeats`` times each, twice) and the ratio.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from jaxvalve.geometry.broad_phase import ball_pairs  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402

CUTOFF = 2.2     # mm: d_hat 0.2 + 2 x dx_max 1.0, the line search's widest


def _one_radius(ca, ra, cb, rb, gap):
    """The baseline: one query with gap + the largest radii (pairs i < j without b)."""
    if cb is None:
        p = cKDTree(ca).query_pairs(gap + 2 * ra.max(), output_type="ndarray")
        return p.reshape(-1, 2).astype(np.int64)
    m = cKDTree(ca).sparse_distance_matrix(cKDTree(cb), gap + ra.max() + rb.max(),
                                           output_type="ndarray")
    return np.column_stack([m["i"], m["j"]]).astype(np.int64)


def _within(p, ca, ra, cb, rb, gap):
    d = ca[p[:, 0]] - cb[p[:, 1]]
    keep = np.einsum("ij,ij->i", d, d) <= (gap + ra[p[:, 0]] + rb[p[:, 1]]) ** 2
    q = p[keep]
    return q[np.lexsort((q[:, 1], q[:, 0]))]


def _queries(x, tri, edges):
    """[(name, ca, ra, cb, rb)] of build_pairs' two queries at the state x (N, 3)."""
    xt = x[tri]
    cen = xt.mean(axis=1)
    rad = np.sqrt(np.max(np.sum((xt - cen[:, None]) ** 2, axis=2), axis=1))
    mid = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    half = 0.5 * np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
    return [("node-triangle", x, np.zeros(len(x)), cen, rad),
            ("edge-edge", mid, half, None, None)]


def _median_time(f, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    if not (args.h > 0 and args.repeats > 0):
        ap.error(f"--h must be > 0 mm and --repeats a positive count; got {args.h}, "
                 f"{args.repeats}")
    print(f"# python benchmarks/broad_phase.py --h {args.h:g} --repeats {args.repeats}")
    print(f"# {platform_summary()}")
    valve = build_scene_valve(Scene(h=args.h, contact="barrier", solver="newton"))
    topo = valve.barrier_topology
    x0 = np.asarray(valve.x_start, float)
    free = ~np.asarray(valve.problem.fixed)
    leaf0 = np.flatnonzero(free & (topo.body == 0))
    node = leaf0[np.argmin(np.linalg.norm(x0[leaf0] - x0[leaf0].mean(axis=0), axis=1))]
    out = np.array([x0[node, 0], x0[node, 1], 0.0])
    blister = x0.copy()
    blister[node] += 15.0 * out / np.linalg.norm(out)
    print(f"benchmark valve, h = {args.h:g} mm: {len(x0)} nodes, {len(topo.triangles)} "
          f"triangles, {len(topo.edges)} edges; cutoff {CUTOFF:g} mm; median of "
          f"{args.repeats} timings each")
    print(f"{'state':10s} {'query':14s} {'pairs':>7} {'listed: one radius':>19} "
          f"{'by class':>9} {'ms: one radius':>15} {'by class':>9} {'speed-up':>9} "
          f"{'same':>5}")
    for state, x in (("placement", x0), ("blister", blister)):
        for name, ca, ra, cb, rb in _queries(x, topo.triangles, topo.edges):
            t_old = t_new = 0.0
            cb_, rb_ = (ca, ra) if cb is None else (cb, rb)
            n_old, n_new = (len(f(ca, ra, cb, rb, CUTOFF)) for f in (_one_radius, ball_pairs))

            def listed_and_cut(f):
                return _within(f(ca, ra, cb, rb, CUTOFF), ca, ra, cb_, rb_, CUTOFF)
            for _ in range(2):     # alternate the two, twice
                a, w_old = _median_time(lambda: listed_and_cut(_one_radius), args.repeats)
                b, w_new = _median_time(lambda: listed_and_cut(ball_pairs), args.repeats)
                t_old, t_new = t_old + a, t_new + b
            same = bool(np.array_equal(w_old, w_new))
            print(f"{state:10s} {name:14s} {len(w_new):7d} {n_old:19d} {n_new:9d} "
                  f"{500 * t_old:15.2f} {500 * t_new:9.2f} {t_old / t_new:8.2f}x "
                  f"{str(same):>5}")


if __name__ == "__main__":
    main()
