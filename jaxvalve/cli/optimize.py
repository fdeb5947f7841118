"""Tune the template (r, a, b) by gradient descent until the coaptation meets targets.

The start is the scene's template (benchmark valve unless SCENE.toml or flags say
otherwise); alpha, the root, material and loads stay fixed.  Targets come from
--target (repeatable, e.g. --target "h_c>=4" --target "h=8") or a TOML file
(--targets FILE: a [targets] table, e.g. h_c = {lower = 4}, h = "h=8", and optionally
[objective] size_weight, margin, constraint_weight and [bounds] r = [8, 16]).
Default: h_c >= 4 mm and h = 8 mm, with the smallest leaflet (size_weight 0.1).
Writes trajectory.csv/.json, checkpoint.npz and optimisation.png to --out after every
iteration; --resume continues a run saved there.  Exit codes: 0 stopped by a stopping
rule, 2 bad input, 3 the run failed (a closure that does not converge at the start, a
non-finite objective).
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from .simulate import add_scene_arguments, make_scene

METRIC_HELP = "METRIC>=X, METRIC<=X, METRIC=X or X<=METRIC<=Y; METRIC one of h_E, h_CC, " \
              "h_avr, NCCA_pct, h, h_c, area (mm, %%, mm^2)"


def add_parser(sub):
    p = sub.add_parser("optimize", help="tune the template r, a, b to coaptation targets",
                       description=__doc__, allow_abbrev=False,
                       epilog='Example: jaxvalve optimize --h 1.5 --target "h_c>=4" '
                              '--target "h=8" --out opt')
    add_scene_arguments(p)
    g = p.add_argument_group("targets and objective")
    g.add_argument("--target", action="append", metavar="EXPR", help=METRIC_HELP)
    g.add_argument("--targets", metavar="FILE.toml", help="targets (and objective) file")
    g.add_argument("--size-weight", type=float, metavar="W",
                   help="weight of the leaflet-size term (area / start area; default 0.1)")
    g.add_argument("--bounds", action="append", metavar="NAME=LO,HI",
                   help="box for r, a or b in mm, e.g. --bounds b=10,20 (defaults: r 8-16, "
                        "a 2-14, b 8-22)")
    g = p.add_argument_group("optimiser")
    g.add_argument("--optimizer", choices=("lbfgs", "adam"), default="lbfgs",
                   help="L-BFGS with a line search (default) or Adam with a decaying step")
    g.add_argument("--max-iter", type=int, default=30, help="iteration limit (default 30)")
    g.add_argument("--cold-closures", action="store_true",
                   help="close every design from the placement instead of warm-starting "
                        "from the last one (about 3x slower; the objective then depends on "
                        "(r, a, b) alone)")
    g.add_argument("--no-check", action="store_true",
                   help="skip the final check (the final design closed once more from the "
                        "placement and compared with the run's objective; one closure, "
                        "~4.5 s at h = 0.88 mm)")
    g.add_argument("--max-step", type=float, default=1.0,
                   help="largest change of r, a or b per iteration, mm (default 1)")
    g.add_argument("--gtol", type=float, default=1e-3,
                   help="stop when the projected gradient norm is below this (default 1e-3)")
    g.add_argument("--ftol", type=float, default=1e-5,
                   help="stop when the objective decreases by less than this, relative "
                        "(default 1e-5)")
    g = p.add_argument_group("output")
    g.add_argument("--out", metavar="DIR", default="optimisation",
                   help="run directory (default ./optimisation)")
    g.add_argument("--resume", action="store_true", help="continue the run saved in --out")
    g.add_argument("--no-figures", action="store_true", help="skip optimisation.png")
    return p


def make_objective(args):
    """The `Objective` of the parsed arguments."""
    from optimize import Objective, parse_target, targets_from_dict
    from ..errors import ParameterError

    kw, targets = {}, []
    if args.targets is not None:
        path = Path(args.targets)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ParameterError(f"cannot read targets file {str(path)!r}: {e}") from None
        bad = set(data) - {"targets", "objective", "bounds"}
        if bad:
            raise ParameterError(f"targets file: unknown tables {sorted(bad)}; allowed: "
                                 "targets, objective, bounds")
        targets += list(targets_from_dict(data.get("targets", {})))
        obj = dict(data.get("objective", {}))
        badk = set(obj) - {"size_weight", "margin", "constraint_weight", "area_ref"}
        if badk:
            raise ParameterError(f"targets file [objective]: unknown keys {sorted(badk)}")
        kw.update(obj)
        if "bounds" in data:
            kw["bounds"] = data["bounds"]
    targets += [parse_target(t) for t in args.target or ()]
    if targets:
        kw["targets"] = tuple(targets)
    if args.size_weight is not None:
        kw["size_weight"] = args.size_weight
    for spec in args.bounds or ():
        try:
            name, rng = spec.split("=")
            lo, hi = (float(v) for v in rng.split(","))
        except ValueError:
            raise ParameterError(f"--bounds takes NAME=LO,HI (mm), e.g. b=10,20; got "
                                 f"{spec!r}") from None
        kw.setdefault("bounds", {})[name.strip()] = (lo, hi)
    return Objective(**kw)


def run(args) -> int:
    from optimize import optimize_template

    def say(msg):
        print(f"[jaxvalve] {msg}", flush=True)

    from optimize.run import OPTIMIZE_MAX_STEPS, OPTIMIZE_RTOL
    from ..io.files import check_out_dir
    from ..progress import Heartbeat
    scene = make_scene(args)
    check_out_dir(args.out)                 # before any closure: a bad --out loses nothing
    if args.rtol is None:
        scene = scene.replace(rtol=OPTIMIZE_RTOL)      # gradients need a tight equilibrium
    if args.max_steps is None:
        scene = scene.replace(max_steps=OPTIMIZE_MAX_STEPS)
    objective = make_objective(args)
    say("targets: " + "; ".join(t.describe() for t in objective.targets)
        + f"; size weight {objective.size_weight:g}")
    with Heartbeat(say) as hb:              # a line at least every 2 s
        res = optimize_template(scene, objective, optimizer=args.optimizer,
                                max_iter=args.max_iter, max_step=args.max_step,
                                gtol=args.gtol, ftol=args.ftol, out=args.out,
                                resume=args.resume, figures=not args.no_figures,
                                warm_start=not args.cold_closures, verify=not args.no_check,
                                progress=hb.say)
    t = res.template
    print(f"  final template: r = {t['r']:.3f} mm, a = {t['a']:.3f} mm, b = {t['b']:.3f} mm")
    print(f"  objective {res.value:.6g} after {res.records[-1]['iteration']} iterations, "
          f"{res.counts['forward']} closures and {res.counts['gradient']} gradients, "
          f"{res.seconds:.1f} s ({res.compile_s:.1f} s compiling)")
    print("  " + "  ".join(f"{k[2:]} = {v:.3f}" for k, v in res.records[-1].items()
                           if k.startswith("m:")))
    print(f"  stopped: {res.reason}")
    say(f"wrote {len(res.files)} files to {args.out}")
    return 3 if res.failed or not res.consistent else 0
