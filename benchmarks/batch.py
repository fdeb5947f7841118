"""Batch evaluation over materials against sequential closures (same valve, same members).

    python benchmarks/batch.py                  # h = 1.5 mm, StVK, E = 1 1.25 1.5 2 MPa
    python benchmarks/batch.py --benchmark      # the benchmark mesh, h = 0.88 mm
    python benchmarks/batch.py --h 2 --E 0.5 0.8 1 1.25 2 --model neo-hookean
    python benchmarks/batch.py --sizes 1 16 64 256  # throughput against the batch size
    python benchmarks/batch.py --sizes 1 16 64 256 --rebuilds members  # the same, with the
                                    # vectorised batch's rebuilds run member by member
    python benchmarks/batch.py --h 2 --E 1 2 0.8 3 --max-steps 5000  # a straggler (0.8 stalls)

One valve is built; the members are closed by `simulate_batch(scene, materials,
valve=valve)` (one jitted vmap over the members, both loads), with each member's solver
loop run in turn (``vectorize=False``, the CPU default), vectorised (``vectorize=True``,
the GPU default, where the last members finish in their own loops), vectorised to the
end (``handoff=0``), and, for comparison, by one `simulate(scene, valve=valve)` per member
(one compiled solve shared by all calls).  Each path runs twice:
the first run compiles (JAX's compile time is reported separately), the second is timed
after compilation.  "solve s" is the wall time of the closures of all members (both loads),
"wall s" adds the host-side metrics; "s / scene" is solve s / members.  The last line
checks that both paths give the same metrics (max difference over members).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("JAXVALVE_CACHE_DIR", "off")

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxvalve  # noqa: E402,F401  (float64)
from jaxvalve.mechanics import materials as M  # noqa: E402
from jaxvalve import valve as V  # noqa: E402
from jaxvalve.batch import METRICS, simulate_batch  # noqa: E402
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet  # noqa: E402
from jaxvalve.scene import BENCHMARK_H, MODELS, Scene  # noqa: E402
from jaxvalve.simulation import simulate  # noqa: E402


def material(model, E, nu):
    if model == "stvk":
        return M.StVenantKirchhoff(E=E, nu=nu)
    if model == "neo-hookean":
        return M.NeoHookean(mu=E / 3)
    if model == "gent":
        return M.Gent(mu=E / 3, Jm=2.3)
    return M.MassSpring.linear(E)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm (default 1.5)")
    ap.add_argument("--benchmark", action="store_true",
                    help=f"the benchmark mesh, h = {BENCHMARK_H} mm")
    ap.add_argument("--model", choices=MODELS, default="stvk")
    ap.add_argument("--E", type=float, nargs="+", default=[1.0, 1.25, 1.5, 2.0],
                    help="Young's moduli of the members, MPa (neo-Hookean, Gent: mu = E/3)")
    ap.add_argument("--nu", type=float, default=0.45, help="StVK Poisson ratio")
    ap.add_argument("--max-steps", type=int, default=None,
                    help="solver step limit per closure (default: the scene's)")
    ap.add_argument("--only-default", action="store_true",
                    help="run only this backend's default batch path (one compile less)")
    ap.add_argument("--sizes", type=int, nargs="+", default=None,
                    help="instead: throughput of the default batch path at these batch sizes "
                         "(members with E spread geometrically over --E's range)")
    ap.add_argument("--rebuilds", choices=("select", "members"), default="select",
                    help="with --sizes: how the vectorised batch runs its pair-list rebuilds "
                         "(`vmap_control.branches`): 'select' (the package's), or 'members', "
                         "member by member, the baseline that 'select' replaced; forces the "
                         "vectorised path")
    args = ap.parse_args(argv)
    if args.rebuilds != "select" and not args.sizes:
        ap.error("--rebuilds needs --sizes")
    h = BENCHMARK_H if args.benchmark else args.h
    scene = Scene(h=h, model=args.model)
    if args.max_steps is not None:
        scene = scene.replace(max_steps=args.max_steps)
    valve = V.build_valve(scene.load_root(), mesh_leaflet(scene.template(), h))
    if args.sizes:
        return scaling(scene, valve, args)
    mats = [material(args.model, e, args.nu) for e in args.E]
    B = len(mats)
    print(f"# {args.model}, h = {h} mm ({len(valve.leaflet.triangles)} triangles a leaflet), "
          f"{B} members E = {args.E} MPa, loads {scene.he_pressure:g} then "
          f"{scene.pressure:g} mmHg, rtol {scene.rtol:g}; {os.cpu_count()} CPU cores")

    rows, results = {}, {}
    for name, vec, handoff in (("batch, member loop (CPU default)", False, None),
                               ("batch, vectorised (GPU default)", True, None),
                               ("batch, vectorised to the end (handoff=0)", True, 0)):
        if args.only_default and (vec != (jax.default_backend() != "cpu") or handoff == 0):
            continue
        # the first call compiles, the second is timed
        kw = dict(valve=valve, throw=False, vectorize=vec, handoff=handoff)
        t0 = time.perf_counter()
        r0 = simulate_batch(scene, mats, **kw)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        rb = simulate_batch(scene, mats, **kw)
        wall = time.perf_counter() - t0
        rows[name] = dict(compile=r0.timings["compile"], first=first, solve=rb.timings["solve"],
                          wall=wall, steps=sum(s.steps for m in rb for s in m.solves),
                          conv=sum(m.converged for m in rb))
        results[name] = rb
    # sequential: the first member's first call compiles; then all members are timed
    t0 = time.perf_counter()
    s0 = [simulate(scene, valve=valve, throw=False).solves]
    comp = sum(s.compile_s for s in s0[0])
    first = time.perf_counter() - t0
    seq, t0 = [], time.perf_counter()
    for mat in mats:
        seq.append(_simulate_material(scene, valve, mat))
    wall = time.perf_counter() - t0
    rows["sequential simulate()"] = dict(
        compile=comp, first=first, solve=sum(s.solve_s for r in seq for s in r.solves),
        wall=wall, steps=sum(s.steps for r in seq for s in r.solves),
        conv=sum(r.converged for r in seq))

    print("\n| path | members | compile s | solve s (after compile) | s / scene | wall s | "
          "FIRE steps (all members) | converged | per scene vs sequential |")
    print("|---|---|---|---|---|---|---|---|---|")
    ref = rows["sequential simulate()"]["solve"] / B
    for name, r in rows.items():
        print(f"| {name} | {B} | {r['compile']:.1f} | {r['solve']:.2f} | {r['solve'] / B:.3f} | "
              f"{r['wall']:.2f} | {r['steps']} | {r['conv']}/{B} | "
              f"{(r['solve'] / B) / ref:.2f} |")
    for name, rb in results.items():
        diff = max(abs(m.summary()[k] - q.summary()[k]) for m, q in zip(rb, seq) for k in METRICS)
        dx = max(float(np.max(np.abs(m.x - q.x))) for m, q in zip(rb, seq))
        print(f"\n{name} vs sequential: max |dx| = {dx:.2e} mm, max metric difference "
              f"{diff:.1e} mm (%); steps per member (3 / 80 mmHg): "
              + " ".join(f"{m.solves[0].steps}/{m.solves[1].steps}" for m in rb))
    print("sequential steps per member: "
          + " ".join(f"{r.solves[0].steps}/{r.solves[1].steps}" for r in seq))


def scaling(scene, valve, args):
    """Throughput of `simulate_batch` (its default path on this backend) against the batch
    size B, with sequential `simulate()` calls of the same members as the reference (at most
    4 of them, timed after compilation).  Each size compiles once (B is a shape).  "solve s"
    includes the closure driver's follow-up of members whose batched attempt failed (their
    barrier-law fallback or continuation, on the host): "follow-up s" of it, for the
    members counted under "of which fell back".
    ``--rebuilds members`` runs the vectorised batch with its rebuilds member by member."""
    vectorize = None
    if args.rebuilds == "members":
        _rebuild_members()
        vectorize = True
    lo, hi = min(args.E), max(args.E)
    print(f"# {args.model}, h = {scene.h} mm ({len(valve.leaflet.triangles)} triangles a "
          f"leaflet), E spread geometrically over [{lo}, {hi}] MPa, loads "
          f"{scene.he_pressure:g} then {scene.pressure:g} mmHg, rtol {scene.rtol:g}; backend "
          f"{jax.default_backend()}, {os.cpu_count()} CPU cores; batch path "
          f"{'vectorised' if vectorize or jax.default_backend() != 'cpu' else 'member loop'}"
          f", rebuilds {args.rebuilds!r}")
    ref_E = np.geomspace(lo, hi, 4) if hi > lo else [lo]
    simulate(scene, valve=valve, throw=False)                      # compiles
    seq = [_simulate_material(scene, valve, material(args.model, e, args.nu)) for e in ref_E]
    seq_s = sum(s.solve_s for r in seq for s in r.solves) / len(seq)
    seq_steps = sum(s.steps for r in seq for s in r.solves) / len(seq)
    print(f"sequential simulate(): {seq_s:.3f} s a scene ({seq_steps:.0f} FIRE steps, "
          f"{1e3 * seq_s / seq_steps:.3f} ms a step), {len(seq)} members timed\n")
    print("| B | compile s | solve s | s / scene | scenes / s | vs sequential | loop steps "
          "(slowest member, both loads) | ms / loop step | converged | of which fell back | "
          "follow-up s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for B in args.sizes:
        mats = [material(args.model, e, args.nu)
                for e in (np.geomspace(lo, hi, B) if B > 1 else [lo])]
        r0 = simulate_batch(scene, mats, valve=valve, throw=False, vectorize=vectorize)
        rb = simulate_batch(scene, mats, valve=valve, throw=False, vectorize=vectorize)
        solve = rb.timings["solve"]
        loop_steps = sum(max(m.solves[k].steps for m in rb) for k in (0, 1))
        print(f"| {B} | {r0.timings['compile']:.1f} | {solve:.2f} | {solve / B:.4f} | "
              f"{B / solve:.1f} | {(solve / B) / seq_s:.3f} | {loop_steps} | "
              f"{1e3 * solve / loop_steps:.3f} | {sum(m.converged for m in rb)}/{B} | "
              f"{sum(any(x.fallback for x in m.solves) for m in rb)} | "
              f"{rb.timings['follow_up']:.2f} |", flush=True)


def _rebuild_members():
    """Make the vectorised batch run its rebuilds member by member: every
    ``branches(policy)`` block of the batch code enters ``branches("members")`` instead.
    For this process only, before anything is traced."""
    import jaxvalve.batch as batch_module
    import jaxvalve.solvers.base as base_module
    from jaxvalve import vmap_control

    def members(_policy):
        return vmap_control.branches("members")

    batch_module.branches = base_module.branches = members


def _simulate_material(scene, valve, mat):
    """`simulate` of the scene with the material ``mat`` (its model's Scene fields)."""
    p = {k: float(getattr(mat, k)) for k in ("E", "nu", "mu", "Jm", "E1", "E2", "E3")
         if hasattr(mat, k)}
    return simulate(scene.replace(**p), valve=valve, throw=False)


if __name__ == "__main__":
    main()
