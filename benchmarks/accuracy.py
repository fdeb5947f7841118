"""Run time against error: every model, mesh size, solver, tolerance and precision.

    python benchmarks/accuracy.py                 # the full study (about an hour here)
    python benchmarks/accuracy.py --quick         # a few minutes: StVK, h = 2 and 1.5 mm
    python benchmarks/accuracy.py --report        # table, orders and figure from the CSV

Each setting closes the benchmark valve (`Scene()`, 3 then 80 mmHg, `simulate`) and is
compared, metric by metric, with the same model's reference: the finest mesh closed by
FIRE to a relative residual of 1e-6.  The whole study (``--full``, default StVK):

- reference on h = 0.44 mm, half the paper's mesh size;
- FIRE at rtol 1e-4 (the default) on meshes h = 4 ... 0.44 mm;
- FIRE at rtol 1e-3 and 1e-5 on h = 2 ... 0.88 mm;
- the paper's Algorithm 2.1 (damped fixed point, its own stop rule ||dx^n|| < 1e-3
  ||dx^0||, at most 60 000 steps) on h = 2 and 1.5 mm;
- float32 FIRE at rtol 1e-4 and 1e-3 on h = 2 and 1.5 mm.

The other models get a reduced study (see `settings`): the same reference and meshes, with
the other tolerances only on h = 2 and 0.88 mm, and Algorithm 2.1 and float32 only on h = 2.

Per row: convergence of both closures, steps, wall time of the two closures after
compilation (a second, warm run where the first took under 5 s, else the first run less its
measured compile time), compile time (`jax.monitoring`), peak resident memory of the run
(VmHWM, reset before each run through /proc/self/clear_refs; the process's resident memory
before the run is recorded beside it), the six metrics and their
errors.  Rows are appended to ``benchmarks/results/accuracy.csv`` as they finish; a rerun
skips the rows already there (``--fresh`` starts over).  The report prints the table, the
cheapest setting per model with every height within 0.1 mm of the reference, the observed
order of mesh convergence per metric (least squares of log|error| on log h over the
converged FIRE meshes h = 2 ... 0.62 mm), and draws ``accuracy_pareto.png``.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import time
from pathlib import Path

import jax
import numpy as np

from jaxvalve import Scene, simulate
from jaxvalve.scene import MODELS
from jaxvalve.simulation import build_scene_valve

RESULTS = Path(__file__).resolve().parent / "results"
HEIGHTS = ("h_E", "h_CC", "h_avr", "h_max", "h_c")    # mm (h_max: the metric h); NCCA (%) apart
METRICS = HEIGHTS + ("NCCA_pct",)
REF = dict(h=0.44, solver="engine", rtol=1e-6, precision="float64")
KEY = ("model", "solver", "rtol", "precision", "h")
TOL_MM = 0.1


def settings(models, quick=False, full=("stvk",)):
    """The study's settings (dicts of KEY), each model's reference first.  Models in
    ``full`` get the whole study; the others a reduced one (the same reference on h =
    0.44 mm and FIRE 1e-4 on h = 4 ... 0.44 mm, but 1e-3 and 1e-5 on h = 2 and 0.88 mm
    only, and Algorithm 2.1 and float32 on h = 2 mm only)."""
    out = []
    f64 = dict(solver="engine", precision="float64")
    if quick:
        for m in models:
            out += [dict(model=m, **dict(REF, h=1.5)),
                    dict(model=m, rtol=1e-4, h=2.0, **f64),
                    dict(model=m, solver="engine", rtol=1e-4, precision="float32", h=2.0),
                    dict(model=m, solver="paper", rtol=0.0, precision="float64", h=2.0)]
        return out
    for m in models:
        whole = m in full
        out.append(dict(model=m, **REF))
        meshes = (4.0, 3.0, 2.0, 1.5, 1.2, 0.88, 0.62, 0.44)
        out += [dict(model=m, rtol=1e-4, h=h, **f64) for h in meshes]
        for rtol in (1e-3, 1e-5):
            out += [dict(model=m, rtol=rtol, h=h, **f64)
                    for h in ((2.0, 1.5, 1.2, 0.88) if whole else (2.0, 0.88))]
        out += [dict(model=m, solver="paper", rtol=0.0, precision="float64", h=h)
                for h in ((2.0, 1.5) if whole else (2.0,))]
        out += [dict(model=m, solver="engine", rtol=rtol, precision="float32", h=h)
                for rtol in (1e-4, 1e-3) for h in ((2.0, 1.5) if whole else (2.0,))]
    return out


def _key(s):
    return (s["model"], s["solver"], float(s["rtol"]), s["precision"], float(s["h"]))


def _peak_reset():
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_mb(field="VmHWM"):
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def run_setting(s, valve):
    """Close the benchmark valve with setting ``s``; returns the CSV row (dict)."""
    scene = Scene(h=s["h"], model=s["model"], solver=s["solver"],
                  rtol=s["rtol"] if s["solver"] == "fire" else 1e-4,
                  precision=s["precision"],
                  max_steps=60_000 if s["solver"] == "paper" else 50_000)
    _peak_reset()
    rss0 = _peak_mb("VmRSS")
    t0 = time.perf_counter()
    res = simulate(scene, throw=False, valve=valve)
    first_wall = time.perf_counter() - t0
    compile_s = sum(r.compile_s for r in res.solves)
    solve_s = sum(r.solve_s for r in res.solves)
    timed = "first-less-compile"
    if solve_s < 5.0:
        res = simulate(scene, throw=False, valve=valve)
        solve_s = sum(r.wall_s for r in res.solves)
        timed = "warm"
    summ = res.summary()
    row = dict({k: s[k] for k in KEY}, triangles=len(valve.leaflet.triangles), converged=res.converged,
               results="/".join(r.result for r in res.solves),
               steps="/".join(str(r.steps) for r in res.solves),
               residual=max(r.residual for r in res.solves),
               solve_s=solve_s, compile_s=compile_s, first_wall_s=first_wall, timed=timed,
               peak_rss_mb=_peak_mb(), rss_before_mb=rss0)
    summ["h_max"] = summ.pop("h")          # the metric h; "h" is the mesh size here
    row.update({m: summ[m] for m in METRICS})
    return row


def read_rows(path):
    if not path.exists():
        return []
    with path.open() as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in ("rtol", "h", "residual", "solve_s", "compile_s", "first_wall_s",
                  "peak_rss_mb", "rss_before_mb") + METRICS:
            r[k] = float(r[k])
        r["triangles"] = int(r["triangles"])
        r["converged"] = r["converged"] == "True"
    return rows


def run(models, path, quick=False, full=("stvk",), say=print):
    done = {_key(r) for r in read_rows(path)}
    valves = {}
    todo = [s for s in settings(models, quick, full) if _key(s) not in done]
    say(f"{len(todo)} settings to run ({len(done)} already in {path.name})")
    for i, s in enumerate(todo):
        if s["h"] not in valves:
            valves[s["h"]] = build_scene_valve(Scene(h=s["h"]))
        row = run_setting(s, valves[s["h"]])
        jax.clear_caches()      # each setting compiles its own solve; keep memory flat
        new = not path.exists()
        with path.open("a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(row))   # KEY first, in one fixed order
            if new:
                w.writeheader()
            w.writerow(row)
        say(f"[{i + 1}/{len(todo)}] {s['model']:11s} {s['solver']:5s} rtol {s['rtol']:7.0e} "
            f"{s['precision']} h {s['h']:4.2f}: {row['results']} steps {row['steps']}, "
            f"{row['solve_s']:.2f} s (+{row['compile_s']:.1f} s compile), "
            f"{row['peak_rss_mb']:.0f} MB")


def retime(path, meshes, say=print):
    """Time again, on a quiet machine, the converged FIRE rows on ``meshes`` (their solve
    and compile times are replaced; the metrics must come out the same)."""
    rows = read_rows(path)
    valves = {}
    for r in rows:
        if not (r["solver"] == "fire" and r["converged"] and r["h"] in meshes
                and (r["rtol"], r["h"]) != (REF["rtol"], REF["h"])):
            continue
        if r["h"] not in valves:
            valves[r["h"]] = build_scene_valve(Scene(h=r["h"]))
        new = run_setting({k: r[k] for k in KEY}, valves[r["h"]])
        jax.clear_caches()
        moved = max(abs(new[m] - r[m]) for m in METRICS)
        say(f"{r['model']:11s} {_label(r):16s} h {r['h']:4.2f}: {r['solve_s']:.2f} -> "
            f"{new['solve_s']:.2f} s (metrics moved {moved:.1e})")
        r.update({k: new[k] for k in ("solve_s", "compile_s", "first_wall_s", "timed",
                                      "peak_rss_mb", "rss_before_mb")})
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _label(r):
    if r["solver"] == "paper":
        return "Alg. 2.1 (own stop)"
    return f"FIRE {r['rtol']:.0e}" + (" f32" if r["precision"] == "float32" else "")


def with_errors(rows):
    """Rows (not the references) with err_<metric> against their model's reference."""
    refs = {}
    for r in rows:   # per model: the tightest float64 FIRE tolerance on the finest mesh
        if r["solver"] == "fire" and r["precision"] == "float64":
            q = refs.get(r["model"])
            if q is None or (r["rtol"], r["h"]) < (q["rtol"], q["h"]):
                refs[r["model"]] = r
    out = []
    for r in rows:
        ref = refs.get(r["model"])
        if ref is None or r is ref:
            continue
        e = {f"err_{m}": r[m] - ref[m] for m in METRICS}
        e["max_height_err"] = max(abs(e[f"err_{m}"]) for m in HEIGHTS)
        out.append(dict(r, **e))
    return out, refs


