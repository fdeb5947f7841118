"""The soft-min pair energy's static prefixes: how many, measured on the benchmark closure.

`SmoothContact`'s force is evaluated on the shortest of a few static prefixes of the
pruned pair list that holds the pairs in use (`smooth.SOFT_PREFIXES` of them, each half
the last), chosen at run time by `lax.switch`.  More prefixes make a force follow the
pairs in use more closely (the leaflets swinging shut have a few, the valve at 80 mmHg
about a third of the slots) and cost compilation, one branch each.

For each model, the benchmark valve (default scene, FIRE on the smooth law, 3 then
80 mmHg) is closed with each prefix count in the same process, alternating: each variant
compiled afresh (`jax.clear_caches()`) and then timed, ``--repeats`` times.  Printed: the
prefixes, compile time, median solve time after compilation, steps and metrics (which
must not change: a longer prefix holds only padding), then the speed-up of each count
against the first (its median over the other's) and the extra compile time.

    python benchmarks/pair_prefixes.py [--h 1.5] [--counts 3 5] [--repeats 3]
        [--models stvk mass-spring] [--out benchmarks/results/pair_prefixes.txt]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.contact import smooth  # noqa: E402
from jaxvalve.contact.neighbours import bucket_sizes  # noqa: E402
from jaxvalve.contact.soft_pairs import default_soft_capacity  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402
from closure_speed import MODELS, Tee  # noqa: E402  (this folder is on the path of a script)

METRICS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")


def closure(scene, valve):
    res = simulate(scene, valve=valve, throw=False)
    steps = "/".join(str(int(s.steps)) for s in res.solves)
    summ = res.summary()
    return (sum(s.solve_s for s in res.solves), sum(s.compile_s for s in res.solves),
            steps, res.converged, tuple(round(float(summ[k]), 6) for k in METRICS))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--counts", type=int, nargs="+", default=[3, smooth.SOFT_PREFIXES])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be a positive integer; got {args.repeats}")
    if any(c < 1 for c in args.counts) or len(args.counts) < 2:
        ap.error(f"--counts needs at least two positive integers; got {args.counts}")
    if any(m not in MODELS for m in args.models):
        ap.error(f"--models must be among {list(MODELS)}; got {args.models}")
    jax.config.update("jax_enable_x64", True)
    out = Tee()
    out(f"# soft-min pair energy: static prefixes, benchmark closure, h = {args.h} mm; "
        f"{args.repeats} timed closures per variant after one that compiles")
    out(f"# {platform_summary()}")
    summary = []
    real = smooth.SOFT_PREFIXES
    try:
        for model in args.models:
            scene = Scene(h=args.h, model=model)
            valve = build_scene_valve(scene)
            cap = default_soft_capacity(valve.problem.n_nodes)
            runs, info = {c: [] for c in args.counts}, {}
            for _ in range(args.repeats):
                for c in args.counts:
                    # the jitted programs do not depend on the constant: cleared and
                    # compiled afresh for each timing
                    smooth.SOFT_PREFIXES = c
                    jax.clear_caches()
                    first = closure(scene, valve)
                    info.setdefault(c, first)
                    s, _, steps, conv, metrics = closure(scene, valve)
                    if (steps, conv, metrics) != info[c][2:]:
                        raise SystemExit(f"{model}, {c} prefixes: a closure differs from "
                                         f"the first ({steps} {metrics} against {info[c][2:]})")
                    runs[c].append(s)
            out(f"\n## {model} ({cap} pair slots)")
            out("| prefixes | sizes | converged | steps 3/80 | compile s | solve s (median) "
                "| runs s | " + " | ".join(METRICS) + " |")
            out("|---" * (7 + len(METRICS)) + "|")
            for c in args.counts:
                sizes = bucket_sizes(cap, smallest=256, most=c, factor=2)
                out(f"| {c} | {' '.join(map(str, sizes))} | {'yes' if info[c][3] else 'NO'} | "
                    f"{info[c][2]} | {info[c][1]:.1f} | {statistics.median(runs[c]):.3f} | "
                    + " ".join(f"{t:.3f}" for t in runs[c]) + " | "
                    + " | ".join(f"{v:.3f}" for v in info[c][4]) + " |")
            first = args.counts[0]
            for c in args.counts[1:]:
                same = info[c][2:] == info[first][2:]
                summary.append(
                    f"{model}, {c} prefixes against {first}: speed-up "
                    f"{statistics.median(runs[first]) / statistics.median(runs[c]):.2f}x "
                    f"({statistics.median(runs[first]):.3f} s against "
                    f"{statistics.median(runs[c]):.3f} s after compilation), compile "
                    f"{info[c][1] - info[first][1]:+.1f} s, same steps and metrics: {same}")
    finally:
        smooth.SOFT_PREFIXES = real
    out.finish(summary, args.out)


if __name__ == "__main__":
    main()
