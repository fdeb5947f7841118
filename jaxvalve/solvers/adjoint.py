"""The implicit-function adjoint of the equilibrium, with its two linear-solve backends.

At an equilibrium R(x*, p) = 0 the derivative of any g(x*) follows from one solve
K^T mu = dg/dx with K = -dR/dx on the free dofs, then dg/dp = mu . dR/dp (and the fixed
positions of x0 get g + mu . dR/dx there).  The solve runs in one of two ways:

* **traced** (`solve_traced`, `cotangents`): GMRES in JAX on exact vector-Jacobian
  products, preconditioned by the 3x3 nodal blocks of the element stiffness made positive
  (the Newton solver's preconditioner).  It runs inside `jax.grad` and `jit`: the custom
  VJPs of `equilibrium.solve` and `equilibrium.implicit_state` call `cotangents`.  An
  adjoint whose relative residual is above `ADJOINT_ACCEPT` raises (a host callback, from
  inside jit too) and poisons the gradient with NaN.
* **LU** (`solve_lu`, on the host): scipy's GMRES on the same exact products
  (`residual_vjp`), preconditioned by the sparse LU of the assembled tangent
  (`jaxvalve.solvers.tangent.assemble`).  Much faster on valves, where contact makes block-Jacobi
  weak (docs/gradients-and-optimisation.md, "Why not block-Jacobi"); the optimiser's
  default (``adjoint="lu"``).  It returns an `AdjointReport` and raises
  `ConvergenceError` when GMRES misses its tolerance.

`residual_vjp` is the one compiled program of the residual's VJP that the LU backend and
the optimiser's pullback to the design parameters share.

On the barrier contact (``nbrs`` a `jaxvalve.contact.ipc_pairs.BarrierPairs`, the pair
list of a barrier closure) the LU backend solves with the *exact* Jacobian that the
barrier solver assembles (`solvers.barrier_newton`: membrane, bending and pair Hessians,
the follower pressure's unsymmetric part), by its sparse LU, and checks the solution with
the residual's VJP; that VJP holds the barrier energy over the fixed pair list, whose
collision weights are functions of the reference coordinates (`contact.barrier.
collision_weights`), so derivatives with respect to the template include them.  The pair
list is exact near an equilibrium: a pair enters the barrier's range at d_hat with zero
energy, force and stiffness (the barrier is C2 there).
"""
from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as spla

from ..mechanics import assembly
from ..contact.neighbours import whole_lists
from ..errors import ConvergenceError, ParameterError
from ..quick_jit import quick_jit
from .newton import _apply_blocks, _precond
from .tangent import assemble

__all__ = ["cotangents", "solve_traced", "solve_lu", "residual_vjp", "AdjointReport",
           "ADJOINT_TOL", "ADJOINT_MAXITER", "ADJOINT_ACCEPT"]


@dataclasses.dataclass(frozen=True)
class AdjointReport:
    """iterations: GMRES iterations; residual: ||K^T mu - g|| / ||g||; seconds: wall time
    (assembly, factorisation and GMRES); nnz: nonzeros of the assembled matrix."""

    iterations: int
    residual: float
    seconds: float
    nnz: int


#: The JAX adjoint's GMRES: its target (relative residual) and iteration cap, and the
#: relative residual above which the gradient is refused (`ConvergenceError`).
ADJOINT_TOL, ADJOINT_MAXITER, ADJOINT_ACCEPT = 1e-12, 2000, 1e-8


def solve_traced(problem, params, x, nbrs, delta, g):
    """mu solving K^T mu = g on free dofs (K = -dR/dx); returns (mu, vjp_fn of R, relative
    residual ||K^T mu - g|| / ||g|| of the GMRES solution)."""
    free = problem.free[:, None]

    def R(xx, pp):
        ref = assembly.prepare(problem, pp)
        return assembly.residual(xx, problem, pp, ref, nbrs, delta)

    _, vjp = jax.vjp(R, x, params)
    ref = assembly.prepare(problem, params)
    V, w = _precond(assembly.block_diagonal(x, problem, params, ref), problem.free)
    KT = lambda v: -vjp(v * free)[0] * free
    M = lambda r: _apply_blocks(V, 1.0 / w, r) * free
    gf = g * free
    ng = jnp.linalg.norm(gf)
    mu, _ = jax.scipy.sparse.linalg.gmres(KT, gf, tol=0.0, atol=ADJOINT_TOL * ng, restart=60,
                                          maxiter=ADJOINT_MAXITER // 60 + 1, M=M,
                                          solve_method="batched")
    res = jnp.linalg.norm(KT(mu) - gf) / jnp.where(ng > 0, ng, 1.0)
    return mu, vjp, res


