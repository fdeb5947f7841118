"""Close a three-leaflet valve in an aortic root and measure its coaptation (h_E, h_C-C,
h_avr, NCCA, h, h_c).

The scene is the benchmark valve unless a SCENE.toml is given (keys = the field names of
jaxvalve.scene.Scene); flags override the file.  Exit codes: 0 converged, 2 bad input,
3 a solve did not converge, 4 a limit point: no equilibrium at the load (the outputs are
still written, of the last equilibrium).
"""
from __future__ import annotations

import json
import sys

from ..scene import MODELS, PRECISIONS, SOLVERS

# flag -> (Scene field, type, help)
_FLAGS = {
    "template (Ozaki leaflet)": [
        ("--r", float, "radius of the template's bottom arc B-C, mm (benchmark 12)"),
        ("--a", float, "length of the straight sutured segments A-B and C-D, mm "
                       "(benchmark 7.1)"),
        ("--b", float, "length of each free-edge segment A-E, E-D (free edge 2b), mm "
                       "(benchmark 15)"),
        ("--alpha", float, "angle subtended by the arc B-C, degrees, in (0, 180] "
                           "(benchmark 160)"),
        ("--h", float, "target mesh edge length, mm (benchmark 0.88: ~1300 triangles a "
                       "leaflet)"),
    ],
    "material": [
        ("--E", float, "Young's modulus, MPa (default 1)"),
        ("--nu", float, "Poisson ratio (StVK; default 0.45)"),
        ("--mu", float, "shear modulus, MPa (neo-Hookean, Gent; default E/3)"),
        ("--Jm", float, "Gent locking parameter Jm (default 2.3)"),
        ("--E1", float, "mass-spring modulus below the first knee, MPa (give E1, E2, E3 "
                        "together; default linear E)"),
        ("--E2", float, "mass-spring modulus between the knees, MPa"),
        ("--E3", float, "mass-spring modulus above the second knee, MPa"),
        ("--thickness", float, "leaflet thickness H, mm (default 0.3)"),
        ("--fibre-angle", float, "fibre direction in the template frame, degrees "
                                 "(anisotropic mass-spring; default 0)"),
        ("--bending", float, "bending stiffness as a multiple of the plate modulus "
                             "D = E H^3 / (12 (1 - nu^2)); 0 = pure membrane (default 1)"),
    ],
    "load": [
        ("--pressure", float, "closing (diastolic) pressure, mmHg (default 80)"),
        ("--he-pressure", float, "load at which the effective height h_E is measured, mmHg "
                                 "(default 3)"),
    ],
    "solver and metrics": [
        ("--rtol", float, "relative force residual ||F_free|| / ||F_pressure|| to reach "
                          "(default 1e-4; optimize: 1e-6)"),
        ("--max-steps", int, "iteration limit per solve (fire, paper; default 50000; "
                             "optimize: 5000)"),
        ("--g-c", float, "coaptation distance g_c, mm: a point is in contact where the gap "
                         "to another leaflet is below it (default 0.5)"),
    ],
}


def _field(flag):
    return flag.lstrip("-").replace("-", "_")


def add_parser(sub):
    p = sub.add_parser(
        "simulate", help="close a valve in an aortic root and measure its coaptation",
        description=__doc__, allow_abbrev=False,
        epilog="Example: jaxvalve simulate --out results   (the benchmark valve)")
    add_scene_arguments(p)
    g = p.add_argument_group("output")
    g.add_argument("--out", metavar="DIR",
                   help="write metrics.json, leaflet_{0,1,2}.vtu and PNG figures here "
                        "(default: write nothing)")
    g.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    g.add_argument("--json", action="store_true",
                   help="print metrics.json to stdout (progress goes to stderr)")
    return p


