"""Material sweeps of the paper's Tables 4 and 5 on one valve (batch evaluation).

--table 4: the mass-spring model (3.3) over the grid E1 x E2 (kPa in the paper: E1 = 50,
106, 180; E2 = 300, 569, 700; E3 = 1200; strain breaks 0.175 and 0.3).  The paper lists 7
of the 9 pairs; all 9 are run.
--table 5: each model (mass-spring, StVK with nu = 0.5, neo-Hookean and Gent with
mu = E/3, Jm = 2.3) at E = 0.1, 1 and 10 MPa.

The valve is the benchmark root with the benchmark template (the paper used a patient root
and its template (b) for Table 4); the members of one model run as one batch
(`jaxvalve.batch.simulate_batch`).  Writes DIR/table{4,5}.csv (one row per member:
parameters, every metric, converged, steps and residual of both loads, and the paper's
values where it gives them) and DIR/table{4,5}.png (a heat map of --metric).  Exit codes:
0 every member converged, 2 bad input (the message names the parameter and its range), 3
some member did not converge (the outputs are still written).
"""
from __future__ import annotations

import argparse
import csv
import math
import sys

from ..scene import BENCHMARK_H

#: Table 4 (kPa in the paper; MPa here).
TABLE4_E1 = (0.050, 0.106, 0.180)
TABLE4_E2 = (0.300, 0.569, 0.700)
TABLE4_E3 = 1.2
#: the paper's (h, h_c) in mm for the pairs it lists, keyed by (E1, E2) in MPa
TABLE4_PAPER = {(0.050, 0.300): (18.4, 13.6), (0.050, 0.569): (17.2, 10.9),
                (0.106, 0.300): (17.3, 12.9), (0.106, 0.569): (16.4, 11.6),
                (0.106, 0.700): (15.7, 11.6), (0.180, 0.569): (15.6, 9.7),
                (0.180, 0.700): (15.4, 9.2)}
#: Table 5: models and Young's moduli (MPa).
TABLE5_MODELS = ("mass-spring", "stvk", "neo-hookean", "gent")
TABLE5_E = (0.1, 1.0, 10.0)
#: the paper's (h, h_c, h_C-C) in mm, keyed by (model, E in MPa); it has no neo-Hookean
#: run at E = 0.1 MPa
TABLE5_PAPER = {("mass-spring", 10.0): (15.4, 7.3, 13.1), ("stvk", 10.0): (15.4, 8.3, 15.1),
                ("neo-hookean", 10.0): (13.0, 7.3, 12.9), ("gent", 10.0): (15.5, 8.4, 13.5),
                ("mass-spring", 1.0): (17.3, 10.7, 16.0), ("stvk", 1.0): (16.7, 12.1, 16.2),
                ("neo-hookean", 1.0): (17.4, 8.2, 15.8), ("gent", 1.0): (16.3, 10.5, 15.9),
                ("mass-spring", 0.1): (21.5, 19.6, 20.3), ("stvk", 0.1): (23.7, 19.7, 23.4),
                ("gent", 0.1): (23.6, 19.0, 23.2)}

METRIC_NAMES = {"h_E": "h_E (mm)", "h_CC": "h_C-C (mm)", "h_avr": "h_avr (mm)",
                "NCCA_pct": "NCCA (%)", "h": "h (mm)", "h_c": "h_c (mm)"}


