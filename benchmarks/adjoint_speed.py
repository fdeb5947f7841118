"""The optimiser's gradient (`Evaluator.gradient`, the LU adjoint) against another checkout.

    python benchmarks/adjoint_speed.py --baseline DIR            # DIR: e.g. a git worktree
    python benchmarks/adjoint_speed.py --baseline DIR --processes 3 --calls 5

At the default optimisation's start (the benchmark valve, h = 0.88 mm, 3 mmHg, rtol 1e-6,
the default objective), each code closes the valve once and then times its gradient: the
first call (tracing and compiling the assembly, the residual's VJP and the pull-back to
(r, a, b), plus the solve) and ``--calls`` calls after it.  Each code runs in fresh
processes (``PYTHONPATH`` set to its checkout, the compilation cache off), alternating, so
that both see the same machine.  Printed per process: the timings, the GMRES iterations,
the adjoint's relative residual and the gradient; then the ratios baseline / this code of
the median first call and the median of all later calls ("speed-up").
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkouts import describe, run_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import dataclasses, json, sys, time
import jax
import numpy as np
jax.config.update("jax_enable_x64", True)
from jaxvalve import Scene
from optimize import Objective
from optimize.evaluate import Evaluator
sc = Scene(rtol=1e-6)
ev = Evaluator(sc, dataclasses.replace(Objective(), area_ref=sc.template().area))
e = ev.forward(np.array([sc.r, sc.a, sc.b]))
assert e.converged, e.reason
ts = []
for _ in range(1 + int(sys.argv[1])):
    t = time.perf_counter()
    v, g, info = ev.gradient(e)
    ts.append(time.perf_counter() - t)
a = info["adjoint"][0]
print(json.dumps(dict(first=ts[0], later=ts[1:], iterations=a.iterations,
                      residual=a.residual, nnz=a.nnz, g=[float(c) for c in g])))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, required=True, metavar="DIR",
                    help="a checkout of another commit")
    ap.add_argument("--processes", type=int, default=2, help="fresh processes per code")
    ap.add_argument("--calls", type=int, default=4, help="timed calls after the first")
    args = ap.parse_args(argv)
    base = args.baseline.resolve()
    if not (base / "jaxvalve" / "solvers" / "adjoint.py").is_file():
        ap.error(f"--baseline must be a jaxvalve checkout; got {base}")
    codes = {"this code": ROOT, "baseline": base}
    for name, root in codes.items():
        print(f"## {name}: {describe(root)}")
    print("Evaluator.gradient (adjoint 'lu') at the default optimisation's start "
          "(benchmark valve, h = 0.88 mm, 3 mmHg, rtol 1e-6); fresh processes, alternating, "
          "compilation cache off")
    out = {name: [] for name in codes}
    for i in range(args.processes):
        for name, root in codes.items():
            r = run_json(root, CHILD, (args.calls,), "the gradient run")
            out[name].append(r)
            print(f"{name:9s} process {i + 1}: first {r['first']:.2f} s, later "
                  f"{' '.join(f'{t:.3f}' for t in r['later'])} s; GMRES {r['iterations']}, "
                  f"residual {r['residual']:.1e}, nnz {r['nnz']}, "
                  f"gradient {' '.join(f'{c:.8f}' for c in r['g'])}", flush=True)
    med = {name: (statistics.median(r["first"] for r in rs),
                  statistics.median(t for r in rs for t in r["later"]))
           for name, rs in out.items()}
    (f1, l1), (f0, l0) = med["this code"], med["baseline"]
    print(f"first call (compile and solve): {f1:.2f} s against {f0:.2f} s, "
          f"speed-up {f0 / f1:.2f}x")
    print(f"later calls: {l1:.3f} s against {l0:.3f} s, speed-up {l0 / l1:.2f}x")


if __name__ == "__main__":
    main()
