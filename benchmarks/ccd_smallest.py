"""The barrier Newton's CCD step bound: every pair followed to its own bound against the
search for the smallest step alone.

    python benchmarks/ccd_smallest.py [--h 2.0] [--moves 40] [--seed 0]

`ccd.max_step` needs only the smallest safe fraction over the pairs.  Followed to its own
bound, every pair of additive CCD advances until its gap has closed by 90 % or t = 1
(``max_step(..., smallest=False)``); with ``smallest=True`` (the default) a pair stops being advanced once its safe t
reaches the smallest t of any pair that has stopped, which cannot lower the minimum.

One process: the benchmark valve (StVK, h mm) closed on the barrier path at 3 and 80 mmHg
(`jaxvalve.valve.closure.close_valve`); at each of the two closed states and at the
placement, ``--moves`` random moves of the free nodes (normal, scaled so that the largest
node move is 0.05-1 mm, the barrier Newton's range: ``dx_max`` = 1 mm) with the pair list
the line search builds for them (`build_pairs`, cutoff d_hat + 2 max |dx|).  Prints, per
state, the summed time of both variants over the moves (alternating, the per-pair variant
first), their ratio, and whether every step agreed exactly.
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

from jaxvalve import Scene  # noqa: E402
from jaxvalve.contact import ccd  # noqa: E402
from jaxvalve.contact.ipc_pairs import build_pairs  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.valve.closure import close_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=2.0)
    ap.add_argument("--moves", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not (args.h > 0 and args.moves > 0):
        ap.error(f"--h must be > 0 mm and --moves a positive count; got {args.h}, "
                 f"{args.moves}")
    print(f"# python benchmarks/ccd_smallest.py --h {args.h:g} --moves {args.moves} "
          f"--seed {args.seed}")
    print(f"# {platform_summary()}")
    sc = Scene(h=args.h, contact="barrier", solver="newton")
    valve = build_scene_valve(sc)
    solves = close_valve(valve, sc, pressures=(3.0, 80.0))
    states = [("placement", np.asarray(valve.x_start, float))]
    states += [(f"closed {ls.report.pressure:g} mmHg ({ls.report.result})",
                np.asarray(ls.x, float)) for ls in solves]
    free = ~np.asarray(valve.problem.fixed)[:, None]
    topo, dhat = valve.barrier_topology, float(sc.contact_law().dhat)
    rng = np.random.default_rng(args.seed)
    print(f"benchmark valve, h = {args.h:g} mm, {valve.problem.n_nodes} nodes; "
          f"{args.moves} random moves per state; s summed over the moves")
    print(f"{'state':34s} {'pairs':>7} {'every pair s':>13} {'smallest s':>11} "
          f"{'ratio':>6} {'same t':>7}")
    for name, x in states:
        t_all = t_min = 0.0
        same, n_pairs = True, 0
        for _ in range(args.moves):
            dx = rng.normal(size=x.shape) * free
            dx *= rng.uniform(0.05, 1.0) / np.max(np.linalg.norm(dx, axis=1))
            big = float(np.max(np.linalg.norm(dx, axis=1)))
            near = build_pairs(topo, x, dhat + 2.0 * big * 1.001 + 1e-9, dx=dx)
            n_pairs += len(near.pt) + len(near.ee)
            t0 = time.perf_counter()
            a = ccd.max_step(x, dx, near, smallest=False)
            t1 = time.perf_counter()
            b = ccd.max_step(x, dx, near)
            t2 = time.perf_counter()
            t_all, t_min = t_all + t1 - t0, t_min + t2 - t1
            same &= a == b
        print(f"{name:34s} {n_pairs // args.moves:7d} {t_all:13.3f} {t_min:11.3f} "
              f"{t_all / t_min:6.2f} {str(same):>7}")


if __name__ == "__main__":
    main()