def add_scene_arguments(p):
    """The scene: an optional SCENE.toml and one flag per `Scene` field (read back by
    `make_scene`); shared by the subcommands that take a scene."""
    p.add_argument("scene", nargs="?", metavar="SCENE.toml",
                   help="scene file (TOML, keys = Scene fields); default: the benchmark")
    g = p.add_argument_group("aortic root and template")
    g.add_argument("--root", nargs="+", metavar="FILE",
                   help="'benchmark' (default) or SURFACE LANDMARKS: a wall mesh (any "
                        "meshio format) and a landmarks .json/.toml (see jaxvalve.io)")
    for title, flags in _FLAGS.items():
        if title != "template (Ozaki leaflet)":
            g = p.add_argument_group(title)
        if title == "material":
            g.add_argument("--model", choices=MODELS,
                           help="material law (default stvk)")
        if title == "solver and metrics":
            g.add_argument("--solver", choices=SOLVERS,
                           help="closure method: engine (IPC barrier contact, leaflets "
                                "never cross; FIRE with a Newton finish) or paper (the "
                                "paper's contact law and damped fixed point, Algorithm "
                                "2.1, for comparison) (default engine)")
            g.add_argument("--precision", choices=PRECISIONS,
                           help="floating type of the solve (default float64)")
        for flag, typ, text in flags:
            g.add_argument(flag, type=typ, dest=_field(flag), metavar=typ.__name__.upper(),
                           help=text)


def make_scene(args):
    """The `Scene` of the parsed arguments: the TOML file (or the defaults) + the flags."""
    from ..errors import ParameterError
    from ..scene import Scene

    names = ["model", "solver", "precision"] + [
        _field(f) for fl in _FLAGS.values() for f, _, _ in fl]
    kw = {k: getattr(args, k) for k in names if getattr(args, k) is not None}
    if args.root is not None:
        if len(args.root) == 1 and args.root[0] == "benchmark":
            kw["root"] = "benchmark"
        elif len(args.root) == 2:
            kw["root"] = tuple(args.root)
        else:
            raise ParameterError(f"--root takes 'benchmark' or SURFACE LANDMARKS; got "
                                 f"{args.root}")
    if args.scene is not None:
        return Scene.from_toml(args.scene, **kw)
    return Scene(**kw)


def _table(result):
    s, solves = result.summary(), result.solves
    rows = [("h_E (effective height)", f"{s['h_E']:.3f} mm"),
            ("h_C-C (at w = 5 mm)", f"{s['h_CC']:.3f} mm"),
            ("h_avr (zone area / free edge)", f"{s['h_avr']:.3f} mm"),
            ("NCCA", f"{s['NCCA_pct']:.1f} %"),
            ("h (max pair height)", f"{s['h']:.3f} mm"),
            ("h_c (central height)", f"{s['h_c']:.3f} mm"),
            ("solve time", f"{sum(r.solve_s for r in solves):.2f} s"),
            ("compile time", f"{sum(r.compile_s for r in solves):.1f} s")]
    for r in solves:
        rows.append((f"solve at {r.pressure:g} mmHg", r.describe()))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)


def run(args) -> int:
    from ..io.report import metrics_json, write_outputs
    from ..simulation import simulate
    from ..io.files import check_out_dir
    from ..progress import Heartbeat

    stream = sys.stderr if args.json else sys.stdout

    def say(msg):
        print(f"[jaxvalve] {msg}", file=stream, flush=True)

    scene = make_scene(args)
    check_out_dir(args.out)                 # before the solve: a bad --out loses nothing
    with Heartbeat(say) as hb:              # a line at least every 2 s
        result = simulate(scene, progress=hb.say, throw=False)
        written = []
        if args.out is not None:
            hb.say(f"writing the outputs to {args.out}")
            written = write_outputs(result, args.out, figures=not args.no_figures)
    if args.json:
        print(json.dumps(metrics_json(result), indent=1, allow_nan=False))
    else:
        print(_table(result))
    if written:
        say(f"wrote {len(written)} files to {args.out}")
    for w in result.warnings:
        print(f"jaxvalve simulate: warning: {w}", file=sys.stderr)
    lim = [r for r in result.solves if r.result == "limit_point"]
    if lim:
        print(f"jaxvalve simulate: warning: LIMIT POINT: the valve has no equilibrium above "
              f"{lim[0].limit_pressure:.3g} mmHg (the inflation analysis of the material is "
              "in the warning above, docs/limit-points.md); the "
              f"metrics are of the equilibrium at {lim[0].limit_pressure:.3g} mmHg, not at "
              f"{lim[-1].pressure:g} mmHg", file=sys.stderr)
        return 4
    if not result.converged:
        bad = [r for r in result.solves if not r.converged]
        what = "; ".join(f"at {r.pressure:g} mmHg: {r.describe()} (rtol {scene.rtol:g})"
                         for r in bad)
        print(f"jaxvalve simulate: warning: the closure did NOT converge ({what}); the "
              "metrics are of an unconverged state", file=sys.stderr)
        return 3
    return 0
