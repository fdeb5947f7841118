"""Stress suite for numerical stability: every run converges cleanly or says why not.

    nice -n 15 .venv/bin/python benchmarks/stress.py            # full matrix + hard cases
    .venv/bin/python benchmarks/stress.py --quick               # a small part (minutes)
    .venv/bin/python benchmarks/stress.py --models stvk --precisions float64 --templates b

Matrix: E in {0.05, 0.1, 1, 10, 20} MPa x P in {3, 80, 200} mmHg x the paper's Fig. 3
templates (a), (b), (c) (made valid: b = |AD|/2 + 1 mm; the templates as given are tried
too and must be refused) x the four models x float32 / float64.  Hard cases, per model and
precision: a randomly perturbed mesh, a mesh with sliver triangles (smallest angle ~2-3
degrees), each at E = 1 MPa, and a start with the leaflets pushed 0.75-2.5 mm through
one another (80 mmHg); Gent near its stretch limit (Jm = 0.3, 0.1); the mass-spring
model with the piecewise modulus of eq. 3.3 (paper Tables 4-5).  Each run is classified
by `stress_suite.py` as converged (all checks passed), reported (non-convergence with its
cause, or a clear error) or silently wrong.

Prints the pass table (per model x precision: tried, converged, reported, silently wrong)
and the list of runs that did not converge, and writes ``benchmarks/results/stress.csv``
(one row per run) and ``benchmarks/results/stress.txt`` (the printed table).  Mesh size
h = 2 mm (3 x 333 triangles), at most 4000 FIRE steps a closure (1000, then 3000 unless
the leaflets have left the root).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: the hard cases beside the matrix (``--cases``)
HARD_CASES = ("paper-template", "perturbed", "slivers", "penetration", "gent-limit",
              "piecewise")


def _parse(argv):
    from jaxvalve.scene import MODELS, PRECISIONS
    from stress_suite import MATRIX_E, MATRIX_P, STRESS_H
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS)
    ap.add_argument("--templates", nargs="+", default=["a", "b", "c"], choices=["a", "b", "c"])
    ap.add_argument("--E", nargs="+", type=float, default=list(MATRIX_E), help="MPa")
    ap.add_argument("--P", nargs="+", type=float, default=list(MATRIX_P), help="mmHg")
    ap.add_argument("--h", type=float, default=STRESS_H, help="mesh size, mm")
    ap.add_argument("--max-steps", type=int, default=4000, help="FIRE steps a closure")
    ap.add_argument("--rtol", type=float, default=1e-4)
    ap.add_argument("--no-special", action="store_true", help="only the matrix")
    ap.add_argument("--no-matrix", action="store_true", help="only the hard cases")
    ap.add_argument("--cases", nargs="+", choices=HARD_CASES, default=list(HARD_CASES),
                    help="the hard cases to run (default all)")
    ap.add_argument("--quick", action="store_true",
                    help="template b, E in {0.1, 1, 20}, P in {3, 80}, fewer hard cases")
    ap.add_argument("--out", default=str(HERE / "results"), help="results folder")
    ap.add_argument("--name", default="stress", help="file stem of the outputs")
    ap.add_argument("--render", metavar="CSV",
                    help="run nothing: print the tables of a finished run from its CSV "
                         "(with today's analysis of its limit points) and write NAME.txt")
    return ap.parse_args(argv)


def _text(S, records, head: str) -> str:
    table = S.summarise(records)
    t = table["all", ""]
    rates = [S.pass_rate(records, p) for p in ("float64", "float32") if ("all", p) in table]
    return (head + f"Runs tried {t['tried']}, converged {t['converged']}, reported as "
            f"non-converged {t['reported']} (of which caught by the state guard of "
            f"valve.close {t['guard']}; at a limit point the inflation analysis predicts "
            f"{t['limit']}), silently wrong {t['silent']}.\n"
            + "".join(f"Converged or at a predicted limit point, {r}.\n" for r in rates)
            + "\n" + S.format_table(records) + "\n")


def main(argv=None):
    import jax
    jax.config.update("jax_enable_x64", True)
    import stress_suite as S
    from jaxvalve.geometry.leaflet_mesh import mesh_leaflet

    args = _parse(argv)
    out = Path(args.out)
    if args.render:
        out.mkdir(parents=True, exist_ok=True)
        records = S.read_csv(args.render)
        old = Path(args.render).with_suffix(".txt")
        head = ""
        if old.exists():          # the finished run's settings and wall time
            import re
            first, rest = old.read_text().split("\n", 1)
            wall = re.search(r"([\d.]+ min wall)", rest.split("\n\n", 1)[0])
            head = first.rstrip(".") + (f"; {wall.group(1)}." if wall else ".") + "\n"
        text = _text(S, records, head)
        print(text)
        (out / f"{args.name}.txt").write_text(text)
        print(f"wrote {out / (args.name + '.txt')}")
        return 1 if S.summarise(records)["all", ""]["silent"] else 0
    if args.quick:
        args.templates, args.E, args.P = ["b"], [0.1, 1.0, 20.0], [3.0, 80.0]
    kw = dict(rtol=args.rtol, max_steps=args.max_steps)
    records = []
    t_start = time.perf_counter()

    out.mkdir(parents=True, exist_ok=True)
    partial = out / f"{args.name}.partial.csv"
    partial.unlink(missing_ok=True)

    def show(r):
        S.append_csv(r, partial)     # the runs so far, should the matrix be stopped
        print(f"[{time.perf_counter() - t_start:7.1f} s] {r.outcome:9s} {r.case:14s} "
              f"{r.template:6s} {r.mesh:9s} {r.model:11s} {r.precision:7s} E={r.E:<5g} "
              f"P={r.P:<4g} {r.extra:22s} steps={r.steps:<6d} res={r.residual:.1e} "
              f"cross={r.crossings} {r.wall_s:5.1f} s  {r.cause}", file=sys.stderr, flush=True)

    cases = set() if args.no_special else set(args.cases)
    if "paper-template" in cases:
        records += S.run_invalid_templates(on_record=show)
    tpls = S.paper_templates()
    base = mesh_leaflet(tpls["b"][0], args.h)
    valves = {k: S.make_valve(tpls[k][0], args.h, S.mapped_mesh(base, tpls[k][0]))
              for k in args.templates}
    sb = tpls["b"][0]
    special = {}
    if "perturbed" in cases:
        special["perturbed"] = S.make_valve(sb, args.h, S.perturbed_mesh(base, 0.3, seed=0))
    if "slivers" in cases:
        special["slivers"] = S.make_valve(sb, args.h, S.poor_mesh(base, 4, 3.0, seed=1))
    e_special = (1.0,)
    p_special = tuple(args.P)
    for model in args.models:
        for prec in args.precisions:
            common = dict(model=model, precision=prec, **kw)
            if not args.no_matrix:
                for k in args.templates:
                    records += S.run_group(valves[k], template=k, mesh="regular", Es=args.E,
                                           Ps=args.P, on_record=show, **common)
            if args.no_special:
                continue
            for name, v in special.items():
                records += S.run_group(v, template="b", mesh=name, Es=e_special,
                                       Ps=p_special, case=name, on_record=show, **common)
            depths = (1.5,) if args.quick or prec == "float32" else (0.75, 2.5)
            if "penetration" in cases:
                vb = valves.get("b") or S.make_valve(sb, args.h, base)
                x_closed = S.closed_state(vb, P=80.0, **common)
                for depth in depths:
                    records.append(S.run_penetration(vb, template="b", depth=depth, P=80.0,
                                                     x_closed=x_closed, on_record=show,
                                                     **common))
            if model == "gent" and "gent-limit" in cases:
                jms = (0.3,) if args.quick else (0.3, 0.1)
                for jm in jms:
                    records += S.run_group(valves.get("b") or S.make_valve(sb, args.h, base),
                                           template="b", mesh="regular",
                                           Es=(0.1, 1.0), Ps=(3.0, 80.0, 200.0),
                                           case="gent-limit", extra=dict(Jm=jm),
                                           on_record=show, **common)
            if model == "mass-spring" and "piecewise" in cases:
                sets = ((0.1, 1.0, 1.2),) if args.quick else (
                    (0.1, 1.0, 1.2), (0.05, 0.3, 1.2), (0.106, 0.569, 1.2), (0.18, 0.7, 1.2))
                for e1, e2, e3 in sets:
                    records += S.run_group(valves.get("b") or S.make_valve(sb, args.h, base),
                                           template="b", mesh="regular", Es=(e2,),
                                           Ps=(3.0, 80.0, 200.0), case="piecewise",
                                           extra=dict(E1=e1, E2=e2, E3=e3),
                                           on_record=show, **common)
    wall = time.perf_counter() - t_start
    t = S.summarise(records)["all", ""]
    head = (f"jaxvalve stress suite: h = {args.h} mm ({len(base.triangles)} triangles a "
            f"leaflet), rtol {args.rtol:g}, at most {args.max_steps} FIRE steps a closure; "
            f"models {' '.join(args.models)}; precisions {' '.join(args.precisions)}; "
            f"templates {' '.join(args.templates)}; E {args.E} MPa; P {args.P} mmHg; "
            f"{wall / 60:.1f} min wall.\n")
    text = _text(S, records, head)
    print(text)
    (out / f"{args.name}.txt").write_text(text)
    S.write_csv(records, out / f"{args.name}.csv")
    partial.unlink(missing_ok=True)
    print(f"wrote {out / (args.name + '.txt')} and {out / (args.name + '.csv')}")
    return 1 if t["silent"] else 0


if __name__ == "__main__":
    sys.exit(main())
