"""FIRE's patience (`jaxvalve.solvers.FIRE`): what stopping a stalled FIRE solve early
saves, side by side in one process.

Each scene is closed twice, with FIRE's default patience and with patience 0 (FIRE runs
to its step cap: the baseline).  On the benchmark valve nothing stalls, and both runs must
be identical.  On soft valves of the paper's Table 4 FIRE on the smooth law stalls at 80
mmHg; they are closed here without the fallback (``fallback=False``), so that the table
shows the FIRE attempt alone: on the default path the barrier fallback then closes the
valve from the 3 mmHg state, which patience does not change, so the time a stalled
attempt saves here is what it saves there.  Prints, per scene and run: whether it
converged, the 80 mmHg result, its steps and residual, the solve time after compilation
(both loads), and the speed-up (the baseline's time over the patient run's).

With ``--batch`` the nine Table 4 valves are closed instead as one batch
(`simulate_batch`, no fallback), whose vectorised loop (the GPU default) runs until its
last member stops: one stalled member there holds the whole batch to its cap.  Prints the
batch's solve time (after compilation) under both patiences and each member's outcome.

    python benchmarks/fire_patience.py [--h 1.5] [--out benchmarks/results/fire_patience.txt]
    python benchmarks/fire_patience.py --batch [--h 1.5] [--out ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.batch import simulate_batch  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.solvers import FIRE  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402
from closure_speed import Tee  # noqa: E402  (this folder is on the path of a script)

SCENES = (("benchmark valve (stvk)", dict()),) + tuple(
    (f"Table 4 E1 = {e1:g}, E2 = {e2:g} MPa, no fallback",
     dict(model="mass-spring", E1=e1, E2=e2, E3=1.2, fallback=False))
    for e1, e2 in ((0.106, 0.3), (0.18, 0.7), (0.05, 0.569)))


TABLE4 = dict(E1=[0.05, 0.05, 0.05, 0.106, 0.106, 0.106, 0.18, 0.18, 0.18],
              E2=[0.3, 0.569, 0.7] * 3)


def run(scene, valve, patience, batch=None):
    """simulate(scene), or simulate_batch(scene, batch), with FIRE's patience set
    (`Scene.make_solver` wrapped)."""
    make = Scene.make_solver

    def make_solver(self):
        s = make(self)
        return dataclasses.replace(s, patience=patience) if isinstance(s, FIRE) else s
    Scene.make_solver = make_solver
    try:
        if batch is not None:
            return simulate_batch(scene, batch, valve=valve, throw=False)
        return simulate(scene, valve=valve, throw=False)
    finally:
        Scene.make_solver = make


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--out", default=None)
    ap.add_argument("--batch", action="store_true",
                    help="the nine Table 4 valves as one batch (simulate_batch)")
    args = ap.parse_args(argv)
    say = Tee()
    default = FIRE().patience
    if args.batch:
        return batch_main(args, say, default)
    say(f"FIRE's patience, h = {args.h} mm; {platform_summary()}")
    say("| scene | patience | converged | 80 mmHg | steps | residual | solve s |")
    say("|---|---|---|---|---|---|---|")
    summary = []
    for name, kw in SCENES:
        sc = Scene(h=args.h, **kw)
        valve = build_scene_valve(sc)
        out = {}
        for patience in (0, default):
            res = run(sc, valve, patience)
            s3, s80 = res.solves
            t = s3.solve_s + s80.solve_s
            out[patience] = (res, t)
            say(f"| {name} | {patience} | {'yes' if res.converged else 'no'} | {s80.result} "
                f"| {s80.steps} | {s80.residual:.2e} | {t:.2f} |")
        (r0, t0), (r1, t1) = out[0], out[default]
        dx = float(np.max(np.abs(np.asarray(r0.x) - np.asarray(r1.x))))
        summary.append(f"{name}: speed-up {t0 / t1:.2f}x (patience 0: {t0:.2f} s, "
                       f"patience {default}: {t1:.2f} s after compilation); the states "
                       f"at 80 mmHg differ by at most {dx:.2e} mm")
    say.finish(summary, args.out)


def batch_main(args, say, default):
    """The Table 4 grid as one batch, without fallback, under patience 0 and the default."""
    sc = Scene(h=args.h, model="mass-spring", E1=0.05, E2=0.3, E3=1.2, fallback=False)
    valve = build_scene_valve(sc)
    say(f"FIRE's patience on a batch: the 9 Table 4 valves (E3 = 1.2 MPa), no fallback, "
        f"h = {args.h} mm; {platform_summary()}")
    times = {}
    for patience in (0, default):       # "solve" excludes JAX's compile time
        res = run(sc, valve, patience, TABLE4)
        times[patience] = res.timings["solve"]
        say(f"patience {patience}: vectorised {res.vectorized}, solve {res.timings['solve']:.2f} s "
            f"after compilation ({res.timings['compile']:.1f} s compile), "
            f"{sum(m.converged for m in res)}/{len(res)} converged")
        say("| E1 | E2 | 3 mmHg | 80 mmHg | steps at 80 | residual at 80 |")
        say("|---|---|---|---|---|---|")
        for m in res:
            s3, s80 = m.solves
            say(f"| {m.material.E1:g} | {m.material.E2:g} | {s3.result} | {s80.result} | "
                f"{s80.steps} | {s80.residual:.2e} |")
    t0, t1 = times[0], times[default]
    say.finish([f"Table 4 batch: speed-up {t0 / t1:.2f}x (patience 0: {t0:.2f} s, patience "
                f"{default}: {t1:.2f} s after compilation)"], args.out)


if __name__ == "__main__":
    main()