def mesh_orders(rows, model):
    """Observed order p per metric: |error| ~ C h^p over converged FIRE 1e-4 float64 rows
    with 0.6 <= h <= 2 (errors against the finest-mesh reference)."""
    sel = [r for r in rows if r["model"] == model and r["solver"] == "fire"
           and r["rtol"] == 1e-4 and r["precision"] == "float64" and r["converged"]
           and 0.6 <= r["h"] <= 2.0]
    orders = {}
    for m in METRICS:
        h = np.array([r["h"] for r in sel])
        e = np.abs([r[f"err_{m}"] for r in sel])
        ok = e > 1e-9
        orders[m] = (float(np.polyfit(np.log(h[ok]), np.log(e[ok]), 1)[0])
                     if ok.sum() >= 3 else math.nan)
    return orders


def report(path, say=print, figure=True):
    rows, refs = with_errors(read_rows(path))
    if not rows:
        say("no rows")
        return
    say("\nReferences (FIRE, rtol 1e-6, finest mesh):")
    for m, ref in refs.items():
        say(f"  {m:11s} h {ref['h']:.2f} ({ref['triangles']} triangles a leaflet): " +
            ", ".join(f"{k} {ref[k]:.3f}" for k in METRICS) +
            f"; {ref['solve_s']:.1f} s, steps {ref['steps']}" +
            ("" if ref["converged"] else " NOT CONVERGED"))
    say(f"\n{'model':11s} {'setting':20s} {'h':>5s} {'tris':>5s} {'conv':>4s} "
        f"{'steps':>12s} {'solve s':>8s} {'comp s':>6s} {'MB':>5s} " +
        " ".join(f"{'d' + m[:5]:>7s}" for m in METRICS) + f" {'max|dh|':>7s}")
    for r in sorted(rows, key=lambda r: (r["model"], _label(r), -r["h"])):
        say(f"{r['model']:11s} {_label(r):20s} {r['h']:5.2f} {r['triangles']:5d} "
            f"{'yes' if r['converged'] else 'NO':>4s} {r['steps']:>12s} {r['solve_s']:8.2f} "
            f"{r['compile_s']:6.1f} {r['peak_rss_mb']:5.0f} " +
            " ".join(f"{r['err_' + m]:+7.3f}" for m in METRICS) + f" {r['max_height_err']:7.3f}")
    say(f"\nCheapest converged setting with every height within {TOL_MM} mm of the reference "
        "(solve time after compilation, both closures):")
    for m in refs:
        good = [r for r in rows if r["model"] == m and r["converged"]
                and r["max_height_err"] <= TOL_MM]
        if not good:
            say(f"  {m:11s} none")
            continue
        best = min(good, key=lambda r: r["solve_s"])
        say(f"  {m:11s} {_label(best)}, h = {best['h']:.2f} mm: {best['solve_s']:.2f} s, "
            f"max height error {best['max_height_err']:.3f} mm, "
            f"NCCA error {best['err_NCCA_pct']:+.2f} points")
    say("\nObserved order of mesh convergence p (|error| ~ h^p; FIRE 1e-4, h = 2 ... 0.62 mm):")
    say(f"  {'model':11s} " + " ".join(f"{m:>8s}" for m in METRICS))
    for m in refs:
        o = mesh_orders(rows, m)
        say(f"  {m:11s} " + " ".join(f"{o[k]:8.2f}" for k in METRICS))
    f32 = [(r, next((q for q in rows if _key(q) == _key(dict(r, precision="float64"))), None))
           for r in rows if r["precision"] == "float32"]
    if f32:
        say("\nfloat32 against float64 (same model, mesh, tolerance):")
        for r, q in sorted(f32, key=lambda t: (t[0]["model"], t[0]["rtol"], -t[0]["h"])):
            if q is None:
                continue
            diff = max(abs(r[k] - q[k]) for k in HEIGHTS)
            say(f"  {r['model']:11s} rtol {r['rtol']:.0e} h {r['h']:4.2f}: f32 {r['results']} "
                f"{r['solve_s']:.2f} s vs f64 {q['results']} {q['solve_s']:.2f} s "
                f"(x{q['solve_s'] / r['solve_s']:.2f}); max height difference {diff:.3f} mm")
    if figure:
        _figure(rows, path.with_name("accuracy_pareto.png"))
        say(f"\nwrote {path.with_name('accuracy_pareto.png')}")


