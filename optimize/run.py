"""`optimize_template(...)`: the whole run (the Python face of ``jaxvalve optimize``)."""
from __future__ import annotations

import dataclasses
import json
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve import Scene
from jaxvalve.errors import ConvergenceError, ParameterError
from jaxvalve.io import check_out_dir

from . import loop
from .evaluate import Evaluator
from .objective import Objective
from .trajectory import plot_run, read_checkpoint, write_checkpoint, write_trajectory

__all__ = ["optimize_template", "OptimizationResult", "default_scene", "OPTIMIZE_RTOL",
           "OPTIMIZE_MAX_STEPS"]

#: Relative residual of the closures an optimisation runs: gradients need a tight
#: equilibrium (the scene's own default, 1e-4, is for reporting metrics).
OPTIMIZE_RTOL = 1e-6
#: FIRE step limit per closure: a warm-started closure takes ~500-900 steps; a trial that
#: cycles is cut short and the line search halves the step.
OPTIMIZE_MAX_STEPS = 5000


def default_scene() -> Scene:
    """The benchmark `Scene` with the closure settings of an optimisation
    (`OPTIMIZE_RTOL`, `OPTIMIZE_MAX_STEPS`): what ``jaxvalve optimize`` runs without
    flags, and what `optimize_template` uses when no scene is given."""
    return Scene(rtol=OPTIMIZE_RTOL, max_steps=OPTIMIZE_MAX_STEPS)


@dataclasses.dataclass(frozen=True)
class OptimizationResult:
    """rab (3,) mm: the final (r, a, b); value: its objective; records: one dict per
    iteration; reason: why the run stopped; failed: it stopped on an error (a start that
    does not close, a non-finite objective) rather than by a stopping rule; counts:
    {'forward', 'gradient'}; seconds: wall time of the iterations; compile_s: of which
    JAX compilation; evaluation: the final `Evaluation`; files: paths written;
    check: the final design closed again from the placement (`verify=True`), a dict with
    'converged', 'value', 'metrics' and 'consistent' (its objective within
    ``verify_rtol`` of the run's), or None when not checked (verify=False, a failed run,
    or a run whose closures start from the placement anyway)."""

    rab: np.ndarray
    value: float
    records: list
    reason: str
    failed: bool
    counts: dict
    seconds: float
    compile_s: float
    evaluation: Any
    files: tuple = ()
    check: dict | None = None

    @property
    def consistent(self) -> bool:
        """False when the final design closes differently from the placement than along
        the run (path dependence through contact; see `check`)."""
        return self.check is None or bool(self.check["consistent"])

    @property
    def template(self) -> dict:
        return dict(r=float(self.rab[0]), a=float(self.rab[1]), b=float(self.rab[2]))


def _config(scene, objective, optimizer, options):
    return dict(scene=scene.as_dict(), objective=objective.as_dict(), optimizer=optimizer,
                options=options)


