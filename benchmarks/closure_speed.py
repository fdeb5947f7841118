"""The benchmark closure (3 then 80 mmHg) on three paths, side by side in one process and
to the same relative residual, for each material model:

* "fire + smooth": the FIRE path alone (smooth one-sided penalty, FIRE, no fallback), the
  baseline;
* "default": `Scene()`'s closure, FIRE on the smooth law with the barrier path as its
  fallback where that fails (`jaxvalve.valve.closure`, "Fallback"); the column "closed by"
  names the path that closed the valve;
* "newton + barrier": the barrier contact and projected Newton throughout.

Prints, per model and path: whether both loads converged, the path that closed them,
steps (3/80 mmHg), solve time after compilation (for the barrier path with its start, the
valve swung shut by FIRE at 3 mmHg), compile time, the smallest distance between the
leaflets, and the headline metrics, whose differences are what the change of contact law
moves; then the speed-ups against the FIRE path (its solve time over the other's: above
1 means faster).

The two FIRE-based paths are timed ``--repeats`` times each (default 3), alternating, and
their median solve time is the figure: on the benchmark valve the default closes on FIRE
with the same steps as the FIRE path, so one timing of each compares two identical
closures and gave ratios of 0.96-1.15x on one machine, timing noise.  The barrier path,
5-50x slower, is timed once.

    python benchmarks/closure_speed.py [--h 1.5] [--rtol 1e-6] [--models stvk gent]
        [--repeats 3] [--out benchmarks/results/closure_speed.txt]

With ``--baseline DIR`` (a checkout of another commit, e.g. a git worktree of the code
before the barrier work, whose only path was FIRE on the smooth law) the script instead
compares this code's default and FIRE paths with DIR's own default closure: each code runs
in fresh processes (``PYTHONPATH`` set to its checkout, the compilation cache off),
alternating, ``--processes`` per code and model, each closing the valve once to compile
and then ``--repeats`` times, timed.  Printed per model and path: steps, the median solve
time after compilation, the first closure's compile time and the metrics; then the
speed-ups against the baseline (its median over this path's).

    python benchmarks/closure_speed.py --baseline DIR [--processes 2] [--repeats 3]
        [--out benchmarks/results/closure_speed_vs_<commit>.txt]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.contact.ipc_pairs import build_pairs  # noqa: E402
from jaxvalve.scene import MODELS  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkouts import describe, run_json  # noqa: E402

PATHS = (("fire + smooth", dict(contact="smooth", solver="fire", fallback=False)),
         ("default", dict()),
         ("newton + barrier", dict(contact="barrier", solver="newton")))
METRICS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")


ROOT = Path(__file__).resolve().parents[1]

#: One code's closures in a fresh process (`--baseline`): argv model, h, rtol, repeats,
#: then the paths; "fire" is FIRE on the smooth law without fallback where the code has
#: those settings, and the code's plain `Scene` where it has not (before the barrier work,
#: FIRE on the smooth law was the only path).
CHILD = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
from jaxvalve import Scene, simulate
from jaxvalve.simulation import build_scene_valve
model, h, rtol, repeats = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
kw = dict(model=model, h=h, rtol=rtol)
def scene(path):
    if path == "fire":
        try:
            return Scene(**kw, contact="smooth", solver="fire", fallback=False)
        except TypeError:
            pass
    return Scene(**kw)
valve, out = None, {}
for path in sys.argv[5:]:
    sc = scene(path)
    valve = build_scene_valve(sc) if valve is None else valve
    runs = [simulate(sc, valve=valve, throw=False) for _ in range(repeats + 1)]
    r = runs[-1]
    out[path] = dict(compile_s=sum(s.compile_s for s in runs[0].solves),
                     solve_s=[sum(s.solve_s for s in q.solves) for q in runs[1:]],
                     steps=[s.steps for s in r.solves], converged=bool(r.converged),
                     closed_by=str(getattr(r.solves[-1], "path", None) or "fire+smooth"),
                     metrics={k: float(v) for k, v in r.summary().items()})
print(json.dumps(out))
"""