def add_parser(sub):
    p = sub.add_parser(
        "sweep", help="material sweeps of the paper's Tables 4 and 5 (batch evaluation)",
        description=__doc__, allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example: jaxvalve sweep --table 4 --h 1.5 --out sweep4")
    p.add_argument("--table", type=int, required=True, metavar="{4,5}",
                   help="4: mass-spring E1 x E2 grid; 5: each model at E = 0.1, 1, 10 MPa")
    p.add_argument("--h", type=float, default=BENCHMARK_H,
                   help=f"mesh size, mm (default {BENCHMARK_H}, the benchmark mesh)")
    p.add_argument("--out", metavar="DIR",
                   help="write tableN.csv and tableN.png here (default: print only)")
    p.add_argument("--metric", default="h_E", metavar="NAME",
                   help=f"metric of the heat map: one of {', '.join(METRIC_NAMES)} "
                        "(default h_E)")
    g = p.add_argument_group("table 4 (mass-spring, MPa)")
    g.add_argument("--E1", type=float, nargs="+", metavar="E1",
                   help="moduli below the first strain break (default 0.05 0.106 0.18)")
    g.add_argument("--E2", type=float, nargs="+", metavar="E2",
                   help="moduli between the breaks (default 0.3 0.569 0.7)")
    g.add_argument("--E3", type=float, default=TABLE4_E3,
                   help=f"modulus above the second break (default {TABLE4_E3})")
    g = p.add_argument_group("table 5")
    g.add_argument("--models", nargs="+", metavar="MODEL",
                   help=f"models among {', '.join(TABLE5_MODELS)} (default all four)")
    g.add_argument("--E", type=float, nargs="+", metavar="E",
                   help="Young's moduli, MPa (default 0.1 1 10; neo-Hookean, Gent: mu = E/3)")
    g.add_argument("--nu", type=float, default=0.5,
                   help="StVK Poisson ratio (default 0.5, as the paper's Table 5)")
    g.add_argument("--Jm", type=float, default=2.3, help="Gent Jm (default 2.3)")
    g = p.add_argument_group("loads and solver")
    g.add_argument("--pressure", type=float, default=80.0, help="closing load, mmHg (80)")
    g.add_argument("--he-pressure", type=float, default=3.0,
                   help="load of the effective height h_E, mmHg (3)")
    g.add_argument("--rtol", type=float, default=1e-4,
                   help="relative force residual to reach (default 1e-4)")
    g.add_argument("--max-steps", type=int, default=50_000,
                   help="FIRE step limit per load and member (default 50000)")
    g.add_argument("--no-figures", action="store_true", help="skip the heat map")
    return p


# ------------------------------------------------------------------------------ members
def _check(args):
    from ..errors import ParameterError
    if args.table not in (4, 5):
        raise ParameterError(f"--table must be 4 (the mass-spring E1 x E2 grid) or 5 (each "
                             f"model at E = 0.1, 1, 10 MPa); got {args.table}")
    if not (math.isfinite(args.h) and args.h > 0):
        raise ParameterError(f"--h must be a finite mesh size > 0 mm (the benchmark mesh is "
                             f"{BENCHMARK_H}); got {args.h}")
    if args.metric not in METRIC_NAMES:
        raise ParameterError(f"--metric must be one of {list(METRIC_NAMES)}; got "
                             f"{args.metric!r}")
    for name in ("E1", "E2", "E", "E3"):
        vals = getattr(args, name)
        vals = [vals] if isinstance(vals, float) else (vals or [])
        for v in vals:
            if not (math.isfinite(v) and v > 0):
                raise ParameterError(f"--{name} values must be finite moduli > 0 MPa; got {v}")
    for m in args.models or ():
        if m not in TABLE5_MODELS:
            raise ParameterError(f"--models: unknown model {m!r}; valid: "
                                 f"{', '.join(TABLE5_MODELS)}")


def table_members(args):
    """[(model, [(labels, material), ...]), ...]: the batches of the sweep, one per model.
    labels: the grid coordinates of the member (E1, E2 or model, E)."""
    from ..mechanics import materials as M
    if args.table == 4:
        e1s, e2s = args.E1 or TABLE4_E1, args.E2 or TABLE4_E2
        return [("mass-spring", [(dict(E1=e1, E2=e2), M.MassSpring(E1=e1, E2=e2, E3=args.E3))
                                 for e1 in e1s for e2 in e2s])]
    out = []
    for model in args.models or TABLE5_MODELS:
        mats = []
        for e in args.E or TABLE5_E:
            mat = {"mass-spring": lambda: M.MassSpring.linear(e),
                   "stvk": lambda: M.StVenantKirchhoff(E=e, nu=args.nu),
                   "neo-hookean": lambda: M.NeoHookean(mu=e / 3.0),
                   "gent": lambda: M.Gent(mu=e / 3.0, Jm=args.Jm)}[model]()
            mats.append((dict(E=e), mat))
        out.append((model, mats))
    return out


def _paper(table, model, labels):
    """The paper's values for a member (dict, empty where it gives none)."""
    if table == 4:
        v = TABLE4_PAPER.get((round(labels["E1"], 6), round(labels["E2"], 6)))
        return {} if v is None else dict(paper_h=v[0], paper_h_c=v[1])
    v = TABLE5_PAPER.get((model, round(labels["E"], 6)))
    return {} if v is None else dict(paper_h=v[0], paper_h_c=v[1], paper_h_CC=v[2])


# ------------------------------------------------------------------------------ outputs
def write_csv(path, rows):
    """One row per member; the columns are the union of the rows' keys, in first-seen
    order; a metric that could not be measured (non-finite state) is left blank."""
    cols = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v)
                            and not k.startswith("residual") else v) for k, v in r.items()})
    return path