def _figure(rows, out):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    models = sorted({r["model"] for r in rows})
    fig, axes = plt.subplots(1, len(models), figsize=(4.2 * len(models), 4), sharey=True,
                             squeeze=False)
    for ax, m in zip(axes[0], models):
        for lab in sorted({_label(r) for r in rows if r["model"] == m}):
            pts = sorted([r for r in rows if r["model"] == m and _label(r) == lab],
                         key=lambda r: r["solve_s"])
            t = [r["solve_s"] for r in pts]
            e = [max(r["max_height_err"], 1e-3) for r in pts]
            ax.loglog(t, e, "o-", label=lab, ms=4)
            for r, ti, ei in zip(pts, t, e):
                ax.annotate(f"{r['h']:g}" + ("" if r["converged"] else "*"), (ti, ei),
                            fontsize=6, xytext=(2, 2), textcoords="offset points")
        ax.axhline(TOL_MM, color="k", lw=0.8, ls="--")
        ax.axvline(1.0, color="k", lw=0.8, ls=":")
        ax.set_title(m)
        ax.set_xlabel("solve time after compilation, s (3 + 80 mmHg)")
    axes[0][0].set_ylabel("max height error vs reference, mm")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle("labels: mesh size h (mm); * = not converged")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--quick", action="store_true", help="a smoke study, coarse meshes")
    ap.add_argument("--full", default="stvk", help="models that get the whole study")
    ap.add_argument("--csv", type=Path, default=None)
    ap.add_argument("--fresh", action="store_true", help="discard the rows already in the CSV")
    ap.add_argument("--report", action="store_true", help="only report from the CSV")
    ap.add_argument("--retime", default=None, metavar="H,H,...",
                    help="time again the converged FIRE rows on these meshes (quiet machine)")
    args = ap.parse_args(argv)
    models = [m for m in args.models.split(",") if m]
    path = args.csv or RESULTS / ("accuracy_quick.csv" if args.quick else "accuracy.csv")
    path.parent.mkdir(parents=True, exist_ok=True)
    if args.fresh and path.exists():
        os.remove(path)
    if args.retime:
        retime(path, {float(v) for v in args.retime.split(",")})
    elif not args.report:
        run(models, path, args.quick, tuple(args.full.split(",")))
    report(path)


if __name__ == "__main__":
    main()
