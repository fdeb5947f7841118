"""FIRE (Bitzek et al. 2006, Guenole et al. 2020): damped inertial relaxation, the engine's
first phase on the barrier contact."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..errors import ParameterError
from ..unvmap import unvmap_any
from .base import RESULTS, check_settings, check_state

#: the fraction of a node's nearest contact distance it may move in one step: two nodes
#: of a pair then close at most 0.8 of their gap, so no step lets a pair meet
CONTACT_MOVE = 0.4


@dataclasses.dataclass(frozen=True)
class FIRE:
    """FIRE with per-node masses equal to a bound on the node's stiffness (N/mm), so that
    every mode has angular frequency <= 1 and ``dt_max`` is dimensionless: the membrane's
    element bound (refreshed every ``refresh`` steps, never lowered: stiffening
    materials) plus the barrier's stiffness at the node (every step, from the force
    evaluation).  Where a node's mass changes, its velocity is kept.

    Each step is filtered so that leaflets never meet: a node moves at most `CONTACT_MOVE`
    of its nearest contact distance, and no node more than the pair lists allow
    (`EquilibriumSystem.step_cap`); a node cut short keeps a velocity to match.  A step
    that would leave the admissible set (a triangle past the Gent stretch limit, or
    collapsed) is refused: the state stays, the velocity is zeroed and dt halved; only once
    dt falls below ``dt_min`` does the solve stop (`RESULTS.stretch_limit`).

    Stops at a relative residual < rtol; with ``patience`` > 0 as `RESULTS.stagnation`
    once its residual, below ``patience_below`` (the leaflets have swung shut: above it
    the residual rises and falls as they swing), has not halved for that many steps nor
    for half the steps run so far (a slow solve that still halves its residual now and
    then, as soft valves on fine meshes do, is not stopped).  The state of the lowest
    residual is kept (``state["best_y"]``, ``state["rmin"]``): where FIRE stagnates, the engine's Newton
    finish starts there (`jaxvalve.solvers.finish`)."""

    rtol: float = 1e-6
    max_steps: int = 50_000
    dt_start: float = 0.1
    dt_max: float = 1.5
    n_min: int = 5
    f_inc: float = 1.1
    f_dec: float = 0.5
    alpha_start: float = 0.1
    f_alpha: float = 0.99
    refresh: int = 100
    dt_min: float = 1e-6
    patience: int = 1000
    patience_below: float = 1e-2
    max_move: float = 1.0

    def __post_init__(self):
        check_settings(self, dict(rtol="positive", max_steps="count", dt_start="positive",
                                  dt_max="positive", n_min="count", f_inc="above_one",
                                  f_dec="unit", alpha_start="unit", f_alpha="unit_closed",
                                  refresh="positive_count", dt_min="positive",
                                  patience="count", patience_below="positive",
                                  max_move="positive"))
        if not self.dt_min < self.dt_start <= self.dt_max:
            raise ParameterError(f"FIRE needs dt_min < dt_start <= dt_max; got dt_min="
                                 f"{self.dt_min}, dt_start={self.dt_start}, "
                                 f"dt_max={self.dt_max}")

    #: the force at y0 comes from the first step (a null step), so that the force is
    #: traced once, inside the loop (a second copy in `init` costs seconds of compile)
    lazy_force = True

    def init(self, system, y, args):
        n = y.shape[0]
        one = lambda v: jnp.asarray(v, y.dtype)
        return dict(F=jnp.zeros_like(y), v=jnp.zeros_like(y), m=jnp.zeros((n,), y.dtype),
                    sq=jnp.ones((n, 1), y.dtype), dmin=jnp.full((n,), jnp.inf, y.dtype),
                    stiff=jnp.zeros((n,), y.dtype), dt=one(self.dt_start),
                    alpha=one(self.alpha_start), npos=jnp.asarray(0), n=jnp.asarray(0),
                    evals=jnp.asarray(0), refused=jnp.asarray(False),
                    admissible=jnp.asarray(True), r=one(jnp.inf), scale=one(1.0),
                    best=one(jnp.inf), mark=jnp.asarray(0), best_y=y, rmin=one(jnp.inf))

    def step(self, system, y, args, s):
        free = system.free
        first = s["n"] == 0                     # the null step: F = v = 0, so y stays
        due = s["n"] % self.refresh == 0
        m = jax.lax.cond(unvmap_any(due), lambda m: jnp.where(
            due, jnp.maximum(m, jnp.where(free, system.bound(y, args), 1.0)), m),
            lambda m: m, s["m"])
        sq = jnp.sqrt(m + s["stiff"])[:, None]
        v = s["v"] * sq / s["sq"]               # the same velocity under the new masses
        f = s["F"] / sq
        up = jnp.sum(f * v) > 0
        npos = jnp.where(up, s["npos"] + 1, 0)
        grow = up & (npos > self.n_min)
        dt = jnp.where(grow, jnp.minimum(s["dt"] * self.f_inc, self.dt_max),
                       jnp.where(up | first, s["dt"], s["dt"] * self.f_dec))
        alpha = jnp.where(grow, s["alpha"] * self.f_alpha,
                          jnp.where(up | first, s["alpha"], self.alpha_start))
        v = jnp.where(up, v, 0.0) + dt * f      # uphill: stop (FIRE 2.0 without the half step back)
        vn, fn = jnp.linalg.norm(v), jnp.linalg.norm(f)
        v = (1.0 - alpha) * v + alpha * vn * f / jnp.where(fn > 0, fn, 1.0)
        dy = dt * v / sq
        cap = jnp.minimum(CONTACT_MOVE * s["dmin"],
                          jnp.minimum(system.step_cap(y, args), self.max_move))
        big = jnp.linalg.norm(dy, axis=-1)
        cut = jnp.where(big > cap, jnp.maximum(cap, 0.0) / jnp.where(big > 0, big, 1.0),
                        1.0)[:, None]
        y0, yn = y, y + dy * cut
        v = v * cut
        args0, args = args, system.update(yn, args)
        F, scale, dmin, stiff = system.parts(yn, args)
        # a step out of the admissible set is refused: back to y0, at rest, half the dt
        admissible = system.admissible(yn, args)
        refuse = ~first & ~admissible
        keep = lambda new, old: jnp.where(refuse, old, new)
        yn, F, scale = keep(yn, y0), keep(F, s["F"]), keep(scale, s["scale"])
        dmin, stiff = keep(dmin, s["dmin"]), keep(stiff, s["stiff"])
        args = jax.tree_util.tree_map(lambda a, b: jnp.where(refuse, b, a), args, args0)
        v = jnp.where(refuse, 0.0, v)
        dt = jnp.where(refuse, dt * self.f_dec, dt)
        alpha = jnp.where(refuse, self.alpha_start, alpha)
        npos = jnp.where(refuse, 0, npos)
        n = s["n"] + 1
        r = jnp.linalg.norm(F) / jnp.where(scale > 0, scale, 1.0)
        # the best state so far (for a Newton finish), and patience: the step at which
        # the residual last fell below half its value at the step before that
        better = ~first & (r < s["rmin"])
        best_y, rmin = jnp.where(better, yn, s["best_y"]), jnp.where(better, r, s["rmin"])
        halved = ~first & (r < 0.5 * s["best"])
        best, mark = jnp.where(halved, r, s["best"]), jnp.where(halved, n, s["mark"])
        return yn, args, dict(F=F, v=v, m=m, sq=sq, dmin=dmin, stiff=stiff, dt=dt,
                              alpha=alpha, npos=npos, n=n, evals=s["evals"] + 1,
                              refused=refuse, admissible=admissible | refuse, r=r,
                              scale=scale, best=best, mark=mark, best_y=best_y, rmin=rmin)

    def terminate(self, system, y, args, s):
        started = s["n"] > 0
        ok = started & (s["r"] < self.rtol)
        bad = jnp.where(started, check_state(system, y, args, s["F"], s["admissible"]), -1)
        stuck = s["refused"] & (s["dt"] < self.dt_min)
        bad = jnp.where((bad < 0) & stuck, RESULTS.stretch_limit, bad)
        stalled = ((self.patience > 0) & (s["rmin"] < self.patience_below)
                   & (s["n"] - s["mark"] > jnp.maximum(self.patience, s["n"] // 2)))
        bad = jnp.where((bad < 0) & ~ok & stalled, RESULTS.stagnation, bad)
        return ok | (bad >= 0), jnp.where(bad >= 0, bad, RESULTS.successful)

    def stats(self, s):
        return dict(force_evals=s["evals"], hvps=jnp.asarray(0))
