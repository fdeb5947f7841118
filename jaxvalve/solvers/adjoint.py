"""The implicit-function adjoint of an equilibrium: one linear solve, never the solver.

At an equilibrium R(x*, p) = 0 the derivative of any g(x*) follows from one solve
K^T mu = dg/dx with K = -dR/dx on the free dofs; then dg/dp = mu . dR/dp, and the fixed
positions of x0 get g + mu . dR/dx there.

* `solve_lu` solves K^T mu = g with the sparse LU of the exact tangent
  (`jaxvalve.solvers.tangent.Tangent`: membrane, bending, the follower pressure's
  unsymmetric part and the barrier pairs' Hessians), on the host, and checks each
  solution against the residual's VJP (`residual_vjp`), which is independent of the
  assembled matrix.
* `implicit_state` returns a solve's x* as a differentiable function of the parameters
  and x0 (a `jax.custom_vjp` whose backward pass calls `solve_lu` through a host
  callback), so `jax.grad` of anything computed from it is exact; `equilibrium.solve`
  returns its state through it.

On the barrier contact the residual holds the barrier energy over the closure's *fixed*
active pair list (`FixedPairs`), its collision weights functions of the reference
coordinates (`jaxvalve.contact.barrier.collision_weights`), so derivatives with respect
to the template include them.  The list is exact near an equilibrium: every pair closer
than d_hat is active there, and a pair enters the barrier's range with zero energy, force
and stiffness (the barrier is C2 at d_hat).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as spla

from ..contact.barrier import collision_weights, pair_weights
from ..errors import ConvergenceError, ParameterError
from ..mechanics import assembly
from .tangent import Tangent

__all__ = ["FixedPairs", "fixed_pairs", "residual", "residual_vjp", "solve_lu",
           "implicit_state", "AdjointReport", "ADJOINT_RTOL"]

#: an adjoint solution whose relative residual ||K^T mu - g|| / ||g||, checked by the
#: residual's VJP, exceeds this is refused (`ConvergenceError`)
ADJOINT_RTOL = 1e-8

#: rows of a fixed pair list are padded to a multiple of this (padding rows weigh 0), so
#: closures whose lists differ in length share compiled programs
PAD = 512


@dataclasses.dataclass(frozen=True)
class AdjointReport:
    """residual: ||K^T mu - g|| / ||g|| by the residual's VJP; seconds: wall time
    (assembly, factorisation, solve and check); nnz: nonzeros of the factorised matrix."""

    residual: float
    seconds: float
    nnz: int


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FixedPairs:
    """The active barrier pairs of a converged closure, compacted and padded: pt (P, 4)
    [p, t0, t1, t2], ee (Q, 4) [a0, a1, b0, b1] and ee_id (Q, 2) their edge rows; the
    first n_pt, n_ee rows are pairs, the rest copies of them weighing 0.  tri_edge (M, 3)
    and n_edges (static) map triangles to edges for the collision weights."""

    pt: Any
    n_pt: Any
    ee: Any
    ee_id: Any
    n_ee: Any
    tri_edge: Any
    n_edges: int = dataclasses.field(metadata=dict(static=True))


def _padded(rows, n):
    rows = np.asarray(rows)[:n]
    if n == 0:
        return rows
    m = -(-n // PAD) * PAD
    return np.concatenate([rows, np.repeat(rows[:1], m - n, axis=0)])


def fixed_pairs(sol, compact: bool = True) -> FixedPairs | None:
    """The `FixedPairs` of a solve's final active list (None without barrier contact):
    compacted to a multiple of `PAD` rows, or, inside a trace or with compact=False, at
    the list's own capacity (its padding rows weigh 0)."""
    if sol.lists is None or sol.topo is None:
        return None
    act = sol.lists.act
    if (not compact or isinstance(act.n_pt, jax.core.Tracer)
            or isinstance(act.n_ee, jax.core.Tracer)):
        return FixedPairs(pt=act.pt, n_pt=act.n_pt, ee=act.ee, ee_id=act.ee_id,
                          n_ee=act.n_ee, tri_edge=sol.topo.tri_edge,
                          n_edges=int(sol.topo.n_edges))
    n_pt, n_ee = int(act.n_pt), int(act.n_ee)
    return FixedPairs(pt=jnp.asarray(_padded(act.pt, n_pt)), n_pt=jnp.asarray(n_pt),
                      ee=jnp.asarray(_padded(act.ee, n_ee)),
                      ee_id=jnp.asarray(_padded(act.ee_id, n_ee)), n_ee=jnp.asarray(n_ee),
                      tri_edge=sol.topo.tri_edge, n_edges=int(sol.topo.n_edges))


