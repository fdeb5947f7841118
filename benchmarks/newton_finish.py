"""FIRE's tail against a Newton finish on the exact tangent: the benchmark closure (3 then
80 mmHg, smooth contact) to the same relative residual, both ways, in one process.

* "fire": FIRE to ``--rtol`` at each load (the default path's solver).
* "fire to S + newton": FIRE to the switch residual S, then plain Newton steps
  x <- x + K^-1 R with K = -dR/dx the assembled stiffness (`jaxvalve.solvers.tangent`,
  exact on the soft-min contact, so Newton converges quadratically near an equilibrium),
  a sparse LU per step, FIRE's contact pair list kept, until the relative residual is
  below ``--rtol`` (at most ``--max-newton`` steps; a step that raises the residual
  tenfold is reported as diverged).  The 80 mmHg closure starts from this path's own
  3 mmHg state.

Every closure is run once to compile and then timed.  Prints, per model, load and path:
FIRE steps, Newton steps, seconds in FIRE and in Newton, their sum, the final relative
residual, the largest distance from the FIRE path's state (mm) and the speed-up (the
FIRE path's time over this path's, where the finish converged); then, per model, the
speed-up of both loads together, or which finish did not converge.

    python benchmarks/newton_finish.py [--h 1.5] [--rtol 1e-6] [--switch 1e-2 1e-3 1e-4]
        [--models stvk gent] [--out benchmarks/results/newton_finish.txt]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

from jaxvalve import Scene  # noqa: E402
from jaxvalve.mechanics import assembly  # noqa: E402
from jaxvalve.scene import MODELS  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.solvers import tangent  # noqa: E402
from jaxvalve.valve import model as V  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from closure_speed import Tee  # noqa: E402


def _relative(problem):
    @jax.jit
    def f(x, params, nbrs):
        R = assembly.residual(x, problem, params, assembly.prepare(problem, params), nbrs)
        return R, jnp.linalg.norm(R) / assembly.pressure_scale(x, problem, params)
    return f


def newton_finish(problem, params, x, nbrs, rtol, max_steps, relative):
    """Plain Newton from x (N, 3) mm on the exact assembled tangent, FIRE's pair list kept,
    until the relative residual is below rtol ("converged"), rises tenfold above its start
    or is not finite ("diverged"), or ``max_steps`` steps ("step cap").
    Returns (state, steps, relative residual, outcome)."""
    free = np.asarray(problem.free)
    x = np.array(x, np.float64)
    R, r = relative(jnp.asarray(x), params, nbrs)
    r0, steps = float(r), 0
    while True:
        r = float(r)
        if r <= rtol:
            return x, steps, r, "converged"
        if not np.isfinite(r) or r > 10 * r0:
            return x, steps, r, "diverged"
        if steps == max_steps:
            return x, steps, r, "step cap"
        K = tangent.assemble(problem, params, x, nbrs)
        x[free] += spla.splu(K).solve(np.asarray(R)[free].ravel()).reshape(-1, 3)
        R, r = relative(jnp.asarray(x), params, nbrs)
        steps += 1


def run_path(valve, scene, switch, rtol, max_newton, relative):
    """Both loads by FIRE to ``switch`` (None: to rtol) and a Newton finish; per load
    (FIRE steps, Newton steps, FIRE s, Newton s, residual, outcome, state)."""
    mat, contact, bending = scene.material(), scene.contact_law(), scene.bending_law()
    fire = dataclasses.replace(scene.make_solver(), rtol=switch or rtol)
    x, out = valve.x_start, []
    for p in (scene.he_pressure, scene.pressure):
        t0 = time.perf_counter()
        sol = V.close(valve, mat, p, solver=fire, contact=contact, thickness=scene.thickness,
                      fibre_angle=np.deg2rad(scene.fibre_angle), bending=bending, x0=x,
                      throw=False)
        jax.block_until_ready(sol.x)
        t1 = time.perf_counter()
        y, n, r, outcome = np.asarray(sol.x, np.float64), 0, float(sol.stats.residual), (
            "converged" if sol.converged else sol.describe())
        if switch is not None and sol.converged:
            params = valve.params(mat, p, contact, scene.thickness,
                                  np.deg2rad(scene.fibre_angle), bending)
            y, n, r, outcome = newton_finish(valve.problem, params, y, sol.nbrs, rtol,
                                             max_newton, relative)
        t2 = time.perf_counter()
        out.append((int(sol.stats.steps), n, t1 - t0, t2 - t1, r, outcome, y))
        x = jnp.asarray(y)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--rtol", type=float, default=1e-6, help="relative residual of both")
    ap.add_argument("--switch", type=float, nargs="*", default=[1e-2, 1e-3, 1e-4],
                    help="relative residuals at which Newton takes over")
    ap.add_argument("--max-newton", type=int, default=10)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.max_newton < 1:
        ap.error(f"--max-newton must be a positive count; got {args.max_newton}")
    if not all(args.rtol < s < 1 for s in args.switch):
        ap.error(f"--switch values must lie between --rtol ({args.rtol:g}) and 1")
    say = Tee()
    say(f"benchmark closure, h = {args.h} mm, to a relative residual of {args.rtol:g}; "
        f"each path compiled by a first run, then timed; {platform_summary()}")
    say("| model | load mmHg | path | FIRE steps | Newton steps | FIRE s | Newton s | "
        "total s | residual | outcome | max dx vs FIRE mm | speed-up |")
    say("|---" * 12 + "|")
    valve, summary = None, []
    for model in args.models:
        scene = Scene(model=model, h=args.h, rtol=args.rtol)
        valve = build_scene_valve(scene) if valve is None else valve
        relative = _relative(valve.problem)
        paths = [None] + list(args.switch)
        runs = {}
        for s in paths:
            run_path(valve, scene, s, args.rtol, args.max_newton, relative)   # compile
            runs[s] = run_path(valve, scene, s, args.rtol, args.max_newton, relative)
        base = runs[None]
        for s in paths:
            name = "fire" if s is None else f"fire to {s:g} + newton"
            for p, (nf, nn, tf, tn, r, outcome, y), b in zip(
                    (scene.he_pressure, scene.pressure), runs[s], base):
                dx = float(np.abs(y - b[6]).max())
                ratio = (f"{(b[2] + b[3]) / (tf + tn):.2f}x" if outcome == "converged"
                         else "-")
                say(f"| {model} | {p:g} | {name} | {nf} | {nn} | {tf:.3f} | {tn:.3f} | "
                    f"{tf + tn:.3f} | {r:.1e} | {outcome} | {dx:.1e} | {ratio} |")
            if s is not None:
                tot = sum(o[2] + o[3] for o in runs[s])
                ok = all(o[5] == "converged" for o in runs[s])
                fire = sum(o[2] + o[3] for o in base)
                summary.append(f"{model}, {name}: " + (
                    f"speed-up {fire / tot:.2f}x over both loads (FIRE {fire:.2f} s, this "
                    f"path {tot:.2f} s)" if ok else
                    "no speed-up figure: " + "; ".join(
                        f"{p:g} mmHg {o[5]} at {o[4]:.1e} after {o[1]} Newton steps"
                        for p, o in zip((scene.he_pressure, scene.pressure), runs[s])
                        if o[5] != "converged")))
    say.finish(summary, args.out)


if __name__ == "__main__":
    main()