def heat_map(path, table, rows, metric):
    """A heat map of ``metric`` over the sweep's grid: E1 x E2 (table 4) or model x E
    (table 5).  Cells of members that did not converge are hatched and marked 'n.c.'."""
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: no global state

    if table == 4:
        ys = sorted({r["E1"] for r in rows})
        xs = sorted({r["E2"] for r in rows})
        key = lambda r: (ys.index(r["E1"]), xs.index(r["E2"]))
        ylab, xlab = "E1 (MPa)", "E2 (MPa)"
        yticks, xticks = [f"{v:g}" for v in ys], [f"{v:g}" for v in xs]
    else:
        ys = list(dict.fromkeys(r["model"] for r in rows))
        xs = sorted({r["E"] for r in rows})
        key = lambda r: (ys.index(r["model"]), xs.index(r["E"]))
        ylab, xlab = "model", "E (MPa)"
        yticks, xticks = ys, [f"{v:g}" for v in xs]
    val = np.full((len(ys), len(xs)), np.nan)
    conv = np.zeros((len(ys), len(xs)), bool)
    for r in rows:
        i, j = key(r)
        val[i, j], conv[i, j] = r[metric], r["converged"]
    fig = Figure(figsize=(1.6 * len(xs) + 3, 0.8 * len(ys) + 2))
    ax = fig.add_subplot()
    ok = conv & np.isfinite(val)
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.85")
    # the colours show the converged members only; the others are grey, hatched, 'n.c.'
    im = ax.imshow(np.ma.masked_where(~ok, val), cmap=cmap, aspect="auto")
    fig.colorbar(im, ax=ax, label=METRIC_NAMES[metric])
    lo, hi = (np.min(val[ok]), np.max(val[ok])) if ok.any() else (0.0, 1.0)
    for i in range(len(ys)):
        for j in range(len(xs)):
            v = val[i, j]
            txt = "" if not np.isfinite(v) else f"{v:.2f}"
            if not ok[i, j]:
                ax.add_patch(_hatch(i, j))
                txt, colour = (txt + "\n" if txt else "") + "n.c.", "k"
            else:
                colour = "k" if hi > lo and (v - lo) / (hi - lo) > 0.6 else "w"
            ax.text(j, i, txt, ha="center", va="center", color=colour, fontsize=9)
    ax.set_xticks(range(len(xs)), xticks)
    ax.set_yticks(range(len(ys)), yticks)
    ax.set_xlabel(xlab)
    ax.set_ylabel(ylab)
    ax.set_title(f"Table {table}: {METRIC_NAMES[metric]}")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def _hatch(i, j):
    from matplotlib.patches import Rectangle
    return Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="//", edgecolor="0.6",
                     linewidth=0)


def _bar(done, total, width=24):
    k = round(width * done / total) if total else width
    return f"[{'#' * k}{'.' * (width - k)}] {done}/{total} members"


def _print_table(rows, table, out):
    cols = (["E1", "E2"] if table == 4 else ["model", "E"]) + list(METRIC_NAMES) + [
        "converged"]
    head = ["E1 MPa", "E2 MPa"] if table == 4 else ["model", "E MPa"]
    head += [METRIC_NAMES[m].replace(" (mm)", "").replace(" (%)", " %") for m in METRIC_NAMES]
    head += ["converged"]
    cells = [[_fmt(r.get(c)) for c in cols] for r in rows]
    w = [max(len(h), *(len(c[k]) for c in cells)) for k, h in enumerate(head)]
    print("  ".join(h.rjust(w[k]) for k, h in enumerate(head)), file=out)
    for c in cells:
        print("  ".join(v.rjust(w[k]) for k, v in enumerate(c)), file=out)


