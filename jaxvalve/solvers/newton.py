"""Newton-Krylov with Levenberg-Marquardt damping.

Hessian-vector products come from `jax.linearize` of the force; the linear solve is a
preconditioned CG (block-Jacobi: the 3x3 nodal blocks of the element stiffness, with their
eigenvalues made positive).  A step that meets negative curvature or fails to reduce the
residual raises the damping mu in (K + mu B) d = F; a good full step lowers it.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..errors import ParameterError
from .base import RESULTS, check_settings, check_state, relative_residual
from .predictor import BulgePredictor


def _precond(B, free, floor_rel=1e-8):
    """Eigen-decomposed positive blocks (V (N,3,3), w (N,3)) of the block diagonal B."""
    w, V = jnp.linalg.eigh(0.5 * (B + jnp.swapaxes(B, -1, -2)))
    w = jnp.abs(w)
    w = jnp.maximum(w, floor_rel * jnp.max(w))
    w = jnp.where(free[:, None], w, 1.0)
    return V, w


def _apply_blocks(V, w, r):
    """V diag(w) V^T r per node."""
    return jnp.einsum("nij,nj,nkj,nk->ni", V, w, V, r)


@dataclasses.dataclass(frozen=True)
class NewtonKrylov:
    """Damped Newton-Krylov to a relative force residual ``rtol``.

    warm_start: solvers run first, in order (default: the one-mode `BulgePredictor`, then
    nothing else); Newton cannot start from a flat membrane under
    pressure, where the out-of-plane stiffness is zero.
    max_step: largest nodal displacement of one Newton step (mm), a trust radius.
    """

    rtol: float = 1e-6
    max_steps: int = 200
    cg_max: int = 300
    eta_max: float = 0.1
    eta_min: float = 1e-4
    max_step: float = 1.0
    mu0: float = 1e-3
    ls_steps: int = 5
    max_fails: int = 12
    warm_start: tuple = (BulgePredictor(),)

    def __post_init__(self):
        check_settings(self, dict(rtol="positive", max_steps="count", cg_max="positive_count",
                                  eta_max="unit", eta_min="unit", max_step="positive",
                                  mu0="positive", ls_steps="count", max_fails="count"))
        if not self.eta_min <= self.eta_max:
            raise ParameterError(f"NewtonKrylov needs eta_min <= eta_max; got eta_min="
                                 f"{self.eta_min}, eta_max={self.eta_max}")
        for w in self.warm_start or ():
            if not (hasattr(w, "init") and hasattr(w, "step") and hasattr(w, "terminate")):
                raise ParameterError(f"NewtonKrylov.warm_start must hold solvers (with init, "
                                     f"step and terminate); got {w!r}")

    def init(self, system, y, args):
        F = system.force(y, args)
        return dict(F=F, F0=jnp.linalg.norm(F), mu=jnp.asarray(self.mu0, y.dtype),
                    n=jnp.asarray(0), fails=jnp.asarray(0), evals=jnp.asarray(1),
                    hvps=jnp.asarray(0))

    def _cg(self, Av, Pinv, F, tol):
        def cond(c):
            x, r, z, p, rz, j, neg = c
            return (j < self.cg_max) & (jnp.linalg.norm(r) > tol) & ~neg

        def body(c):
            x, r, z, p, rz, j, neg = c
            Ap = Av(p)
            pAp = jnp.sum(p * Ap)
            neg = pAp <= 0
            a = rz / jnp.where(neg, 1.0, pAp)
            x_new = x + a * p
            r_new = r - a * Ap
            z_new = Pinv(r_new)
            rz_new = jnp.sum(r_new * z_new)
            p_new = z_new + (rz_new / rz) * p
            keep = lambda old, new: jnp.where(neg, old, new)
            return (keep(x, x_new), keep(r, r_new), keep(z, z_new), keep(p, p_new),
                    keep(rz, rz_new), j + 1, neg)

        z0 = Pinv(F)
        c0 = (jnp.zeros_like(F), F, z0, z0, jnp.sum(F * z0), jnp.asarray(0), jnp.asarray(False))
        x, r, z, p, rz, j, neg = jax.lax.while_loop(cond, body, c0)
        # negative curvature on the first direction: fall back to the preconditioned force
        x = jnp.where(neg & (jnp.max(jnp.abs(x)) == 0), z0, x)
        return x, j, neg

    def step(self, system, y, args, s):
        args = system.update(y, args)
        free = system.free[:, None]
        F = s["F"]
        Fn = jnp.linalg.norm(F)
        force = lambda z: system.force(z, args)
        _, f_lin = jax.linearize(force, y)
        V, w = _precond(system.block_diag(y, args), system.free)
        mu = s["mu"]
        Av = lambda v: -f_lin(v * free) + mu * _apply_blocks(V, w, v) * free
        Pinv = lambda r: _apply_blocks(V, 1.0 / ((1.0 + mu) * w), r) * free
        eta = jnp.clip(jnp.sqrt(Fn / s["F0"]), self.eta_min, self.eta_max)
        d, n_cg, neg = self._cg(Av, Pinv, F, eta * Fn)
        dmax = jnp.max(jnp.linalg.norm(d, axis=-1))
        limit = jnp.minimum(self.max_step, system.step_cap(y, args))
        alpha0 = jnp.minimum(1.0, limit / jnp.where(dmax > 0, dmax, 1.0))

        def ls_cond(c):
            alpha, k, ok, _, _ = c
            return (~ok) & (k < self.ls_steps)

        def ls_body(c):
            alpha, k, _, _, _ = c
            yt = y + alpha * d
            Ft = force(yt)
            Ftn = jnp.linalg.norm(Ft)
            ok = (Ftn < (1.0 - 1e-4 * alpha) * Fn) & jnp.isfinite(Ftn) & system.admissible(yt, args)
            return jnp.where(ok, alpha, 0.25 * alpha), k + 1, ok, yt, Ft

        alpha, k, ok, yt, Ft = jax.lax.while_loop(
            ls_cond, ls_body, (alpha0, jnp.asarray(0), jnp.asarray(False), y, F))
        full = ok & (k == 1) & ~neg
        mu = jnp.where(ok, jnp.where(full, mu * 0.1, mu), jnp.maximum(mu * 10.0, 1e-4))
        mu = jnp.where(neg, jnp.maximum(mu * 4.0, 1e-4), mu)
        y = jnp.where(ok, yt, y)
        F = jnp.where(ok, Ft, F)
        return y, args, dict(F=F, F0=s["F0"], mu=mu, n=s["n"] + 1,
                       fails=jnp.where(ok, 0, s["fails"] + 1), evals=s["evals"] + k,
                       hvps=s["hvps"] + n_cg + 1)

    def terminate(self, system, y, args, s):
        ok = relative_residual(system, y, args, s["F"]) < self.rtol
        bad = check_state(system, y, args, s["F"])
        stuck = (s["fails"] >= self.max_fails) | (s["mu"] > 1e12)
        code = jnp.where(bad >= 0, bad, jnp.where(ok, RESULTS.successful, RESULTS.stagnation))
        return ok | (bad >= 0) | stuck, code

    def stats(self, s):
        return dict(force_evals=s["evals"], hvps=s["hvps"])
