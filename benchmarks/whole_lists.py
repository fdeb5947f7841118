"""The optimiser's closures on whole contact pair lists against the prefix switch.

    python benchmarks/whole_lists.py [--rounds 2] [--h 0.88]
    python benchmarks/whole_lists.py --simulate [--rounds 2] [--h 0.88]

`optimize.Evaluator` closes the valve at 80 mmHg only (the default objective) with
``equilibrium.solve(..., whole_lists=True)``: the soft-min contact is traced on its whole
pair list instead of a `lax.switch` over up to three prefixes of it. Each variant runs in
its own fresh process with the compilation cache off, alternating, --rounds times:

* first forward: the first `Evaluator.forward` at the start template (trace + compile of
  the solve and of the metrics program, then one closure from the placement), s;
* trace / compile: JAX's tracing and XLA compile time inside it (`jax.monitoring`), s;
* placement: a closure from the placement (the final check's), s after compilation;
* warm: a closure of a template 0.3 mm smaller from the start's closed state (a line-search
  trial's), s after compilation.

Prints one row per process and the medians' ratios (prefixes / whole lists).

--simulate: `jaxvalve.simulate` (3 mmHg, then 80 mmHg from there) instead, with every
solve of the process traced inside `contact.neighbours.whole_lists` for the whole-list
variant (simulate itself keeps the prefixes): its first run's compile time, then each
closure's time after compilation (best of two more runs).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import dataclasses, json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)
import numpy as np
from jax import monitoring
spent = {"trace": 0.0, "compile": 0.0}
def listen(event, secs, **kw):
    if event.endswith("jaxpr_trace_duration"):
        spent["trace"] += secs
    elif event.endswith("backend_compile_duration"):
        spent["compile"] += secs
monitoring.register_event_duration_secs_listener(listen)
from jaxvalve import Scene
from optimize import Objective
from optimize.evaluate import Evaluator
whole, h = sys.argv[1] == "1", float(sys.argv[2])
sc = Scene(h=h, rtol=1e-6)
ev = Evaluator(sc, dataclasses.replace(Objective(), area_ref=sc.template().area))
ev.whole_lists = whole
rab = np.array([sc.r, sc.a, sc.b])
t0 = time.perf_counter()
e0 = ev.forward(rab)
first = time.perf_counter() - t0
assert e0.converged, e0.reason
out = dict(first=first, **spent, steps0=e0.solves[0]["steps"], value=e0.value)
place, warm = [], []
for _ in range(2):
    e = ev.forward(rab, None)
    place.append(e.solves[0]["seconds"])
    out["dvalue"] = abs(e.value - e0.value)
for _ in range(2):
    e = ev.forward(rab - 0.3, e0)
    warm.append(e.solves[0]["seconds"])
    out["warm_value"] = e.value
out.update(placement=min(place), warm=min(warm), warm_steps=e.solves[0]["steps"])
print("RESULT " + json.dumps(out))
"""

CHILD_SIM = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)
import jaxvalve
from jaxvalve import Scene
from jaxvalve.contact.neighbours import whole_lists
whole, h = sys.argv[1] == "1", float(sys.argv[2])
if whole:
    held = whole_lists()      # kept referenced: the context ends when it is collected
    held.__enter__()
t0 = time.perf_counter()
r = jaxvalve.simulate(Scene(h=h))
first = time.perf_counter() - t0
out = dict(first=first, compile=sum(s.compile_s for s in r.solves),
           steps=[s.steps for s in r.solves], converged=all(s.converged for s in r.solves))
best = [float("inf")] * 2
for _ in range(2):
    r = jaxvalve.simulate(Scene(h=h))
    best = [min(b, s.wall_s) for b, s in zip(best, r.solves)]
out.update(p3=best[0], p80=best[1], h_c=float(r.metrics.h_c))
print("RESULT " + json.dumps(out))
"""


def run(whole: bool, h: float, child: str = CHILD) -> dict:
    p = subprocess.run([sys.executable, "-c", child, "1" if whole else "0", str(h)],
                       cwd=ROOT, capture_output=True, text=True)
    line = [s for s in p.stdout.splitlines() if s.startswith("RESULT ")]
    if p.returncode != 0 or not line:
        raise SystemExit(f"child failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return json.loads(line[0][7:])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--h", type=float, default=0.88)
    ap.add_argument("--simulate", action="store_true")
    args = ap.parse_args(argv)
    if args.simulate:
        return simulate_table(args)
    rows = []
    for _ in range(args.rounds):
        for whole in (False, True):
            rows.append((whole, run(whole, args.h)))
    print(f"Evaluator closures at 80 mmHg, h = {args.h} mm, default objective; fresh process "
          f"each, compilation cache off")
    print(f"{'contact lists':>14} {'first fwd s':>11} {'trace s':>8} {'compile s':>9} "
          f"{'placement s':>11} {'warm s':>7} {'steps':>11} {'f':>10}")
    for whole, r in rows:
        print(f"{'whole' if whole else 'prefixes':>14} {r['first']:11.2f} {r['trace']:8.2f} "
              f"{r['compile']:9.2f} {r['placement']:11.3f} {r['warm']:7.3f} "
              f"{r['steps0']:>5d}/{r['warm_steps']:<5d} {r['value']:10.6f}")
    med = lambda key, w: statistics.median(r[key] for ww, r in rows if ww == w)  # noqa: E731
    print("ratios prefixes / whole lists (medians): " + ", ".join(
        f"{k} {med(k, False) / med(k, True):.2f}"
        for k in ("first", "trace", "compile", "placement", "warm")))
    vals = {w: [r["value"] for ww, r in rows if ww == w] for w in (False, True)}
    gap = max(abs(a - b) for a in vals[False] for b in vals[True])
    print(f"largest objective difference between the variants: {gap:.1e}")


def simulate_table(args):
    rows = [(w, run(w, args.h, CHILD_SIM)) for _ in range(args.rounds) for w in (False, True)]
    print(f"simulate(Scene(h={args.h})), fresh process each, compilation cache off")
    print(f"{'contact lists':>14} {'first run s':>11} {'compile s':>9} {'3 mmHg s':>8} "
          f"{'80 mmHg s':>9} {'steps':>10} {'h_c mm':>8}")
    for whole, r in rows:
        print(f"{'whole' if whole else 'prefixes':>14} {r['first']:11.2f} {r['compile']:9.2f} "
              f"{r['p3']:8.2f} {r['p80']:9.2f} {'/'.join(map(str, r['steps'])):>10} "
              f"{r['h_c']:8.4f}{'' if r['converged'] else '  NOT CONVERGED'}")
    med = lambda key, w: statistics.median(r[key] for ww, r in rows if ww == w)  # noqa: E731
    print("ratios prefixes / whole lists (medians): " + ", ".join(
        f"{k} {med(k, False) / med(k, True):.2f}" for k in ("first", "compile", "p3", "p80")))


if __name__ == "__main__":
    main()