def optimize_template(scene: Scene | None = None, objective: Objective | None = None, *,
                      optimizer: str = "lbfgs", max_iter: int = 30, max_step: float = 1.0,
                      gtol: float = 1e-3, ftol: float = 1e-5, eps: float = 0.1,
                      out=None, resume: bool = False,
                      warm_start: bool | None = None, verify: bool = True,
                      verify_rtol: float = 1e-3,
                      figures: bool = True, evaluator: Evaluator | None = None,
                      progress: Callable[[str], None] | None = None) -> OptimizationResult:
    """Tune (r, a, b) of ``scene``'s template (its r, a, b are the start; alpha, the root,
    mesh size h, material and loads are the scene's) to minimise ``objective``.

    out: directory for trajectory.csv/json, checkpoint.npz and optimisation.png (written
    after every iteration); resume: continue the run saved in ``out`` (same scene,
    objective and options, else `ParameterError`), giving the same iterates as an
    uninterrupted run.  evaluator: an `Evaluator` for this scene and objective to reuse
    (its compiled functions; e.g. in a notebook).  progress: called with one line per
    iteration (e.g. ``print``).  warm_start: start each closure from the last accepted
    point's closed state (True, about 3x cheaper) or from the placement (False: the
    objective is then a function of (r, a, b) alone); None: the given evaluator's own
    setting, else True.  verify: close the final design once more from
    the placement and compare its objective with the run's (relative ``verify_rtol``): a
    warm-started run can follow a branch of closed states that the open valve does not
    reach; `OptimizationResult.check` and ``consistent`` report it.  scene None:
    `default_scene()` (the benchmark valve with rtol 1e-6, as ``jaxvalve optimize``); a
    given scene is used as it is, so pass rtol=1e-6 for gradients that match its CLI.
    """
    from jaxvalve.simulation import compile_timer

    scene = default_scene() if scene is None else scene
    objective = Objective() if objective is None else objective
    if objective.area_ref is None:
        objective = dataclasses.replace(objective, area_ref=scene.template().area)
    if evaluator is not None and (
            evaluator.scene != scene or evaluator.eps != eps
            or _baked(evaluator.objective) != _baked(objective)):
        # its compiled gradients hold the objective's weights and targets as constants
        raise ParameterError("the evaluator was built for another scene, eps or objective")
    for name, v in (("max_iter", max_iter),):
        if not (isinstance(v, int) and v >= 0):
            raise ParameterError(f"{name} must be an integer >= 0; got {v!r}")
    for name, v in (("max_step", max_step), ("gtol", gtol), ("ftol", ftol),
                    ("verify_rtol", verify_rtol)):
        if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
            raise ParameterError(f"{name} must be a finite number > 0; got {v!r}")
    for name, v in (("warm_start", warm_start), ("verify", verify)):
        if not (isinstance(v, bool) or (name == "warm_start" and v is None)):
            raise ParameterError(f"{name} must be True or False; got {v!r}")
    if warm_start is None:
        warm_start = True if evaluator is None else evaluator.warm_start
    options = dict(max_iter=max_iter, max_step=max_step, gtol=gtol, ftol=ftol, eps=eps,
                   warm_start=bool(warm_start))
    out = check_out_dir(out, "out")    # before any closure: a bad folder loses nothing
    config = _config(scene, objective, optimizer, options)
    opt = loop.make_optimizer(optimizer)
    say = progress or (lambda s: None)
    if resume and out is None:
        raise ParameterError("resume needs the run directory (out)")
    kw = dict(max_step=max_step, gtol=gtol, ftol=ftol, max_iter=max_iter,
              line_search=(optimizer == "lbfgs"))
    t_start = time.perf_counter()
    with compile_timer() as ct:
        if resume:
            saved = read_checkpoint(out)
            same = lambda c: {**c, "options": {k: v for k, v in c["options"].items()  # noqa
                                               if k != "max_iter"}}
            if same(json.loads(json.dumps(config))) != same(saved["trajectory"]["config"]):
                raise ParameterError(f"cannot resume {str(out)!r}: its scene, objective "
                                     "or options differ from this run's")
            ck = saved["checkpoint"]
            records = saved["trajectory"]["records"]
            evaluator = _evaluator(evaluator, scene, objective, eps, ck["mesh_at"],
                                   warm_start)
            ev = evaluator.forward(ck["rab"], {l: jnp.asarray(ck[f"x_{l}"])
                                               for l in evaluator.loads})
            if not ev.converged:
                raise ParameterError(f"cannot resume {str(out)!r}: {ev.reason}")
            treedef = jax.tree_util.tree_structure(opt.init(ck["rab"]))
            n = treedef.num_leaves
            opt_state = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(ck[f"opt_{i}"])
                                                               for i in range(n)])
            counts = dict(forward=int(ck["forward"]), gradient=int(ck["gradient"]))
            state = loop.LoopState(int(ck["iteration"]), ev, float(ck["value"]),
                                   np.asarray(ck["grad"]), opt_state, counts,
                                   float(ck["seconds"]), record=records[-1])
            say(f"resumed at iteration {state.iteration}: objective {state.value:.6g}")
        else:
            evaluator = _evaluator(evaluator, scene, objective, eps, None, warm_start)
            try:
                state = loop.init(evaluator, opt)
            except ConvergenceError as e:                 # reported in the run directory
                if out is not None:
                    write_trajectory(out, config, [], dict(done=True, failed=True,
                                                           reason=str(e)))
                raise
            records = [state.record]
            say(_line(state.record))
            if out is not None:
                write_trajectory(out, config, records, dict(done=False))
                write_checkpoint(out, state, evaluator)
        while not state.done and state.iteration < max_iter:
            try:
                state = loop.update(evaluator, opt, state, **kw)
            except Exception as e:                      # noqa: BLE001 - reported, re-raised
                if out is not None:
                    write_trajectory(out, config, records,
                                     dict(done=True, failed=True, reason=str(e)))
                raise
            if state.iteration > records[-1]["iteration"]:       # a step was accepted
                records.append(state.record)
                say(_line(state.record))
            if out is not None:
                write_trajectory(out, config, records, dict(done=state.done, reason=state.reason))
                write_checkpoint(out, state, evaluator)
        reason = state.reason or f"reached max_iter = {max_iter}"
        failed = state.failed
        check = None
        if verify and not failed and warm_start:     # a cold run's closures already are
            check = _verify(evaluator, state, verify_rtol)
            say(check["message"])
    seconds = time.perf_counter() - t_start
    say(f"stopped: {reason}")
    files = ()
    if out is not None:
        write_trajectory(out, config, records, dict(done=True, failed=failed, reason=reason,
                                                    seconds=seconds, compile_s=ct.seconds,
                                                    check=check))
        files = (out / "trajectory.json", out / "trajectory.csv", out / "checkpoint.npz")
        if figures:
            files = files + (plot_run(out, records, scene.alpha, objective.targets),)
    return OptimizationResult(np.asarray(state.rab), state.value, records, reason, failed,
                              state.counts, seconds, ct.seconds, state.evaluation, files,
                              check)


