"""The hinge bending law under mesh refinement: D w (1 - cos theta) against (D/2) w theta^2.

The two discrete hinge energies agree to second order in the fold angle theta, so on a
smooth surface (theta ~ h kappa per hinge) they tend to the same plate energy as the mesh
is refined; they differ on creases, where the moment of 1 - cos theta, D w sin theta,
falls past 90 degrees and that of theta^2 / 2, D w theta, keeps growing
(docs/known-limits.md, "Creases stop the barrier Newton at its fold bound").  This
script closes the benchmark valve (default path) at each mesh size with each law and
prints every metric and its change, beside the metric's own change from mesh to mesh.
Each law runs in a process of its own (the theta^2 law is patched in there).

    python benchmarks/hinge_convergence.py [--model neo-hookean] [--h 1.5 1.2 1.0 0.88 0.75]
        [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

KEYS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")


def _theta2_law():
    """Replace the hinge energy by (D / 2) w arccos(n1 . n2)^2 (series in 1 - c near the
    flat state, where arccos has no derivative)."""
    import jax.numpy as jnp

    import jaxvalve.mechanics.bending as B
    import jaxvalve.solvers.tangent as T

    def half_theta2(c):
        u = 1.0 - c
        small = u < 1e-3
        cs = jnp.clip(jnp.where(small, 0.0, c), -1.0 + 1e-12, 1.0)
        series = u + u ** 2 / 6 + 4 * u ** 3 / 45 + 2 * u ** 4 / 35   # arccos(1 - u)^2 / 2
        return jnp.where(small, series, 0.5 * jnp.arccos(cs) ** 2)

    def energy(x, hinge, weights, D, triangles):
        xt = x[triangles]
        n = B._unit(jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]))
        c = jnp.sum(n[hinge[:, 4]] * n[hinge[:, 5]], -1)
        return D * jnp.sum(weights * half_theta2(c))
    B.bending_energy = energy
    T.bending_energy = energy


def _child(law, model, hs):
    """One law, every mesh: one JSON line per closure on stdout."""
    if law == "theta2":
        _theta2_law()
    from jaxvalve import Scene, simulate
    for h in hs:
        t = time.perf_counter()
        r = simulate(Scene(h=h, model=model), throw=False)
        print(json.dumps(dict(law=law, mesh_h=h, converged=bool(r.converged),
                              wall_s=time.perf_counter() - t,
                              **{k: float(v) for k, v in r.summary().items()})), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="neo-hookean")
    ap.add_argument("--h", type=float, nargs="+", default=[1.5, 1.2, 1.0, 0.88, 0.75])
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", choices=["cos", "theta2"], help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args.child, args.model, args.h)
    from closure_speed import Tee
    from jaxvalve.xla_setup import platform_summary
    out = Tee()
    out(f"hinge law under refinement: {platform_summary()}; benchmark valve, {args.model}, "
        "default path")
    rows = {}
    for law in ("cos", "theta2"):
        cmd = [sys.executable, __file__, "--child", law, "--model", args.model, "--h",
               *map(str, args.h)]
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
        for line in done.stdout.splitlines():
            if line.startswith("{"):
                r = json.loads(line)
                rows[(law, r["mesh_h"])] = r
    out("| h mm | law | converged | " + " | ".join(KEYS) + " | s |")
    out("|---|---|---|" + "---|" * len(KEYS) + "---|")
    for h in args.h:
        for law in ("cos", "theta2"):
            r = rows[(law, h)]
            out(f"| {h:g} | {law} | {'yes' if r['converged'] else 'NO'} | "
                + " | ".join(f"{r[k]:.3f}" for k in KEYS) + f" | {r['wall_s']:.0f} |")
    out("")
    out("| h mm | " + " | ".join(f"theta2 - cos {k}" for k in KEYS) + " |")
    out("|---|" + "---|" * len(KEYS))
    for h in args.h:
        a, b = rows[("cos", h)], rows[("theta2", h)]
        out(f"| {h:g} | " + " | ".join(f"{b[k] - a[k]:+.3f}" for k in KEYS) + " |")
    cos = [rows[("cos", h)] for h in args.h]
    spread = {k: max(r[k] for r in cos) - min(r[k] for r in cos) for k in KEYS}
    gap = {k: max(abs(rows[("theta2", h)][k] - rows[("cos", h)][k]) for h in args.h)
           for k in KEYS}
    out.finish(["largest change of law, against the metric's spread over the meshes (cos): "
                + "; ".join(f"{k} {gap[k]:.3f} / {spread[k]:.3f}" for k in KEYS)], args.out)


if __name__ == "__main__":
    main()
