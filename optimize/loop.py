"""The outer loop: an optax optimiser over theta = (r, a, b), as an init / update pair.

    state = init(evaluator, optimizer)          # evaluates f and its gradient at the start
    while not state.done:
        state = update(evaluator, optimizer, state)
        print(state.record)

The default optimiser is L-BFGS (`optax.scale_by_lbfgs`) with a backtracking (Armijo) line
search run here, on the host: each trial step is one warm-started forward closure, and only
the accepted point pays for a gradient.  ``adam`` (optax.adam with an exponentially
decaying step) takes one value and gradient per iteration and no line search.

Every step is capped at ``max_step`` mm per parameter, projected onto the bounds, and kept
feasible (a valid template with 2b > |AD| and 2b > the commissure distance); an infeasible
or non-converged trial is treated as a failed trial and the step is halved.  The run stops
when the projected gradient is small, the objective stops decreasing, the line search
fails, the iterations run out, or the objective goes non-finite (``state.reason`` says
which).
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import numpy as np
import optax

from jaxvalve.errors import ConvergenceError, ParameterError

__all__ = ["LoopState", "make_optimizer", "init", "update", "OPTIMIZERS"]

OPTIMIZERS = ("lbfgs", "adam")


def make_optimizer(name: str = "lbfgs", learning_rate: float = 0.5, decay: float = 0.9):
    """optax transformation whose updates are *added* to (r, a, b) (mm).

    lbfgs: -(L-BFGS direction), with memory 5 (three parameters need no more);
    adam: optax.adam with learning rate ``learning_rate * decay^k`` (mm per step)."""
    if name == "lbfgs":
        return optax.chain(optax.scale_by_lbfgs(memory_size=5), optax.scale(-1.0))
    if name == "adam":
        if not (learning_rate > 0 and 0 < decay <= 1):
            raise ParameterError(f"adam needs learning_rate > 0 and decay in (0, 1]; got "
                                 f"{learning_rate}, {decay}")
        return optax.adam(optax.exponential_decay(learning_rate, 1, decay))
    raise ParameterError(f"optimizer must be one of {OPTIMIZERS}; got {name!r}")


@functools.lru_cache(maxsize=8)
def _compiled_update(optimizer):
    """optimizer.update under one jit (eager, each of its operations would compile)."""
    return jax.jit(optimizer.update)


@dataclasses.dataclass(frozen=True)
class LoopState:
    """iteration; evaluation (`optimize.evaluate.Evaluation`) at the current point; value,
    grad (3,); opt_state (optax); counts {'forward', 'gradient'}; seconds (cumulative);
    done, reason; failed: stopped on an error (a non-finite objective or gradient), not by
    a stopping rule; record (dict: the last iteration's report)."""

    iteration: int
    evaluation: Any
    value: float
    grad: np.ndarray
    opt_state: Any
    counts: dict
    seconds: float
    done: bool = False
    reason: str = ""
    failed: bool = False
    record: dict = dataclasses.field(default_factory=dict)

    @property
    def rab(self):
        return self.evaluation.rab


def projected_gradient(rab, grad, lower, upper):
    """The gradient with components removed where a bound blocks descent (mm^-1)."""
    g = np.array(grad, float)
    g[(rab <= lower + 1e-9) & (g > 0)] = 0.0
    g[(rab >= upper - 1e-9) & (g < 0)] = 0.0
    return g


def _record(ev, state_it, value, grad, counts, seconds, extra):
    r = dict(iteration=state_it, r=float(ev.rab[0]), a=float(ev.rab[1]), b=float(ev.rab[2]),
             objective=float(value), grad_norm=float(np.linalg.norm(grad)),
             grad_r=float(grad[0]), grad_a=float(grad[1]), grad_b=float(grad[2]))
    r.update({f"m:{k}": float(v) for k, v in ev.metrics.items()})
    r.update({f"f:{k}": float(v) for k, v in ev.terms.items()})
    r.update(forward=counts["forward"], gradient=counts["gradient"], seconds=float(seconds),
             generation=ev.generation,
             steps=sum(s["steps"] for s in ev.solves),
             residual=max(s["residual"] for s in ev.solves))
    r.update(extra)
    return r


def _gradient(evaluator, ev, counts):
    v, g, info = evaluator.gradient(ev)
    counts["gradient"] += 1
    if not (np.isfinite(v) and np.all(np.isfinite(g))):
        raise ConvergenceError(f"the objective or its gradient is not finite at (r, a, b) = "
                               f"{tuple(ev.rab)}: value {v}, gradient {g}")
    adj = info["adjoint"]
    return v, g, (max(a.residual for a in adj) if adj else float("nan"))


def init(evaluator, optimizer, *, warm=None) -> LoopState:
    """Evaluate the start (the evaluator's scene r, a, b) and its gradient.

    Raises `ParameterError` for an infeasible start and `ConvergenceError` when the start
    does not close or its objective is not finite."""
    t0 = time.perf_counter()
    rab = np.array([evaluator.scene.r, evaluator.scene.a, evaluator.scene.b], float)
    why = evaluator.feasible(rab)
    if why:
        raise ParameterError(f"the start is not a valid design: {why}")
    counts = {"forward": 0, "gradient": 0}
    ev = evaluator.forward(rab, warm)
    counts["forward"] += 1
    if not ev.converged:
        raise ConvergenceError(f"the start did not close: {ev.reason}", ev)
    v, g, adj = _gradient(evaluator, ev, counts)
    secs = time.perf_counter() - t0
    rec = _record(ev, 0, v, g, counts, secs, dict(step=0.0, trials=0, adjoint_residual=adj))
    return LoopState(0, ev, v, g, optimizer.init(rab), counts, secs, record=rec)


def update(evaluator, optimizer, state: LoopState, *, max_step: float = 1.0, line_search: bool = True, max_trials: int = 6,
           gtol: float = 1e-3, ftol: float = 1e-5, max_iter: int = 30) -> LoopState:
    """One iteration: direction, line search, gradient at the accepted point."""
    if state.done:
        return state
    t0 = time.perf_counter()
    obj = evaluator.objective
    lo, hi = obj.lower, obj.upper
    rab, g = state.rab, state.grad
    counts = dict(state.counts)
    upd, opt_state = _compiled_update(optimizer)(g, state.opt_state, rab)
    d = np.asarray(upd, float)
    if not np.all(np.isfinite(d)):
        return dataclasses.replace(state, done=True, failed=True,
                                   reason="the optimiser's step is not finite")
    if np.max(np.abs(d)) > max_step:
        d = d * (max_step / np.max(np.abs(d)))
    if line_search and float(np.dot(d, g)) >= 0:   # not a descent direction: restart
        opt_state = optimizer.init(rab)
        d = -g * min(1.0, max_step / max(np.max(np.abs(g)), 1e-300))
    t, trials, accepted, why, log = 1.0, 0, None, "", []
    while trials < max_trials:
        cand = obj.project(rab + t * d)
        trials += 1
        why = evaluator.feasible(cand)
        ev = None
        if not why:
            ev = evaluator.forward(cand, state.evaluation)
            counts["forward"] += 1
            log.append((t, sum(s["steps"] for s in ev.solves), ev.value))
            why = "" if ev.converged else ev.reason
        if ev is not None and ev.converged:
            decrease = 1e-4 * float(np.dot(g, cand - rab))
            if not line_search or ev.value <= state.value + decrease:
                accepted = ev
                break
            why = f"no sufficient decrease ({ev.value:.6g} vs {state.value:.6g})"
        t *= 0.5
    if accepted is None:
        return dataclasses.replace(state, counts=counts, done=True,
                                   reason=f"line search failed after {trials} trials: {why}")
    try:
        v, g_new, adj = _gradient(evaluator, accepted, counts)
    except ConvergenceError as e:
        return dataclasses.replace(state, counts=counts, done=True, reason=str(e), failed=True)
    secs = state.seconds + time.perf_counter() - t0
    it = state.iteration + 1
    pg = projected_gradient(accepted.rab, g_new, lo, hi)
    done, reason = False, ""
    if np.linalg.norm(pg) < gtol:
        done, reason = True, f"projected gradient norm {np.linalg.norm(pg):.2e} < gtol {gtol:g}"
    elif state.value - v < ftol * max(1.0, abs(v)):
        done, reason = True, (f"objective decrease {state.value - v:.2e} < ftol {ftol:g} "
                              "(relative)")
    elif it >= max_iter:
        done, reason = True, f"reached max_iter = {max_iter}"
    rec = _record(accepted, it, v, g_new, counts, secs,
                  dict(step=float(np.max(np.abs(accepted.rab - rab))), trials=trials,
                       adjoint_residual=adj,
                       line_search=" ".join(f"{a:g}:{n}:{v:.4g}" for a, n, v in log)))
    return LoopState(it, accepted, v, g_new, opt_state, counts, secs, done, reason,
                     record=rec)