def _baked(objective):
    """The parts of an objective that an `Evaluator`'s compiled gradient holds as
    constants (area_ref is traced; bounds are applied on the host)."""
    return (objective.targets, objective.size_weight, objective.margin,
            objective.constraint_weight)


def _verify(evaluator, state, rtol):
    """The final design closed from the placement, against the run's (warm-started)
    evaluation: {'converged', 'value', 'metrics', 'consistent', 'message'}."""
    ev = evaluator.forward(state.rab, None)
    f_run = state.value
    if not ev.converged:
        return dict(converged=False, value=None, metrics={}, consistent=False,
                    message=f"WARNING: the final design does not close from the placement "
                            f"({ev.reason}); its metrics hold only along this run's path")
    gap = abs(ev.value - f_run) / max(abs(f_run), 1e-12)
    ok = bool(gap <= rtol)
    dm = {k: ev.metrics[k] - state.evaluation.metrics[k] for k in ev.metrics}
    worst = max(dm, key=lambda k: abs(dm[k]))
    msg = (f"check: the final design closed from the placement gives f = {ev.value:.6g} "
           f"(run: {f_run:.6g}; relative gap {gap:.1e}, largest metric change "
           f"{worst} {dm[worst]:+.3g})")
    if not ok:
        msg = ("WARNING: path-dependent closure: " + msg + f", above {rtol:g}: the run "
               "followed a branch of closed states the open valve does not reach; rerun "
               "with closures from the placement (warm_start=False, --cold-closures)")
    return dict(converged=True, value=float(ev.value),
                metrics={k: float(v) for k, v in ev.metrics.items()}, consistent=ok,
                message=msg)


def _evaluator(given, scene, objective, eps, mesh_at, warm_start=True):
    if given is None:
        return Evaluator(scene, objective, eps=eps, mesh_at=mesh_at, warm_start=warm_start)
    given.warm_start = warm_start
    start = np.array([scene.r, scene.a, scene.b]) if mesh_at is None else np.asarray(mesh_at)
    if not np.array_equal(given.mesh_at, start):
        given._build(start)          # the run's mesh (a remesh in an earlier run moved it)
    given.objective = objective
    return given


def _line(r):
    ms = "  ".join(f"{k[2:]} {v:.3f}" for k, v in r.items() if k.startswith("m:"))
    return (f"it {r['iteration']:3d}  r {r['r']:.4f}  a {r['a']:.4f}  b {r['b']:.4f}  "
            f"f {r['objective']:.6g}  |g| {r['grad_norm']:.3g}  {ms}  "
            f"[{r['forward']} fwd, {r['gradient']} grad, {r['seconds']:.1f} s]")