def residual(x, problem, params, pairs: FixedPairs | None):
    """R(x, params) (N, 3) N: internal, pressure and barrier forces on free nodes, the
    barrier over the fixed pair list ``pairs``."""
    ref = assembly.prepare(problem, params)
    F, _ = assembly.membrane_force(x, problem, params, ref)
    if pairs is None:
        return F
    nw, ew, l2 = collision_weights(params.ref, problem.triangles, pairs.tri_edge,
                                   pairs.n_edges)
    pt_w, ee_w, eps = pair_weights(nw, ew, l2, pairs.pt[:, 0], pairs.ee_id)
    pt_w = jnp.where(jnp.arange(pairs.pt.shape[0]) < pairs.n_pt, pt_w, 0.0)
    ee_w = jnp.where(jnp.arange(pairs.ee.shape[0]) < pairs.n_ee, ee_w, 0.0)
    g = jax.grad(lambda z: params.contact.energy_pairs(z, pairs.pt, pt_w, pairs.ee, ee_w,
                                                       eps))(x)
    return F - g * problem.free[:, None]


@jax.jit
def residual_vjp(x, problem, params, pairs, v):
    """(v . dR/dx (N, 3), v . dR/dparams (a `Params`)) at x (N, 3) for v (N, 3): the
    adjoint's K^T products and its pullback to the parameters."""
    return jax.vjp(lambda z, p: residual(z, problem, p, pairs), x, params)[1](v)


def _check_rhs(g, N):
    g = np.asarray(g, float)
    if g.ndim not in (2, 3) or g.shape[-2:] != (N, 3):
        raise ParameterError(f"the adjoint's right-hand side g must be ({N}, 3) or "
                             f"(k, {N}, 3) (one row per node); got shape {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ParameterError(f"the adjoint's right-hand side g must be finite; it holds "
                             f"{int(np.sum(~np.isfinite(g)))} NaN or infinite entries")
    return g


def solve_lu(problem, params, x, pairs: FixedPairs | None, g):
    """mu (N, 3) with K^T mu = g on the free dofs (K = -dR/dx at the equilibrium x), zero
    on fixed nodes, by the sparse LU of the exact tangent, each solution checked by the
    residual's VJP.  g (k, N, 3): k right-hand sides share one factorisation; then mu
    (k, N, 3) and k reports.  Returns (mu, `AdjointReport`); raises `ParameterError` on
    a g of the wrong shape or not finite (before any assembly) and `ConvergenceError`
    when a check misses `ADJOINT_RTOL`."""
    t0 = time.perf_counter()
    N = problem.n_nodes
    g = _check_rhs(g, N)
    many = g.ndim == 3
    tan = Tangent(problem)
    weights = None
    if pairs is not None:
        weights = collision_weights(params.ref, problem.triangles, pairs.tri_edge,
                                    pairs.n_edges)
    K = tan.matrix(x, params, pairs, weights)
    lu = spla.splu(K.T.tocsc(), permc_spec="MMD_AT_PLUS_A")
    fdof = np.repeat(np.asarray(problem.free), 3)
    mus, reps = [], []
    for gi in (g if many else g[None]):
        b = gi.reshape(-1)[fdof]
        mu = np.zeros(3 * N)
        res = 0.0
        nb = np.linalg.norm(b)
        if nb > 0.0:
            mu[fdof] = lu.solve(b)
            gx, _ = residual_vjp(jnp.asarray(x), problem, params, pairs,
                                 jnp.asarray(mu.reshape(N, 3)))
            res = float(np.linalg.norm(-np.asarray(gx).reshape(-1)[fdof] - b) / nb)
            if not res <= ADJOINT_RTOL:
                raise ConvergenceError(
                    f"the adjoint solve of the equilibrium gradient failed: the exact "
                    f"tangent's solution has a relative residual of {res:.3e} by the "
                    f"residual's VJP (it must be <= {ADJOINT_RTOL:g}); the state is not an "
                    f"equilibrium of this pair list, or K is singular there")
        mus.append(mu.reshape(N, 3))
        reps.append(AdjointReport(res, time.perf_counter() - t0, int(lu.nnz)))
    return (np.stack(mus), tuple(reps)) if many else (mus[0], reps[0])


