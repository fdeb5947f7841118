"""What each saving in a FIRE step buys on the benchmark closure: this code against itself
with one piece put back as it was.

Pieces (each variant reverts one, the rest as in this code):

* "3 prefixes": the soft-min pair energy chooses among 3 static prefixes of its pruned
  list (6144, 3072, 1536 slots at h = 1.5 mm) instead of `smooth.SOFT_PREFIXES`, each half
  the last; the swing-shut, with a few pairs in use, then pays for 1536 slots;
* "scale apart": FIRE's relative residual takes its scale (||F_pressure||) from a second
  pressure-load evaluation (`EquilibriumSystem.force_scale` None) instead of the force's;
* "bound by matmul": `assembly.spectral_bound` squares its 9x9 blocks with XLA's batched
  matrix product (a frozen copy below) instead of elementwise outer products (FIRE's
  mass refresh, every 100 steps).

For each model the benchmark valve (default scene, both loads, rtol 1e-6) is closed by
each variant in one process, alternating, each compiled afresh (`jax.clear_caches()`:
the jitted programs do not see the switch) and then timed, ``--repeats`` times.
Printed: compile time, median solve time after compilation, steps and metrics; then this
code's speed-up against each variant (the variant's median over this code's) and the
compile time the piece adds.  The prefixes and the fused scale change no number (the
script checks that steps and metrics agree); the bound's rounding moves the masses in
the last bits, so its steps may differ by a few.

    python benchmarks/step_savings.py [--h 1.5] [--repeats 3] [--models stvk gent]
        [--out benchmarks/results/step_savings.txt]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.contact import smooth  # noqa: E402
from jaxvalve.mechanics import assembly  # noqa: E402
from jaxvalve.solvers import equilibrium  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402
from closure_speed import METRICS, MODELS, Tee  # noqa: E402  (this folder is on the path)

THIS = "this code"
EXACT = ("3 prefixes", "scale apart")       # variants that must give the same numbers


def spectral_bound_matmul(H, squarings: int = 3):
    """`assembly.spectral_bound` as it was: the squarings by batched matrix products."""
    f = jnp.sqrt(jnp.sum(H * H, axis=(-2, -1)))
    B = H / jnp.where(f > 0, f, 1.0)[..., None, None]
    for _ in range(squarings):
        B = B @ B
    t = jnp.sum(B * B, axis=(-2, -1))
    m2 = 2.0 ** (squarings + 1)
    return jnp.where(t > 0, f * jnp.where(t > 0, t, 1.0) ** (1.0 / m2), 0.0)


REAL = dict(prefixes=smooth.SOFT_PREFIXES, make_system=equilibrium.make_system,
            bound=assembly.spectral_bound)


def variant(name):
    """Put this code back, then revert the piece ``name`` names; clear the compiled
    programs."""
    smooth.SOFT_PREFIXES = REAL["prefixes"]
    equilibrium.make_system = REAL["make_system"]
    assembly.spectral_bound = REAL["bound"]
    if name == "3 prefixes":
        smooth.SOFT_PREFIXES = 3
    elif name == "scale apart":
        equilibrium.make_system = lambda *a: REAL["make_system"](*a)._replace(
            force_scale=None)
    elif name == "bound by matmul":
        assembly.spectral_bound = spectral_bound_matmul
    jax.clear_caches()


VARIANTS = (THIS, "3 prefixes", "scale apart", "bound by matmul")


def closure(scene, valve):
    res = simulate(scene, valve=valve, throw=False)
    steps = "/".join(str(int(s.steps)) for s in res.solves)
    summ = res.summary()
    return (sum(s.solve_s for s in res.solves), sum(s.compile_s for s in res.solves),
            steps, res.converged, tuple(round(float(summ[k]), 6) for k in METRICS))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--rtol", type=float, default=1e-6, help="relative residual")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be a positive integer; got {args.repeats}")
    if any(m not in MODELS for m in args.models):
        ap.error(f"--models must be among {list(MODELS)}; got {args.models}")
    jax.config.update("jax_enable_x64", True)
    out = Tee()
    out(f"# FIRE step savings, benchmark closure, h = {args.h} mm, rtol = {args.rtol:g}; "
        f"per variant {args.repeats} x (compile afresh, then one timed closure), "
        "alternating")
    out(f"# {platform_summary()}")
    summary = []
    try:
        for model in args.models:
            scene = Scene(h=args.h, model=model, rtol=args.rtol)
            valve = build_scene_valve(scene)
            runs, info = {v: [] for v in VARIANTS}, {}
            for _ in range(args.repeats):
                for v in VARIANTS:
                    variant(v)
                    first = closure(scene, valve)
                    info.setdefault(v, first)
                    s, _, steps, conv, metrics = closure(scene, valve)
                    if (steps, conv, metrics) != info[v][2:]:
                        raise SystemExit(f"{model}, {v}: a closure differs from the "
                                         f"first ({steps} {metrics} against {info[v][2:]})")
                    runs[v].append(s)
            out(f"\n## {model}")
            out("| variant | converged | steps 3/80 | compile s | solve s (median) | runs s | "
                + " | ".join(METRICS) + " |")
            out("|---" * (6 + len(METRICS)) + "|")
            for v in VARIANTS:
                out(f"| {v} | {'yes' if info[v][3] else 'NO'} | {info[v][2]} | "
                    f"{info[v][1]:.1f} | {statistics.median(runs[v]):.3f} | "
                    + " ".join(f"{t:.3f}" for t in runs[v]) + " | "
                    + " | ".join(f"{x:.3f}" for x in info[v][4]) + " |")
            me = statistics.median(runs[THIS])
            for v in VARIANTS[1:]:
                same = info[v][2:] == info[THIS][2:]
                same_metrics = info[v][3:] == info[THIS][3:]
                if v in EXACT and not same:
                    raise SystemExit(f"{model}, {v}: steps or metrics differ from this "
                                     f"code's ({info[v][2:]} against {info[THIS][2:]})")
                if not (info[v][3] and info[THIS][3]):
                    summary.append(f"{model}, this code against '{v}': no speed-up "
                                   "figure: a closure did not converge")
                    continue
                summary.append(
                    f"{model}, this code against '{v}': speed-up "
                    f"{statistics.median(runs[v]) / me:.2f}x ({statistics.median(runs[v]):.3f}"
                    f" s against {me:.3f} s after compilation), compile "
                    f"{info[THIS][1] - info[v][1]:+.1f} s, same steps: "
                    f"{info[v][2] == info[THIS][2]}, same metrics: {same_metrics}")
    finally:
        variant(THIS)
    out.finish(summary, args.out)


if __name__ == "__main__":
    main()
