"""Gradient-based tuning of the Ozaki template (r, a, b) against coaptation targets.

    from optimize import optimize_template, default_scene, Objective, parse_target
    res = optimize_template(default_scene().replace(h=1.5),   # rtol 1e-6, 5000 steps
                            Objective(targets=(parse_target("h_c>=4"), parse_target("h=8"))))

Modules: targets (what a metric should be), objective (targets + leaflet size +
template constraints), evaluate (closures, smooth metrics and adjoint gradients as
functions of theta), loop (optax init / update with a host line search), trajectory
(files and figures), run (the whole run, resumable).  The CLI is ``jaxvalve optimize``.
"""
import jaxvalve  # noqa: F401  (float64)

from .evaluate import Evaluation, Evaluator
from .loop import LoopState, init, make_optimizer, update
from .objective import DEFAULT_BOUNDS, Objective
from .run import OptimizationResult, default_scene, optimize_template
from .targets import DEFAULT_TARGETS, METRICS, Target, parse_target, targets_from_dict

__all__ = ["optimize_template", "default_scene", "OptimizationResult", "Objective", "DEFAULT_BOUNDS",
           "Target", "parse_target", "targets_from_dict", "METRICS", "DEFAULT_TARGETS",
           "Evaluator", "Evaluation", "LoopState", "init", "update", "make_optimizer"]
