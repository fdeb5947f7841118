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
  (`jaxvalve.tangent.assemble`).  Much faster on valves, where contact makes block-Jacobi
  weak (docs/gradients-and-optimisation.md, "Why not block-Jacobi"); the optimiser's
  default (``adjoint="lu"``).  It returns an `AdjointReport` and raises
  `ConvergenceError` when GMRES misses its tolerance.

`residual_vjp` is the one compiled program of the residual's VJP that the LU backend and
the optimiser's pullback to the design parameters share.
"""
from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as spla

from . import assembly
from .contact.neighbours import whole_lists
from .errors import ConvergenceError
from .quick_jit import quick_jit
from .solvers.newton import _apply_blocks, _precond
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
            f"(jaxvalve.adjoint.solve_lu, the optimiser's adjoint='lu') on valves")


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


@quick_jit
def residual_vjp(x, problem, params, nbrs, v):
    """(v . dR/dx (N, 3), v . dR/dparams (a `Params`)) for the residual R(x, params), v
    (N, 3).  One compiled program serves the adjoint's K^T products (`adjoint_solve`) and
    the pullback of an adjoint to the parameters (`optimize.Evaluator`)."""
    def R(z, p):
        return assembly.residual(z, problem, p, assembly.prepare(problem, p), nbrs)
    with whole_lists():
        return jax.vjp(R, x, params)[1](v)


def solve_lu(problem, params, x, nbrs, g, *, rtol=1e-10, maxiter=300):
    """mu (N, 3) with K^T mu = g on the free dofs (K = -dR/dx at the equilibrium x); mu is
    zero on fixed nodes.  GMRES (scipy) on exact VJPs, preconditioned by the sparse LU of
    the assembled approximation of K^T.  Returns (mu, `AdjointReport`)."""
    t0 = time.perf_counter()
    x = jnp.asarray(x)
    free = np.asarray(problem.free)
    fdof = np.repeat(free, 3)
    N = problem.n_nodes
    K = assemble(problem, params, x, nbrs)
    lu = spla.splu(K.T.tocsc(), permc_spec="MMD_AT_PLUS_A")
    b = np.asarray(g, float).reshape(-1)[fdof]
    nb = float(np.linalg.norm(b))
    if nb == 0.0:
        return np.zeros((N, 3)), AdjointReport(0, 0.0, time.perf_counter() - t0, K.nnz)

    def KT(vf):
        v = np.zeros(3 * N)
        v[fdof] = vf
        gx, _ = residual_vjp(x, problem, params, nbrs, jnp.asarray(v.reshape(N, 3)))
        return -np.asarray(gx).reshape(-1)[fdof]

    A = spla.LinearOperator((b.size, b.size), matvec=KT, dtype=float)
    M = spla.LinearOperator((b.size, b.size), matvec=lu.solve, dtype=float)
    count = [0]
    mu_f, _ = spla.gmres(A, b, M=M, rtol=rtol, atol=0.0, restart=60, maxiter=maxiter // 60 + 1,
                         callback=lambda r: count.__setitem__(0, count[0] + 1),
                         callback_type="pr_norm")
    res = float(np.linalg.norm(KT(mu_f) - b) / nb)
    rep = AdjointReport(count[0], res, time.perf_counter() - t0, int(K.nnz))
    if not np.isfinite(res) or res > 100 * rtol:
        raise ConvergenceError(f"adjoint solve did not converge: relative residual {res:.3e} "
                               f"after {count[0]} GMRES iterations (tolerance {rtol:g})")
    mu = np.zeros(3 * N)
    mu[fdof] = mu_f
    return mu.reshape(N, 3), rep
