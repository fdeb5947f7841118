"""Batch evaluation over materials against sequential closures (same valve, same members).

    python benchmarks/batch.py                       # h = 1.5 mm, StVK, E = 1 1.25 1.5 2 MPa
    python benchmarks/batch.py --table4              # the 9 cells of the paper's Table 4
    python benchmarks/batch.py --h 2 --E 0.5 1 2 --model neo-hookean

One valve is built; the members are closed by `simulate_batch(scene, materials,
valve=valve)` (the engine's FIRE phase under one jitted vmap per load, each member then
through the closure driver) and, for comparison, by one `simulate(scene, valve=valve)`
per member (one compiled solve shared by all calls).  Each path runs twice: the first
compiles (JAX's compile time reported apart), the second is timed.  "solve s" is the wall
time of all members' closures (both loads); "s / valve" is solve s / members.  The last
lines compare the two paths' metrics and steps member by member.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


from jaxvalve import Scene, simulate, simulate_batch  # noqa: E402
from jaxvalve.batch import METRICS  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.timing import compile_timer  # noqa: E402
from jaxvalve.xla_setup import platform_summary  # noqa: E402

TABLE4 = [dict(E1=e1, E2=e2, E3=1.2) for e1 in (0.05, 0.106, 0.18) for e2 in (0.3, 0.569, 0.7)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--h", type=float, default=1.5)
    p.add_argument("--model", default="stvk")
    p.add_argument("--E", type=float, nargs="+", default=[1.0, 1.25, 1.5, 2.0])
    p.add_argument("--table4", action="store_true", help="the mass-spring Table 4 grid")
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    if a.table4:
        scene = Scene(h=a.h, model="mass-spring")
        members = [scene.replace(**m) for m in TABLE4]
    else:
        scene = Scene(h=a.h, model=a.model)
        members = [scene.replace(E=e) for e in a.E]
    mats = [m.material() for m in members]
    valve = build_scene_valve(scene)
    lines = [f"simulate_batch against sequential simulate: {len(mats)} members "
             f"({mats[0].name}), h = {a.h} mm, 3 then 80 mmHg", f"platform: {platform_summary()}",
             "", "| path | compile s | solve s | s / valve | converged |", "|---|---|---|---|---|"]
    results = {}
    for name in ("batch", "sequential"):
        times = []
        for rep in range(2):
            with compile_timer() as ct:
                t0 = time.perf_counter()
                if name == "batch":
                    out = list(simulate_batch(scene, mats, valve=valve, throw=False))
                else:
                    out = [simulate(m, valve=valve, throw=False) for m in members]
                wall = time.perf_counter() - t0
            times.append((ct.seconds, wall))
        results[name] = out
        comp, wall = times[0][0], times[1][1]
        ok = sum(bool(r.converged) for r in out)
        lines.append(f"| {name} | {comp:.1f} | {wall:.2f} | {wall / len(mats):.2f} | "
                     f"{ok}/{len(mats)} |")
        print(lines[-1], flush=True)
    lines += ["", "member: steps per load (batch / sequential), largest metric difference (mm, %)"]
    for i, (b, s) in enumerate(zip(results["batch"], results["sequential"])):
        db = max(abs(b.summary()[k] - s.summary()[k]) for k in METRICS)
        lines.append(f"  {i}: {[x.steps for x in b.solves]} / {[x.steps for x in s.solves]}, "
                     f"{db:.2e}, {'converged' if b.converged else 'NOT converged'}")
    print("\n".join(lines))
    if a.out:
        a.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