def against_baseline(args, say):
    """``--baseline``: this code's default and FIRE paths against DIR's default closure,
    fresh processes alternating (module docstring)."""
    base = args.baseline.resolve()
    if not (base / "jaxvalve" / "__init__.py").is_file():
        raise SystemExit(f"--baseline must be a jaxvalve checkout; got {base}")
    codes = (("baseline", base, ("default",)), ("this code", ROOT, ("default", "fire")))
    for name, root, _ in codes:
        say(f"# {name}: {describe(root)}")
    say(f"# benchmark closure, h = {args.h} mm, rtol = {args.rtol:g}; {args.processes} fresh "
        f"processes per code and model, alternating, each compiling once and then timing "
        f"{args.repeats} closures (median of all); compilation cache off; "
        f"{platform_summary()}")
    say("| model | code | path | converged | closed by | steps 3/80 | solve s (median) | "
        "runs s | compile s | " + " | ".join(METRICS) + " |")
    say("|---" * (9 + len(METRICS)) + "|")
    summary = []
    for model in args.models:
        got = {}
        for _ in range(args.processes):
            for name, root, paths in codes:
                r = run_json(root, CHILD, (model, args.h, args.rtol, args.repeats, *paths),
                             "the closures")
                for path, v in r.items():
                    got.setdefault((name, path), []).append(v)
        med = {}
        for (name, path), vs in got.items():
            runs = [t for v in vs for t in v["solve_s"]]
            ok = all(v["converged"] for v in vs)
            med[(name, path)] = statistics.median(runs) if ok else float("nan")
            v, m = vs[0], vs[0]["metrics"]
            say(f"| {model} | {name} | {path} | {'yes' if ok else 'no'} | {v['closed_by']} "
                f"| {'/'.join(str(n) for n in v['steps'])} | {med[(name, path)]:.3f} | "
                f"{' '.join(f'{t:.2f}' for t in runs)} | "
                f"{statistics.median(x['compile_s'] for x in vs):.1f} | "
                + " | ".join(f"{m[k]:.3f}" for k in METRICS) + " |")
        b = med[("baseline", "default")]
        for path in ("default", "fire"):
            t = med[("this code", path)]
            summary.append(f"{model}, this code's {path} against the baseline's closure: "
                           + (f"speed-up {b / t:.2f}x ({b:.3f} s against {t:.3f} s after "
                              "compilation)" if b == b and t == t else
                              "no speed-up figure: a closure did not converge"))
    say.finish(summary, args.out)


class Tee:
    """Prints each line as it comes and keeps it, to write the results file at the end."""

    def __init__(self):
        self.lines = []

    def __call__(self, s=""):
        print(s, flush=True)
        self.lines.append(s)

    def write(self, path):
        if path:
            Path(path).write_text("\n".join(self.lines) + "\n")

    def finish(self, summary, path):
        """Print the summary lines after a blank line, then write everything to path."""
        self()
        for s in summary:
            self(s)
        self.write(path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--rtol", type=float, default=1e-6, help="relative residual of both")
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--repeats", type=int, default=3,
                    help="timings of each FIRE-based path (median)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--baseline", type=Path, default=None, metavar="DIR",
                    help="compare with another checkout's closure instead (docstring)")
    ap.add_argument("--processes", type=int, default=2,
                    help="with --baseline: fresh processes per code and model")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be a positive count; got {args.repeats}")
    if args.processes < 1:
        ap.error(f"--processes must be a positive count; got {args.processes}")
    say = Tee()
    if args.baseline is not None:
        return against_baseline(args, say)
    say(f"benchmark closure, h = {args.h} mm, rtol = {args.rtol:g}, FIRE-based paths timed "
        f"{args.repeats}x (median); {platform_summary()}")
    say("| model | path | converged | closed by | steps 3/80 | solve s | compile s | "
        "min gap mm | " + " | ".join(METRICS) + " |")
    say("|---" * (8 + len(METRICS)) + "|")
    valve = None
    summary = []
    for model in args.models:
        solve_s = {}
        results = {}
        for rep in range(args.repeats):
            for name, kw in PATHS:
                if rep and name == PATHS[2][0]:
                    continue                  # the barrier path: once
                sc = Scene(model=model, h=args.h, rtol=args.rtol, **kw)
                valve = build_scene_valve(sc) if valve is None else valve
                res = simulate(sc, valve=valve, throw=False)
                s3, s80 = res.solves
                t = s3.solve_s + s80.solve_s + res.timings.get("start", 0.0)  # + swing-shut
                solve_s.setdefault(name, []).append(t if res.converged else float("nan"))
                results.setdefault(name, res)
        solve_s = {k: float(np.median(v)) for k, v in solve_s.items()}
        for name, _ in PATHS:
            res = results[name]
            s3, s80 = res.solves
            t = solve_s[name]
            gap = build_pairs(valve.barrier_topology, res.x, 1.0).min_distance
            m = res.summary()
            say(f"| {model} | {name} | {'yes' if res.converged else s3.result + '/' + s80.result} "
                f"| {s80.path} | {s3.steps}/{s80.steps} | {t:.2f} | "
                f"{s3.compile_s + s80.compile_s:.1f} "
                f"| {gap:.3f} | " + " | ".join(f"{m[k]:.3f}" for k in METRICS) + " |")
        fire = solve_s[PATHS[0][0]]
        for name, _ in PATHS[1:]:
            other = solve_s[name]
            if fire == fire and other == other:       # both converged
                summary.append(f"{model}, {name}: speed-up {fire / other:.2f}x (FIRE "
                               f"{fire:.2f} s, {name} {other:.2f} s after compilation)")
            else:
                summary.append(f"{model}, {name}: no speed-up figure: "
                               + " and ".join(n for n in (PATHS[0][0], name)
                                              if solve_s[n] != solve_s[n])
                               + " did not converge")
    say.finish(summary, args.out)


if __name__ == "__main__":
    main()
