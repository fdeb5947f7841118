"""The paper's Algorithm 2.1: damped fixed point x <- x + delta F."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp

import jax

from ..unvmap import unvmap_any
from ..errors import ParameterError
from .base import RESULTS, check_settings, check_state, relative_residual


@dataclasses.dataclass(frozen=True)
class FixedPoint:
    """Algorithm 2.1 (explicit damped fixed point).

    delta: step (mm/N).  None derives it from a stiffness bound: delta = safety / max_i b_i,
    with b_i >= lambda_max(K) the per-node element bound (`assembly.stiffness_bound`), which
    keeps the iteration stable (it needs delta < 2 / lambda_max).  Stiffening materials raise
    lambda_max along the path, so the bound takes each model at its stiffest tangent modulus,
    is re-evaluated every ``refresh`` steps and whenever ||F|| doubles in one step, and delta
    only ever decreases (refresh=0 keeps the paper's constant delta).
    Stopping: the paper's rule ||dx^n|| < step_rtol ||dx^0|| when ``rtol`` is None, else the
    relative force residual ||F_free|| / ||F_pressure|| < rtol.
    """

    rtol: float | None = None
    step_rtol: float = 1e-3
    max_steps: int = 200_000
    delta: float | None = None
    safety: float = 1.0
    refresh: int = 200

    def __post_init__(self):
        # safety < 2: delta = safety / lambda_max must stay below the stability limit 2 / lambda_max
        check_settings(self, dict(rtol="positive", step_rtol="unit", max_steps="count",
                                  delta="positive", safety="positive", refresh="count"),
                       optional=("rtol", "delta"))
        if not self.safety < 2:
            raise ParameterError(f"FixedPoint.safety must lie in (0, 2) (the explicit "
                                 f"iteration is unstable past 2); got {self.safety}")

    def _delta_bound(self, system, y, args):
        return self.safety / jnp.max(jnp.where(system.free, system.bound(y, args), 0.0))

    def init(self, system, y, args):
        F = system.force(y, args)
        delta = (self._delta_bound(system, y, args) if self.delta is None
                 else jnp.asarray(self.delta, y.dtype))
        Fn = jnp.linalg.norm(F)
        return dict(F=F, Fn=Fn, delta=delta, dx0=delta * Fn, dx=delta * Fn, n=jnp.asarray(0),
                    evals=jnp.asarray(1))

    def step(self, system, y, args, s):
        args = system.update(y, args)
        y = y + s["delta"] * s["F"]
        F = system.force(y, args)
        delta = s["delta"]
        Fn = jnp.linalg.norm(F)
        if self.delta is None and self.refresh > 0:
            # refresh on schedule, and at once when the force grows (onset of instability)
            due = ((s["n"] + 1) % self.refresh == 0) | (Fn > 2.0 * s["Fn"])
            delta = jax.lax.cond(
                unvmap_any(due),
                lambda d: jnp.where(due, jnp.minimum(d, self._delta_bound(system, y, args)), d),
                lambda d: d, delta)
        return y, args, dict(F=F, Fn=Fn, delta=delta, dx0=s["dx0"], dx=delta * Fn,
                             n=s["n"] + 1, evals=s["evals"] + 1)

    def terminate(self, system, y, args, s):
        if self.rtol is None:
            ok = s["dx"] < self.step_rtol * s["dx0"]
        else:
            ok = relative_residual(system, y, args, s["F"]) < self.rtol
        bad = check_state(system, y, args, s["F"])
        done = ok | (bad >= 0)
        return done, jnp.where(bad >= 0, bad, RESULTS.successful)

    def stats(self, s):
        return dict(force_evals=s["evals"], hvps=jnp.asarray(0))