def _fmt(v):
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.3g}" if abs(v) < 1 else f"{v:.2f}"
    return str(v)


# ------------------------------------------------------------------------------ run
def _run_groups(args, scene, groups, total, hb):
    """Close every member of every (model, members) group; the CSV rows, in order."""
    from ..batch import simulate_batch
    from ..geometry.leaflet_mesh import mesh_leaflet
    from ..mechanics.inflation import inflation_limit
    from ..valve import model as V

    say = hb.say
    say(f"table {args.table}: {total} members in {len(groups)} batch"
        f"{'es' * (len(groups) != 1)}, h = {args.h} mm")
    say("building the valve (benchmark root and template)")
    valve = V.build_valve(scene.load_root(), mesh_leaflet(scene.template(), args.h))
    say(f"  3 x {len(valve.leaflet.triangles)} triangles")
    rows, done = [], 0
    hb.count(0, total)
    for model, members in groups:
        res = simulate_batch(scene.replace(model=model), [m for _, m in members],
                             valve=valve, throw=False, progress=lambda m: say("  " + m))
        for (labels, mat), row in zip(members, res.rows()):
            row = {"table": args.table, **labels, **row}
            lims = [row[f"limit_pressure_{k}"] for k in ("he", "closing")
                    if row[f"result_{k}"] == "limit_point"]
            if lims:            # does the material explain it? (docs/limit-points.md)
                row["inflation"] = inflation_limit(mat, scene.thickness).describe(lims[0])
            row["member"] = len(rows)
            row.update(_paper(args.table, model, labels))
            rows.append(row)
        done += len(members)
        hb.count(done, total)
        say(f"{_bar(done, total)}  ({model}: {res.timings['solve']:.1f} s solve, "
            f"{res.timings['compile']:.1f} s compile)")
    return rows


def run(args) -> int:
    from ..errors import JaxvalveError
    from ..scene import Scene
    from ..io.files import check_out_dir
    from ..progress import Heartbeat

    def say(msg):
        print(f"[jaxvalve sweep] {msg}", file=sys.stderr, flush=True)

    _check(args)
    groups = table_members(args)
    if args.max_steps <= 0:
        raise JaxvalveError(f"--max-steps must be a positive integer; got {args.max_steps}")
    scene = Scene(h=args.h, model=groups[0][0], rtol=args.rtol, max_steps=args.max_steps,
                  pressure=args.pressure, he_pressure=args.he_pressure)
    out = check_out_dir(args.out)           # before the solves: a bad --out loses nothing
    total = sum(len(m) for _, m in groups)
    with Heartbeat(say, unit="members") as hb:   # a line at least every 2 s
        rows = _run_groups(args, scene, groups, total, hb)
    written = []
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
            written.append(write_csv(out / f"table{args.table}.csv", rows))
            if not args.no_figures:
                written.append(heat_map(out / f"table{args.table}.png", args.table, rows,
                                        args.metric))
        except OSError as e:
            raise JaxvalveError(f"cannot write the outputs to '{out}': {e}") from None
    _print_table(rows, args.table, sys.stdout)
    for p in written:
        say(f"wrote {p}")
    bad = [r for r in rows if not r["converged"]]
    if bad:
        what = "; ".join(
            f"member {r['member']} ({r['model']}, "
            + ", ".join(f"{k}={r[k]:g}" for k in (("E1", "E2") if args.table == 4 else ("E",)))
            + "): " + ", ".join(f"{t} mmHg {r['result_' + k]} residual {r['residual_' + k]:.2e}"
                                for k, t in (("he", args.he_pressure), ("closing", args.pressure))
                                if r["result_" + k] != "successful")
            + (f" ({r['inflation']})" if r.get("inflation") else "")
            for r in bad)
        print(f"jaxvalve sweep: warning: {len(bad)} of {len(rows)} members did NOT converge "
              f"(rtol {args.rtol:g}): {what}", file=sys.stderr)
        return 3
    return 0
