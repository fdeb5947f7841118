"""The benchmark valve's closure (3 then 80 mmHg, `simulate`) by this code against another
checkout's, each in fresh processes, for the material models and the soft pericardium of
the paper's Table 4.

Each code runs in its own processes (``PYTHONPATH`` set to its checkout, the compilation
cache off), alternating, one process per code and case: the process closes the valve once
(compiling) and then ``--repeats`` times, timed.  Printed per case and code: whether both
loads converged, the path that closed them (the baseline names its fallback), the steps
per load (Newton steps of the engine's finish in brackets), the median solve time after
compilation, the first closure's compile time, and the headline metrics; then the speed-up
(the baseline's median solve time over this code's: above 1 means faster) and the change
of the metrics.

    python benchmarks/closure_speed.py --baseline DIR [--h 1.5] [--repeats 2]
        [--cases stvk ms_mid] [--root SURFACE LANDMARKS] [--out FILE]

``--root`` closes the valve in a patient's root instead of the benchmark's (e.g. the
segmented phantom: ``jaxvalve phantom --out scan && jaxvalve segment scan/ct.nii.gz --out
seg --landmarks scan/landmarks_true.mrk.json``, then ``--root seg/root.stl
seg/landmarks.mrk.json``); the figures add the sharpest fold of the closed leaflets.

DIR is a checkout of the baseline commit (``git worktree add DIR <commit>``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkouts import describe, run_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
METRICS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")

#: case -> Scene fields: the four models at the benchmark's moduli, and three Table 4 cells
#: (mass-spring, E3 = 1.2 MPa): the stiffest, the middle and the softest pericardium
CASES = {
    "stvk": dict(model="stvk"),
    "neo-hookean": dict(model="neo-hookean"),
    "gent": dict(model="gent"),
    "mass-spring": dict(model="mass-spring"),
    "ms_stiff": dict(model="mass-spring", E1=0.18, E2=0.7, E3=1.2),
    "ms_mid": dict(model="mass-spring", E1=0.106, E2=0.569, E3=1.2),
    "ms_soft": dict(model="mass-spring", E1=0.05, E2=0.3, E3=1.2),
}

#: One code's closures in a fresh process: argv case fields (JSON), h, repeats.
CHILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from jaxvalve import Scene, simulate
from jaxvalve.simulation import build_scene_valve
kw, h, repeats = json.loads(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
if isinstance(kw.get("root"), list):
    kw["root"] = tuple(kw["root"])
sc = Scene(h=h, **kw)
from jaxvalve.valve.checks import triangle_checks
valve = build_scene_valve(sc)
runs = []
for i in range(1 + repeats):
    r = simulate(sc, valve=valve, throw=False)
    runs.append(dict(
        converged=bool(r.converged),
        steps=[int(s.steps) for s in r.solves],
        newton=[int(getattr(s, "newton_steps", 0)) for s in r.solves],
        path=[str(getattr(s, "path", "") or "") + (" (fallback)" if getattr(s, "fallback", None) else "")
              for s in r.solves],
        solve_s=sum(s.solve_s for s in r.solves),
        compile_s=sum(s.compile_s for s in r.solves),
        metrics={k: float(v) for k, v in r.summary().items()},
        fold=float(triangle_checks(valve.ref, valve.triangles, r.x, fold_deg=180.0).max_fold_deg)))
print(json.dumps(runs))
"""


def _one(root: Path, case: str, h: float, repeats: int, valve_root=None) -> dict:
    import json
    kw = dict(CASES[case])
    if valve_root:
        kw["root"] = [str(Path(p).resolve()) for p in valve_root]
    runs = run_json(root, CHILD, [json.dumps(kw), h, repeats], f"case {case}")
    first, timed = runs[0], runs[1:] or runs[:1]
    return dict(first=first, solve_s=statistics.median(r["solve_s"] for r in timed),
                compile_s=first["compile_s"], runs=runs)


def _row(name, res):
    f = res["first"]
    steps = "/".join(f"{s}" + (f" ({n})" if n else "") for s, n in zip(f["steps"], f["newton"]))
    m = "  ".join(f"{k} {f['metrics'][k]:.2f}" for k in METRICS) + f"  fold {f['fold']:.1f} deg"
    return (f"  {name:9s} {'yes' if f['converged'] else 'NO ':3s}  {f['path'][-1]:22s} "
            f"{steps:18s} {res['solve_s']:7.2f} s  (+{res['compile_s']:5.1f} s compile)  {m}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--baseline", type=Path, required=True, help="checkout of the baseline")
    p.add_argument("--h", type=float, default=1.5)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--root", nargs=2, metavar=("SURFACE", "LANDMARKS"))
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    from jaxvalve.xla_setup import platform_summary
    where = "the benchmark valve" if not a.root else f"the valve in the root {a.root[0]}"
    lines = [f"closure of {where}, h = {a.h} mm, 3 then 80 mmHg (simulate); "
             f"median of {a.repeats} timed closures after a compiling one, fresh processes",
             f"this code: {describe(ROOT)} (+ working tree)",
             f"baseline:  {describe(a.baseline)}", f"platform: {platform_summary()}", "",
             "  code      conv path (80 mmHg)        steps 3/80 (Newton) solve        "
             "compile               metrics (mm, %)"]
    print("\n".join(lines), flush=True)
    summary = []
    for case in a.cases:
        new = _one(ROOT, case, a.h, a.repeats, a.root)
        base = _one(a.baseline, case, a.h, a.repeats, a.root)
        block = [f"{case}: {CASES[case]}", _row("baseline", base), _row("this", new)]
        ratio = base["solve_s"] / new["solve_s"]
        total = ((base["solve_s"] + base["compile_s"]) / (new["solve_s"] + new["compile_s"]))
        dm = "  ".join(f"{k} {new['first']['metrics'][k] - base['first']['metrics'][k]:+.2f}"
                       for k in METRICS)
        block.append(f"  speed-up {ratio:.2f}x solve, {total:.2f}x with compilation; "
                     f"metric change (this - baseline): {dm}")
        summary.append(f"  {case:12s} {ratio:6.2f}x solve  {total:6.2f}x with compile")
        print("\n".join(block), flush=True)
        lines += block
    lines += ["", "speed-ups (baseline time / this code's time):"] + summary
    print("\n".join(lines[-len(summary) - 1:]))
    if a.out:
        a.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
