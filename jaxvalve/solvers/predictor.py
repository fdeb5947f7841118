"""A one-mode predictor for a slack membrane under pressure.

At a flat (or slack) start the out-of-plane stiffness is zero and Newton cannot start.  The
shape of a membrane under uniform tension T and pressure solves T L phi = F_pressure, with L
the cotangent Laplacian of the reference mesh.  The predictor takes phi, then finds the
amplitude s where the force along that mode vanishes, phi . F(x0 + s phi) = 0 (a one-mode
Galerkin solve, by bracketing and regula falsi).  It does one step.

A trial amplitude whose state is past the material's stretch limit (Gent) or has a
non-finite force counts as "too far", like a negative mode force: the bracket then closes
there and the root search bisects towards the admissible side.  (Past the Gent limit the
strain energy is masked, so the mode force there is the bare pressure load; read at face
value it kept the bracket growing until it gave up and the predictor left the membrane
flat, where Newton cannot start.)
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from .base import RESULTS, check_settings


@dataclasses.dataclass(frozen=True)
class BulgePredictor:
    """Predict the bulge of a pressurised membrane from the start state (one step)."""

    cg_steps: int = 400
    root_steps: int = 20
    max_steps: int = 1

    def __post_init__(self):
        check_settings(self, dict(cg_steps="positive_count", root_steps="positive_count",
                                  max_steps="count"))

    def init(self, system, y, args):
        return dict(n=jnp.asarray(0), evals=jnp.asarray(0))

    def _shape(self, system, y, args):
        free = system.free[:, None]
        b = system.force(y, args)  # at a slack start this is the pressure load
        A = lambda v: system.laplacian(v * free, args) * free
        phi, _ = jax.scipy.sparse.linalg.cg(A, b, maxiter=self.cg_steps, tol=1e-6)
        return phi * free

    def step(self, system, y, args, s):
        phi = self._shape(system, y, args)

        def g(t):
            """Mode force phi . F at amplitude t; -inf where the state is not admissible."""
            z = y + t * phi
            gt = jnp.sum(phi * system.force(z, args))
            valid = jnp.isfinite(gt) & system.admissible(z, args)
            return jnp.where(valid, gt, -jnp.inf)

        pmax = jnp.max(jnp.linalg.norm(phi, axis=-1))
        span = jnp.max(jnp.ptp(y, axis=0))
        t0 = 1e-3 * span / jnp.where(pmax > 0, pmax, 1.0)

        # bracket: double t until the mode force changes sign (or the state is too far)
        def bcond(c):
            t, gt, k = c
            return (gt > 0) & (k < 40)

        def bbody(c):
            t, gt, k = c
            return 2.0 * t, g(2.0 * t), k + 1

        t_hi, g_hi, kb = jax.lax.while_loop(bcond, bbody, (t0, g(t0), jnp.asarray(0)))
        t_lo = jnp.where(kb > 0, 0.5 * t_hi, 0.0)
        g_lo = g(t_lo)

        def rbody(_, c):  # Illinois regula falsi; bisection while the upper end is too far
            a, ga, b, gb, side = c
            rf = (a * gb - b * ga) / jnp.where(gb != ga, gb - ga, 1.0)
            t = jnp.where(jnp.isfinite(gb), rf, 0.5 * (a + b))
            gt = g(t)
            pos = gt > 0
            a2, ga2 = jnp.where(pos, t, a), jnp.where(pos, gt, jnp.where(side == -1, 0.5 * ga, ga))
            b2, gb2 = jnp.where(pos, b, t), jnp.where(pos, jnp.where(side == 1, 0.5 * gb, gb), gt)
            return a2, ga2, b2, gb2, jnp.where(pos, 1, -1)

        a, ga, b, gb, _ = jax.lax.fori_loop(0, self.root_steps, rbody,
                                            (t_lo, g_lo, t_hi, g_hi, jnp.asarray(0)))
        # the end with the smaller mode force; an end past the limit (-inf) is never taken
        near = jnp.abs(ga) < jnp.abs(gb)
        t, gt = jnp.where(near, a, b), jnp.where(near, ga, gb)
        ok = (g_hi <= 0) & jnp.isfinite(t) & jnp.isfinite(gt)
        y = jnp.where(ok, y + t * phi, y)
        return y, args, dict(n=s["n"] + 1, evals=s["evals"] + kb + self.root_steps + 2)

    def terminate(self, system, y, args, s):
        return s["n"] >= 1, jnp.asarray(RESULTS.successful)

    def stats(self, s):
        return dict(force_evals=s["evals"], hvps=jnp.asarray(0))