def _raise_unconverged(res):
    res = float(res)
    if not res <= ADJOINT_ACCEPT:        # NaN fails too
        raise ConvergenceError(
            f"the adjoint solve of the equilibrium gradient did not converge: relative "
            f"residual {res:.3e} after at most {ADJOINT_MAXITER} GMRES iterations (it must "
            f"be <= {ADJOINT_ACCEPT:g}); use the LU-preconditioned adjoint "
            f"(jaxvalve.solvers.adjoint.solve_lu, the optimiser's adjoint='lu') on valves")


def cotangents(problem, params, y, nb, delta, g):
    """(d/dparams, d/dx0) of <g, x*> at the equilibrium y: one adjoint solve."""
    mu, vjp, res = solve_traced(problem, params, y, nb, delta, g)
    # a gradient from an unconverged adjoint is wrong: raise (inside jit, via a host
    # callback) and poison it with NaN, never return it silently
    jax.debug.callback(_raise_unconverged, res)
    mu = jnp.where(res <= ADJOINT_ACCEPT, mu, jnp.nan)
    gx, gp = vjp(mu)
    # x*[fixed] = x0[fixed] directly, and R depends on x0[fixed] through x*
    return gp, (g + gx) * problem.fixed[:, None]


def residual_vjp(x, problem, params, nbrs, v):
    """(v . dR/dx (N, 3), v . dR/dparams (a `Params`)) for the residual R(x, params), v
    (N, 3).  One compiled program serves the adjoint's K^T products (`adjoint_solve`) and
    the pullback of an adjoint to the parameters (`optimize.Evaluator`).  nbrs: the
    closure's contact pair list (`BarrierPairs` on the barrier contact)."""
    from ..contact.ipc_pairs import BarrierPairs
    if isinstance(nbrs, BarrierPairs):
        rows = _barrier_rows(problem, nbrs)
        return _barrier_residual_vjp(x, problem, params, rows, v, n_edges=rows.pop("n"))
    return _residual_vjp(x, problem, params, nbrs, v)


@quick_jit
def _residual_vjp(x, problem, params, nbrs, v):
    def R(z, p):
        return assembly.residual(z, problem, p, assembly.prepare(problem, p), nbrs)
    with whole_lists():
        return jax.vjp(R, x, params)[1](v)


#: rows of a barrier pair list are padded to a multiple of this (padding rows weigh 0),
#: so that closures whose lists differ in length share compiled programs
BARRIER_PAD = 512


def _pad(a, n):
    out = np.zeros((n,) + a.shape[1:], a.dtype)
    out[:len(a)] = a
    return out


