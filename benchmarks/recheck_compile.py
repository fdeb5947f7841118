"""Compile time of the solve's independent recheck: traced with the contact's prefix switch
against the whole pair lists.

    python benchmarks/recheck_compile.py [--h 2.0 0.88] [--pressure 3]

`equilibrium.recheck` evaluates a converged solve's residual once, in a program of its own
(`equilibrium._recheck`).  The soft-min contact is traced either as the solver's loop
traces it, a `lax.switch` over up to three prefixes of its pair list
(`contact.neighbours.bucket_sizes`), or on the whole list (`contact.neighbours.whole_lists`),
one branch.  A program that runs once only pays for the extra branches.

One process, the compilation cache off.  For each mesh size the benchmark valve is closed
once (FIRE, the default scene at ``--pressure`` mmHg; the table says whether it converged); then the recheck's residual program is
lowered both ways at the closed state, alternately, and each lowered module compiled
(``.compile()``, timed alone): the switch (as the recheck was traced before), the whole
lists, and the whole lists with `jaxvalve.quick_jit`'s older CPU fusion emitters (as
`equilibrium._recheck` compiles now), then all three again.  Prints compile seconds per
variant (the best of the two), the ratios to the switch, and the largest difference of
the residual vectors relative to the largest force.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)

import numpy as np  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from jaxvalve import valve as V  # noqa: E402
from jaxvalve.contact.neighbours import whole_lists  # noqa: E402
from jaxvalve.mechanics import assembly  # noqa: E402
from jaxvalve.quick_jit import QUICK_CPU_OPTIONS  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402


def _residual(problem, params, y, nbrs, delta):
    return assembly.residual(y, problem, params, assembly.prepare(problem, params), nbrs,
                             delta)


def measure(h: float, pressure: float) -> dict:
    sc = Scene(h=h)
    valve = build_scene_valve(sc)
    sol = V.close(valve, sc.material(), pressure, solver=sc.make_solver(),
                  contact=sc.contact_law(), thickness=sc.thickness,
                  bending=sc.bending_law(), throw=False)
    params = valve.params(sc.material(), pressure, sc.contact_law(), sc.thickness, 0.0,
                          sc.bending_law())
    args = (valve.problem, params, sol.x, sol.nbrs, jax.numpy.zeros_like(sol.x))
    out, secs = {}, {"switch": [], "whole": [], "quick": []}
    for _ in range(2):
        for name in ("switch", "whole", "quick"):
            fun = jax.jit(lambda *a: _residual(*a))    # a fresh function: no cache hit
            if name == "switch":
                lowered = fun.lower(*args)
            else:
                with whole_lists():
                    lowered = fun.lower(*args)
            t0 = time.perf_counter()
            compiled = lowered.compile(QUICK_CPU_OPTIONS if name == "quick" else None)
            secs[name].append(time.perf_counter() - t0)
            out[name] = np.asarray(compiled(*args))
    scale = float(np.max(np.abs(out["switch"])))
    diff = max(float(np.max(np.abs(out["switch"] - out[k]))) for k in ("whole", "quick"))
    diff /= max(scale, 1e-300)
    return dict(h=h, nodes=int(valve.problem.n_nodes), converged=bool(sol.converged),
                switch=min(secs["switch"]),
                whole=min(secs["whole"]), quick=min(secs["quick"]), diff=diff)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, nargs="+", default=[2.0, 0.88])
    ap.add_argument("--pressure", type=float, default=3.0)
    args = ap.parse_args(argv)
    if not (all(h > 0 for h in args.h) and args.pressure > 0):
        ap.error(f"--h must be > 0 mm and --pressure > 0 mmHg; got {args.h}, {args.pressure}")
    print(f"# python benchmarks/recheck_compile.py --h {' '.join(map(str, args.h))} "
          f"--pressure {args.pressure:g}")
    print(f"# {platform_summary()}")
    print(f"recheck residual program at the benchmark valve closed at {args.pressure:g} mmHg "
          "(FIRE); compile s, best of 2, one process")
    print(f"{'h mm':>6} {'nodes':>6} {'closed':>8} {'switch s':>9} {'whole s':>8} "
          f"{'ratio':>6} {'whole+quick s':>14} {'ratio':>6} {'max |dF|/max|F|':>16}")
    for h in args.h:
        r = measure(h, args.pressure)
        print(f"{r['h']:6.2f} {r['nodes']:6d} {str(r['converged']):>8} {r['switch']:9.2f} "
              f"{r['whole']:8.2f} {r['switch'] / r['whole']:6.2f} {r['quick']:14.2f} "
              f"{r['switch'] / r['quick']:6.2f} {r['diff']:16.1e}")


if __name__ == "__main__":
    main()