def _zeros_like(t):
    return jax.tree_util.tree_map(
        lambda a: (None if not jnp.issubdtype(jnp.asarray(a).dtype, jnp.inexact)
                   else jnp.zeros_like(a)), t)


def _raise_unconverged(res):
    res = float(res)
    if not res <= ADJOINT_RTOL:                  # NaN fails too
        raise ConvergenceError(
            f"the adjoint solve of the equilibrium gradient failed: the exact tangent's "
            f"solution has a relative residual of {res:.3e} by the residual's VJP (it must "
            f"be <= {ADJOINT_RTOL:g})")


def implicit_state(problem, params, x0, sol):
    """sol.x, an equilibrium of ``problem`` under ``params`` from x0 (its fixed nodes),
    as a differentiable function of params and x0: its VJP is one adjoint solve with the
    exact tangent, never the solver.  The tangent's blocks are computed in the backward
    program; their assembly and sparse LU run in a host callback (NumPy and SciPy only),
    and the solution is checked there after by the residual's VJP: above `ADJOINT_RTOL`
    the gradient is NaN and a `ConvergenceError` is raised (from inside jit too).
    ``sol`` must have converged (`Solution`, with its pair lists where the contact is
    the barrier); ``problem`` must be concrete (the tangent's pattern is built on the
    host)."""
    from ..contact.barrier import BarrierContact
    if params.contact is not None and not isinstance(params.contact, BarrierContact):
        raise ParameterError("the adjoint differentiates the barrier contact only (the "
                             "paper's contact law (2.2) is not differentiable)")
    if not isinstance(sol.result, jax.core.Tracer) and int(sol.result) != 0:
        from .base import RESULTS
        raise ConvergenceError(f"no adjoint of a state that is not an equilibrium: the solve "
                               f"ended with {RESULTS(int(sol.result)).name}, relative "
                               f"residual {float(sol.stats.residual):.3e}")
    pairs = fixed_pairs(sol) if params.contact is not None else None
    tan = Tangent(problem)
    fdof = np.repeat(~np.asarray(problem.fixed), 3)

    def host_mu(tri, hin, pt, ee, pt_rows, ee_rows, counts, g):
        K = tan.assemble(tri, hin, pt, ee, pt_rows, ee_rows, counts)
        g = np.asarray(g)
        mu = np.zeros(g.size, g.dtype)
        b = g.reshape(-1)[fdof]
        if np.linalg.norm(b) > 0:
            mu[fdof] = spla.splu(K.T.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(b)
        return mu.reshape(g.shape)

    @jax.custom_vjp
    def state(params, x0, x, pairs):
        return x

    def fwd(params, x0, x, pairs):
        return x, (params, x, pairs)

    def bwd(res, g):
        params, x, pairs = res
        weights = None
        if pairs is not None:
            weights = collision_weights(params.ref, problem.triangles, pairs.tri_edge,
                                        pairs.n_edges)
        tri, hin, pt, ee = tan.blocks(x, params, pairs, weights)
        rows = ((pairs.pt, pairs.ee, jnp.stack([pairs.n_pt, pairs.n_ee]))
                if pairs is not None else (None, None, jnp.zeros(2, jnp.int32)))
        mu = jax.pure_callback(host_mu, jax.ShapeDtypeStruct(x.shape, x.dtype), tri, hin,
                               pt, ee, *rows, g, vmap_method="sequential")
        gx, gp = residual_vjp(x, problem, params, pairs, mu)
        free = problem.free[:, None]
        gf = g * free
        ng = jnp.linalg.norm(gf)
        err = jnp.linalg.norm((gx + g) * free) / jnp.where(ng > 0, ng, 1.0)
        jax.debug.callback(_raise_unconverged, err)
        ok = err <= ADJOINT_RTOL
        gp = jax.tree_util.tree_map(lambda a: jnp.where(ok, a, jnp.nan), gp)
        # x*[fixed] = x0[fixed], and R depends on x0[fixed] through x*
        gx0 = jnp.where(ok, (g + gx) * problem.fixed[:, None], jnp.nan)
        return gp, gx0, jnp.zeros_like(x), _zeros_like(pairs)

    state.defvjp(fwd, bwd)
    return state(params, x0, jax.lax.stop_gradient(sol.x), pairs)