def _barrier_rows(problem, pairs) -> dict:
    """The pair list as padded integer arrays, with the edge map of the mesh."""
    from ..geometry.mesh import unique_edges
    edges, tri_edge = unique_edges(np.asarray(problem.triangles))
    P, Q = len(pairs.pt), len(pairs.ee)
    p_, q_ = (-(-max(k, 1) // BARRIER_PAD) * BARRIER_PAD for k in (P, Q))
    return dict(pt=_pad(np.asarray(pairs.pt, np.int64), p_),
                pt_on=_pad(np.ones(P), p_), ee=_pad(np.asarray(pairs.ee, np.int64), q_),
                ee_edges=_pad(np.asarray(pairs.ee_edges, np.int64), q_),
                ee_on=_pad(np.ones(Q), q_), tri_edge=tri_edge.astype(np.int64),
                n=int(len(edges)))


def barrier_energy(y, problem, params, rows, n_edges):
    """Strain, bending and barrier energy (N mm) at y (N, 3) over a padded pair list
    (`_barrier_rows`), the collision weights from ``params.ref``."""
    from ..contact.barrier import collision_weights, pair_weights
    ref = assembly.prepare(problem, params)
    e = assembly.conservative_energy(y, problem, params.replace(contact=None), ref)
    nw, ew, l2 = collision_weights(params.ref, problem.triangles, rows["tri_edge"], n_edges)
    pt_w, ee_w, ee_eps = pair_weights(nw, ew, l2, rows["pt"][:, 0], rows["ee_edges"])
    return e + params.contact.energy_pairs(y, rows["pt"], pt_w * rows["pt_on"], rows["ee"],
                                           ee_w * rows["ee_on"], ee_eps)


@functools.partial(jax.jit, static_argnames=("n_edges",))
def _barrier_residual_vjp(x, problem, params, rows, v, n_edges):
    def R(z, p):
        f = (assembly.pressure_force(z, problem.triangles, p.pressure)
             - jax.grad(barrier_energy)(z, problem, p, rows, n_edges))
        return f * problem.free[:, None]
    return jax.vjp(R, x, params)[1](v)


def _barrier_lu(problem, params, x, pairs, fdof, rtol):
    """`solve_lu` on the barrier contact: the exact Jacobian that the barrier solver
    assembles, and a solve of one right-hand side by its sparse LU, checked by the
    residual's VJP (module docstring).  Returns (K, solve(b) -> (mu_f, 0, residual))."""
    from .barrier_newton import _Model
    N = problem.n_nodes
    _, K = _Model(problem, params, None).tangent(np.asarray(x, float), pairs, exact=True)
    lu = spla.splu(K.T.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(b):
        mu = np.zeros(3 * N)
        mu[fdof] = lu.solve(b)
        # the check: K^T mu by the residual's VJP, independent of the assembled matrix
        gx, _ = residual_vjp(jnp.asarray(x), problem, params, pairs,
                             jnp.asarray(mu.reshape(N, 3)))
        res = float(np.linalg.norm(-np.asarray(gx).reshape(-1)[fdof] - b)
                    / np.linalg.norm(b))
        if not np.isfinite(res) or res > 100 * rtol:
            raise ConvergenceError(f"adjoint solve on the barrier contact: the exact "
                                   f"Jacobian's solution has a relative residual of "
                                   f"{res:.3e} by the residual's VJP (tolerance "
                                   f"{100 * rtol:g})")
        return mu[fdof], 0, res
    return K, solve


def _gmres_lu(problem, params, x, nbrs, fdof, rtol, maxiter):
    """`solve_lu` on the other contact laws: the assembled tangent (`tangent.assemble`),
    and a solve of one right-hand side by GMRES on the residual's VJPs preconditioned by
    its sparse LU.  Returns (K, solve(b) -> (mu_f, GMRES iterations, residual))."""
    x = jnp.asarray(x)
    N = problem.n_nodes
    K = assemble(problem, params, x, nbrs)
    lu = spla.splu(K.T.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def KT(vf):
        v = np.zeros(3 * N)
        v[fdof] = vf
        gx, _ = residual_vjp(x, problem, params, nbrs, jnp.asarray(v.reshape(N, 3)))
        return -np.asarray(gx).reshape(-1)[fdof]

    A = spla.LinearOperator(K.shape, matvec=KT, dtype=float)
    M = spla.LinearOperator(K.shape, matvec=lu.solve, dtype=float)

    def solve(b):
        count = [0]
        mu_f, _ = spla.gmres(A, b, M=M, rtol=rtol, atol=0.0, restart=60,
                             maxiter=maxiter // 60 + 1,
                             callback=lambda r: count.__setitem__(0, count[0] + 1),
                             callback_type="pr_norm")
        res = float(np.linalg.norm(KT(mu_f) - b) / np.linalg.norm(b))
        if not np.isfinite(res) or res > 100 * rtol:
            raise ConvergenceError(f"adjoint solve did not converge: relative residual "
                                   f"{res:.3e} after {count[0]} GMRES iterations "
                                   f"(tolerance {rtol:g})")
        return mu_f, count[0], res
    return K, solve


def solve_lu(problem, params, x, nbrs, g, *, rtol=1e-10, maxiter=300):
    """mu (N, 3) with K^T mu = g on the free dofs (K = -dR/dx at the equilibrium x); mu is
    zero on fixed nodes.  GMRES (scipy) on exact VJPs, preconditioned by the sparse LU of
    the assembled K^T (exact where `tangent.assemble` holds every term of the
    residual, as on the soft-min contact: then one iteration).  Returns (mu, `AdjointReport`).

    g (k, N, 3): k right-hand sides (e.g. one per metric) share one assembly and
    factorisation; then mu (k, N, 3) and a tuple of k reports (seconds counted from the
    start of the call).  A g of another shape, or with a NaN or infinite entry, raises
    `ParameterError` before any assembly."""
    from ..contact.ipc_pairs import BarrierPairs
    t0 = time.perf_counter()
    g = np.asarray(g, float)
    N = problem.n_nodes
    if g.ndim not in (2, 3) or g.shape[-2:] != (N, 3):
        raise ParameterError(f"solve_lu's right-hand side g must be ({N}, 3) or (k, {N}, 3) "
                             f"(one row per node); got shape {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ParameterError(f"solve_lu's right-hand side g must be finite; it holds "
                             f"{int(np.sum(~np.isfinite(g)))} NaN or infinite entries")
    many = g.ndim == 3
    fdof = np.repeat(np.asarray(problem.free), 3)
    if isinstance(nbrs, BarrierPairs):
        K, solve = _barrier_lu(problem, params, x, nbrs, fdof, rtol)
    else:
        K, solve = _gmres_lu(problem, params, x, nbrs, fdof, rtol, maxiter)
    mus, reps = [], []
    for gi in (g if many else g[None]):
        b = gi.reshape(-1)[fdof]
        mu = np.zeros(3 * N)
        its, res = 0, 0.0
        if np.linalg.norm(b) > 0.0:
            mu[fdof], its, res = solve(b)
        mus.append(mu.reshape(N, 3))
        reps.append(AdjointReport(its, res, time.perf_counter() - t0, int(K.nnz)))
    return (np.stack(mus), tuple(reps)) if many else (mus[0], reps[0])
