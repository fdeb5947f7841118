"""Projected Newton on the barrier contact: the intersection-free closure solver.

The state moves only along steps that continuous collision detection proves free of
contact (`jaxvalve.contact.ccd`), so the leaflets can never cross.  Each step:

1. Tangent.  The Hessian of the strain energy plus the symmetric part of the pressure
   load's stiffness, per triangle (9 x 9), of the bending energy per hinge (12 x 12) and
   of the barrier per pair (12 x 12), each projected to positive semi-definite (its
   negative eigenvalues set to zero), assembled into a sparse matrix over the free dofs.
2. Direction.  (K + diag(K) / tau) d = F, with a sparse LU factorisation (scipy's SuperLU,
   in its symmetric mode: `_SYMMETRIC`);
   tau is the pseudo-time step of pseudo-transient continuation (switched evolution
   relaxation: tau grows as the residual falls, and is cut where a step had to be
   shortened), which keeps the first steps short while the leaflets swing shut.  Below a
   relative residual of ``exact_below`` the first direction tried is Newton's on the exact
   Jacobian -dF/dx (unsymmetric: the follower pressure), assembled from the same element,
   hinge and pair Hessians before projection, solved inexactly by GMRES preconditioned by
   the projected factor (`_krylov`): fast convergence at the end, where the projected
   model alone converges linearly.
3. Step length.  At most ``dx_max`` mm for any node; then the largest fraction that
   additive CCD allows on a pair list that holds every pair able to meet on the move; then
   backtracking on the merit  Phi(alpha) = E(x + alpha d) - E(x) - W(alpha),  E the
   conservative energy (strain, bending, barrier) and W the work of the follower pressure
   along the step, exact by Simpson's rule (the load is quadratic in the positions).  A
   trial state must also be admissible: finite and inside the material's stretch limit;
   without self-contact (`BarrierTopology.self_contact` False) also without an edge
   folded past 150 degrees (the bound of `jaxvalve.valve.checks`), since nothing else
   would then keep a leaflet from folding through itself.  With self-contact (the
   default) a crease is held open by the barrier between the leaflet's own elements,
   and its fold angle is free.
4. Stop when ||F_free|| / ||F_pressure|| < rtol (with ``max_pushes`` > 0, at a stable
   state: `lowest_modes`; an unstable equilibrium is pushed off along its mode, at most
   ``max_pushes`` times, then `RESULTS.unstable`), with `RESULTS.escaped` once a node has
   moved farther than the start state's diameter (past a limit point the merit has no
   minimum and each step moves ``dx_max``; `jaxvalve.solvers.continuation` takes it from
   there), or with `RESULTS.stagnation` once the best residual, in the Newton-Krylov
   regime, has not halved for ``patience`` steps while no node moved farther than
   `DRIFT` of that diameter (a cycle, not a runaway; the continuation then cuts the load
   step).

The solve runs on the host: a Python loop around jitted kernels (energies, forces, element
and pair Hessians), each compiled once per mesh: pair lists are evaluated in chunks of
`CHUNK` rows, so their changing length recompiles nothing, and every physical parameter
is traced.
"""
from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..mechanics import assembly
from . import tangent
from .. import progress as _progress
from ..contact import ccd
from ..contact.barrier import ee_energies, pt_energies
from ..contact.ipc_pairs import BarrierTopology, build_pairs, pair_distances2
from ..valve.checks import FOLD_DEG
from ..errors import ParameterError
from .base import RESULTS, Solution, Stats, check_settings, escape_distance

__all__ = ["BarrierNewton", "solve_barrier", "CHUNK", "DRIFT"]

CHUNK = 512

#: Patience's drift guard, as a fraction of the start state's diameter (the escape
#: distance): a solve whose best residual has not halved within its patience is stopped
#: as cycling only if no node moved farther than this since the last halving; one that
#: did is running away (past a limit point) and goes on until it escapes, for the
#: continuation to bracket the limit.  Measured at h = 0.88 mm: the failing solves of
#: Table 4's cells E1 = 0.05 MPa (E2 = 0.3, 0.569) moved 0.001-7.3 mm in their windows
#: of 40 steps (diameters 30.7-33.1 mm: at most 0.24 of it); a runaway past the limit
#: point of Table 5's 0.1 MPa springs moved 25.0 mm in its window (0.69 of 36.0 mm).
DRIFT = 0.25

_log = logging.getLogger("jaxvalve")


@dataclasses.dataclass(frozen=True)
class BarrierNewton:
    """Settings of the projected Newton solve (see the module docstring).

    rtol: relative residual to reach.  max_steps: Newton iterations.  dx_max (mm): the
    largest move of any node in one step.  ccd_s: the fraction of each pair's gap that one
    step may close at most is 1 - ccd_s.  tau0: first pseudo-time step (dimensionless,
    relative to diag(K)).  armijo: sufficient-decrease constant of the line search.
    max_pushes: a converged state is checked for stability (`lowest_modes`); an unstable
    one is pushed along its unstable mode and the solve goes on, at most max_pushes
    times (0, the default: no check).  Where ARPACK finds no eigenvalues the state is
    returned as converged, with a `jaxvalve` log warning that its stability is unknown.
    exact_below: below this relative residual the first direction tried is Newton's on
    the exact Jacobian (undamped), solved by GMRES (relative tolerance krylov_rtol,
    at most krylov_iters products) preconditioned by the projected factor, tried at
    exact_halvings step lengths (halved in between; 1: only the longest that the node
    move cap and CCD allow) before the projected direction is tried.
    patience: the solve stops as `RESULTS.stagnation` once its best relative residual,
    below exact_below, has not halved for this many steps (0: never) and no node has
    moved more than `DRIFT` of the start's diameter since it last did, as FIRE's does;
    continuation in pressure then cuts the load step (`cut_on`)."""

    rtol: float = 1e-6
    max_steps: int = 300
    dx_max: float = 1.0
    ccd_s: float = 0.1
    tau0: float = 1.0
    armijo: float = 1e-4
    max_halvings: int = 30
    #: trial lengths of a Newton-Krylov step (1: no halving).  With 4, the stress suite's
    #: template (c) neo-Hookean valves at 1 and 10 MPa stopped short of 200 mmHg (stalls at
    #: 180 and 101 mmHg); logged step by step, the 10 MPa one accepted steps cut to 1/8
    #: for small gains, each halving the pseudo-time step, and cycled at relative
    #: residuals of 7e-3 to 4e-2 (docs/barrier-contact.md)
    exact_halvings: int = 1
    exact_below: float = 0.05
    krylov_rtol: float = 1e-2
    krylov_iters: int = 20
    #: pushes off an unstable equilibrium before the solve ends as `RESULTS.unstable`
    #: (0, the default: no stability check).  Opt-in: with 10, the benchmark valve's
    #: mass-spring closure at 80 mmHg ended `unstable` after 548 steps, its states
    #: keeping a negative eigenvalue after every push (compressed membrane regions, whose
    #: wrinkling modes the model resolves only at the mesh scale, are the suspect)
    max_pushes: int = 0
    #: soft valves' solves that fail end in a cycle of the line search at relative
    #: residuals of 3e-4 to 5e-3 for the rest of their step cap (800 steps measured on
    #: Table 4's cell E1 = 0.05, E2 = 0.569 MPa, h = 1.5 mm, 3 -> 22.25 mmHg), while
    #: the ones that converge halve their best residual at least every 28 steps (7
    #: solves of its continuation); stopped at 40 steps without a halving (with the
    #: `DRIFT` guard), that cell at h = 0.88 mm closes in 1346 steps where without the
    #: patience it stopped at the continuation's step budget (docs/barrier-contact.md)
    patience: int = 40
    #: failures after which continuation in pressure cuts the load step
    #: (`jaxvalve.solvers.continuation.cut_on`): Newton converges in tens of iterations from a
    #: near enough start, so a solve still short of rtol at its cap had too long a step.
    #: A state the valve's check rejects for a collapsed triangle (`inverted_triangles`:
    #: the barrier keeps leaflets apart, but a spring triangle has no area stiffness) is
    #: an equilibrium off the branch the load step should have followed: Table 4's cell
    #: E1 = 0.05, E2 = 0.7 MPa (h = 1.5 mm) reached one straight from 3 to 80 mmHg
    #: (171 steps), and through 41.5 mmHg a valid one
    cut_on = ("stagnation", "max_steps_reached", "inverted_triangles")

    def without_patience(self):
        """This solver without its early stop (patience 0), or None where it has none:
        the solver of `continuation.ramp`'s confirm solves (`continuation.full_solver`)."""
        return dataclasses.replace(self, patience=0) if self.patience else None

    def __post_init__(self):
        check_settings(self, dict(rtol="positive", max_steps="positive_count",
                                  dx_max="positive", ccd_s="unit", tau0="positive",
                                  armijo="unit", max_halvings="count", exact_halvings="count",
                                  exact_below="positive", krylov_rtol="unit",
                                  krylov_iters="positive_count", max_pushes="count",
                                  patience="count"))


# ------------------------------------------------------------------ jitted kernels
def _psd(H):
    """Project symmetric blocks (B, n, n) to positive semi-definite (clamp eigenvalues)."""
    H = 0.5 * (H + jnp.swapaxes(H, -1, -2))
    w, V = jnp.linalg.eigh(H)
    return (V * jnp.maximum(w, 0.0)[..., None, :]) @ jnp.swapaxes(V, -1, -2)


def _membrane_energy(x, problem, params, ref):
    """Strain plus bending energy (N mm), without contact."""
    return assembly.conservative_energy(x, problem, params.replace(contact=None), ref)


@jax.jit
def _membrane(x, problem, params, ref):
    """(energy N mm, its gradient (N, 3), pressure force (N, 3))."""
    e, g = jax.value_and_grad(_membrane_energy)(x, problem, params, ref)
    return e, g, assembly.pressure_force(x, problem.triangles, params.pressure)


@jax.jit
def _triangle_blocks(x, problem, params, ref):
    """Per triangle (M, 9, 9): (projected: the strain Hessian projected to PSD plus the
    symmetric part of the pressure stiffness, not projected (projecting the sum, or
    nothing, took more iterations on the benchmark valve); exact: -dF/dx, the strain
    Hessian minus the pressure load's unsymmetric Jacobian)."""
    H = assembly._element_hessians(x, problem, params, ref)
    J = tangent.pressure_blocks(x, problem, params)
    return _psd(H) - 0.5 * (J + jnp.swapaxes(J, 1, 2)), H - J


@jax.jit
def _hinge_blocks(x, params, ref, hinge_nodes, hinge_tris):
    """(projected, exact) bending Hessians per hinge (K, 12, 12), `tangent.hinge_hessians`."""
    H = tangent.hinge_hessians(x, params, ref, hinge_nodes, hinge_tris)
    return _psd(H), H


# The pair kernels take the pairs' own coordinates (C, 4, 3), gathered on the host, not
# the state (N, 3) with row indices: their shapes are then those of a chunk alone, so each
# compiles once per process instead of once per mesh size (the test suite's compile log:
# 8-9 compiles of each, 16-32 s per kernel, for the meshes of its files).

def _local_rows(n_rows):
    return jnp.arange(4 * n_rows).reshape(n_rows, 4)


@jax.jit
def _pt_rows_value_grad(law, xr, w):
    """(energy N mm, its gradient (C, 4, 3)) of point-triangle rows xr (C, 4, 3)."""
    loc = _local_rows(xr.shape[0])
    return jax.value_and_grad(
        lambda y: jnp.sum(pt_energies(law, y.reshape(-1, 3), loc, w)))(xr)


@jax.jit
def _ee_rows_value_grad(law, xr, w, eps):
    """(energy N mm, its gradient (C, 4, 3)) of edge-edge rows xr (C, 4, 3)."""
    loc = _local_rows(xr.shape[0])
    return jax.value_and_grad(
        lambda y: jnp.sum(ee_energies(law, y.reshape(-1, 3), loc, w, eps)))(xr)


@jax.jit
def _pt_rows_blocks(law, xr, w):
    loc = jnp.arange(4)[None]

    def e(x12, wi):
        return pt_energies(law, x12.reshape(4, 3), loc, wi[None])[0]

    H = jax.vmap(jax.hessian(e))(xr.reshape(-1, 12), w)
    return _psd(H), H


@jax.jit
def _ee_rows_blocks(law, xr, w, eps):
    loc = jnp.arange(4)[None]

    def e(x12, wi, ei):
        return ee_energies(law, x12.reshape(4, 3), loc, wi[None], ei[None])[0]

    H = jax.vmap(jax.hessian(e))(xr.reshape(-1, 12), w, eps)
    return _psd(H), H


def _gather(x, rows):
    """The coordinates (C, 4, 3) of pair rows (C, 4) of the state x (N, 3)."""
    return np.asarray(x)[np.asarray(rows)]


def _scatter(g, rows, n):
    """Per-row gradients g (C, 4, 3) summed onto the nodes: (n, 3)."""
    idx = np.asarray(rows).reshape(-1)
    g = np.asarray(g).reshape(-1, 3)
    return np.stack([np.bincount(idx, weights=g[:, k], minlength=n) for k in range(3)], 1)


def _pt_value_grad(law, x, rows, w):
    """(energy N mm, gradient (N, 3)) of point-triangle rows (C, 4) of the state x."""
    e, g = _pt_rows_value_grad(law, _gather(x, rows), w)
    return e, _scatter(g, rows, np.shape(x)[0])


def _ee_value_grad(law, x, rows, w, eps):
    """(energy N mm, gradient (N, 3)) of edge-edge rows (C, 4) of the state x."""
    e, g = _ee_rows_value_grad(law, _gather(x, rows), w, eps)
    return e, _scatter(g, rows, np.shape(x)[0])


def _pt_blocks(law, x, rows, w):
    """(projected, exact) Hessians (C, 12, 12) of point-triangle rows (C, 4) of x."""
    return _pt_rows_blocks(law, _gather(x, rows), w)


def _ee_blocks(law, x, rows, w, eps):
    """(projected, exact) Hessians (C, 12, 12) of edge-edge rows (C, 4) of x."""
    return _ee_rows_blocks(law, _gather(x, rows), w, eps)


def _chunks(*arrays):
    """Yield the arrays cut into CHUNK rows, the last chunk padded with zeros."""
    n = arrays[0].shape[0]
    for s in range(0, n, CHUNK):
        out = []
        for a in arrays:
            c = a[s:s + CHUNK]
            if c.shape[0] < CHUNK:
                pad = np.zeros((CHUNK - c.shape[0],) + a.shape[1:], a.dtype)
                c = np.concatenate([c, pad])
            out.append(c)
        yield s, min(CHUNK, n - s), out


# ------------------------------------------------------------------ host-side model
class _Model:
    """Energies, forces and the tangent of one membrane problem with barrier contact."""

    def __init__(self, problem, params, topo: BarrierTopology):
        self.problem, self.params, self.topo = problem, params, topo
        self.law = params.contact
        self.ref = jax.jit(assembly.prepare)(problem, params)
        self.free = np.asarray(problem.free)
        self.asm = tangent.BlockAssembler(self.free)
        self.nf = self.asm.nf
        self.bends = self.ref.hinge_w is not None and params.bending is not None
        if self.bends:
            self.hinge_nodes, self.hinge_tris = tangent.local_hinges(problem)
        hinges = self.hinge_nodes if self.bends else np.zeros((0, 4), np.int64)
        # a fixed pattern for the membrane and hinge blocks; the pairs' blocks go by COO
        self._static = self.asm.pattern([np.asarray(problem.triangles), hinges])
        self.n = self.free.shape[0]

    def tangent(self, x, pairs, exact=False):
        """Projected tangent (nf, nf) CSR over the free dofs at x, with the pair list:
        the element, hinge and pair Hessians each projected to positive semi-definite.

        The pairs' Hessians are projected in full.  A cheaper model, the barrier's Hessian
        along the contact normal only (rank one per pair, PSD without an
        eigendecomposition, a third of the tangent's cost), left soft valves short of
        equilibrium: the Table 4 cell E1 = 0.18, E2 = 0.3 MPa (h = 1.5 mm, 80 mmHg from
        the 3 mmHg state) ended its 200 steps in a two-state cycle at a residual of
        1.7e-3, where the full projection converges in 74 steps (`jaxvalve sweep
        --table 4 --h 1.5`; docs/barrier-contact.md, "Soft valves").
        With ``exact``: the pair (projected, exact), the exact one -dF/dx of the total
        force (unsymmetric: the follower pressure) from the same element Hessians.

        Each kernel holds one batched eigendecomposition and is waited for before the next
        starts: a program with two of them (LAPACK calls that XLA's CPU runtime may run
        at the same time) hung in a futex wait after 40-120 calls (jaxlib 0.10.1)."""
        xj = jnp.asarray(x)
        tp, te = map(np.asarray, _triangle_blocks(xj, self.problem, self.params, self.ref))
        if self.bends:
            hp, he = map(np.asarray, _hinge_blocks(xj, self.params, self.ref,
                                                   self.hinge_nodes, self.hinge_tris))
        else:
            hp = he = np.zeros((0, 12, 12))
        proj, full, nodes = [], [], []
        for s, k, (rows, w) in _chunks(pairs.pt, pairs.pt_w):
            bp, be = _pt_blocks(self.law, x, rows, w)
            proj.append(np.asarray(bp)[:k])
            if exact:
                full.append(np.asarray(be)[:k])
            nodes.append(pairs.pt[s:s + k])
        for s, k, (rows, w, eps) in _chunks(pairs.ee, pairs.ee_w, pairs.ee_eps):
            bp, be = _ee_blocks(self.law, x, rows, w, eps)
            proj.append(np.asarray(bp)[:k])
            if exact:
                full.append(np.asarray(be)[:k])
            nodes.append(pairs.ee[s:s + k])

        def assemble(tb, hb, pb):
            K = self._static.matrix([tb, hb])
            if pb:
                K = K + self.asm.coo(np.concatenate(pb), np.concatenate(nodes))
            return K
        K = assemble(tp, hp, proj)
        return (K, assemble(te, he, full)) if exact else K

    def evaluate(self, x, pairs):
        """(conservative energy N mm, total force (N, 3) on free nodes, pressure force
        (N, 3)) at x with the pair list."""
        xj = jnp.asarray(x)
        e, g, fp = _membrane(xj, self.problem, self.params, self.ref)
        e, g = float(e), np.asarray(g)
        for _, _, (rows, w) in _chunks(pairs.pt, pairs.pt_w):
            eb, gb = _pt_value_grad(self.law, x, rows, w)
            e, g = e + float(eb), g + np.asarray(gb)
        for _, _, (rows, w, eps) in _chunks(pairs.ee, pairs.ee_w, pairs.ee_eps):
            eb, gb = _ee_value_grad(self.law, x, rows, w, eps)
            e, g = e + float(eb), g + np.asarray(gb)
        fp = np.asarray(fp)
        F = (fp - g) * self.free[:, None]
        return e, F, fp

    def pressure(self, x):
        """Follower pressure force (N, 3) at x."""
        return np.asarray(_pressure(jnp.asarray(x), self.problem, self.params))

    def admissible(self, x):
        fold = -2.0 if self.topo.self_contact else _FOLD_COS     # -2: no fold bound
        return bool(_admissible(jnp.asarray(x), self.problem, self.params, self.ref,
                                fold))


#: SuperLU told that A = K + diag(K) / tau is symmetric (one ordering for rows and
#: columns, diagonal pivots preferred; pivoting stays on): 1.25-1.77x faster to factorise
#: and solve than the default mode on the benchmark closure's tangents, to the same
#: residual, where CHOLMOD (`cholespy`) was 1.02-1.71x and conjugate gradients
#: preconditioned by a factor kept from another state 0.09-1.35x
#: (`benchmarks/linear_solve.py`)
_SYMMETRIC = dict(SymmetricMode=True)

#: cosine of the fold limit without self-contact: a step may not turn two triangles that
#: share an edge more than `jaxvalve.valve.checks.FOLD_DEG` (150 degrees) apart
_FOLD_COS = float(np.cos(np.radians(FOLD_DEG)))


@jax.jit
def _pressure(x, problem, params):
    return assembly.pressure_force(x, problem.triangles, params.pressure)


@jax.jit
def _admissible(x, problem, params, ref, fold_cos):
    """Finite, inside the material's stretch limit, and no edge folded so far that the
    cosine between its triangles' normals is fold_cos or below."""
    ok = assembly.stretch_admissible(x, problem, params, ref) & jnp.all(jnp.isfinite(x))
    if problem.hinges is not None and problem.hinges.shape[0]:
        xt = x[problem.triangles]
        n = jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
        n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
        c = jnp.sum(n[problem.hinges[:, 4]] * n[problem.hinges[:, 5]], axis=-1)
        ok = ok & jnp.all(c > fold_cos)
    return ok


def _krylov(J, lu, rhs, guess, solver):
    """GMRES on the exact Jacobian J (assembled, `_Model.tangent`), preconditioned by the
    projected factor ``lu``, from ``guess``: the direction d (free dofs), or None where it
    is not finite.  GMRES's own convergence flag is not a test of d: along the coapted
    leaflets' sliding mode the projected factor is nearly singular, and GMRES reports
    failure (a preconditioned residual stuck at 0.25) for directions whose true residual
    ||J d - F|| / ||F|| is 4e-3 and whose step halves the force residual (the Table 4
    cell E1 = 0.05, E2 = 0.569 MPa at 40 mmHg).  Its line search is the test; the
    projected direction follows where it fails.  The inexact solve matters: Newton's
    direction on the exact Jacobian, solved exactly, needed backtracking to 0.01-0.3 from
    relative residuals of 4e-2 to 5e-3 on the benchmark valve and stalled at 4e-3, where
    this one converges in 19 steps."""
    M = spla.LinearOperator(J.shape, matvec=lu.solve, dtype=float)
    dk, _ = spla.gmres(J, rhs, x0=guess, M=M, rtol=solver.krylov_rtol,
                       restart=solver.krylov_iters, maxiter=1)
    return dk if np.all(np.isfinite(dk)) else None


def _line_search(model, topo, x, d, E, fp, res, scale, slope, exact, dhat, solver):
    """Step length along d (N, 3): at most ``dx_max`` for any node, the CCD bound, then
    halving until the merit falls enough (or, for a Newton-Krylov direction, the
    residual).  A Newton-Krylov direction gets at most ``exact_halvings`` trial lengths:
    one that must be cut further is a poor model of the force, and the projected
    direction takes over (accepted after 30 halvings, such steps of 1e-9 left soft
    closures crawling at relative residuals of 1.4e-4 to 5.6e-4 for 70-130 iterations;
    accepted after 3 halvings, steps of 1/8 with small gains kept a stiff closure cycling
    at relative residuals of 7e-3 to 4e-2, docs/barrier-contact.md).  Returns (accepted,
    alpha, a0, ccd fraction, (x, pairs, E, F, fp, res) at the accepted state, force
    evaluations)."""
    big = float(np.max(np.linalg.norm(d, axis=1)))
    a0 = min(1.0, solver.dx_max / big) if big > 0 else 1.0
    move = a0 * big
    near = build_pairs(topo, x, dhat + 2.0 * move * 1.001 + 1e-9, dx=a0 * d)
    t = ccd.max_step(x, a0 * d, near, solver.ccd_s)
    alpha = a0 * t
    # E at x: the pairs beyond d_hat that `near` adds carry no energy
    g0 = float(np.sum(fp * d))
    evals = 0
    for _ in range(solver.exact_halvings if exact else solver.max_halvings):
        xn = x + alpha * d
        if model.admissible(xn):
            d_pt, d_ee = pair_distances2(xn, near.pt, near.ee)
            trial = near.within(d_pt, d_ee, dhat)
            En, Fn, fpn = model.evaluate(xn, trial)
            evals += 1
            fph = model.pressure(x + 0.5 * alpha * d)
            W = alpha / 6.0 * (g0 + 4.0 * float(np.sum(fph * d)) + float(np.sum(fpn * d)))
            phi = En - E - W
            res_n = float(np.linalg.norm(Fn)) / scale
            if (phi <= -solver.armijo * alpha * slope
                    or (exact and res_n < (1.0 - solver.armijo * alpha) * res)):
                return True, alpha, a0, t, (xn, trial, En, Fn, fpn, res_n), evals
        alpha *= 0.5
    return False, alpha, a0, t, None, evals


def lowest_modes(model, x, pairs, k=12):
    """(lowest real part of an eigenvalue of the exact Jacobian -dF/dx at x (N/mm), its
    mode (N, 3) real, unit largest node move) or (None, None) where ARPACK fails.

    Shift-invert about sigma = -0.1 max diag(K), K the projected tangent: every
    eigenvalue in (2 sigma, 0) is nearer the shift than any positive one, so the k
    nearest hold the negative ones first (0.1 s on the benchmark valve).  The mode is
    that of the lowest; a complex pair gives its real part.  An equilibrium whose lowest
    eigenvalue is negative is not stable: a closing valve passes through it, it does not
    settle there (two closed states of the Table 4 cell E1 = 0.106, E2 = 0.7 MPa: the
    one a solver reached had an eigenvalue -0.024, the other none below +1.4e-4)."""
    K, Kx = model.tangent(x, pairs, exact=True)
    sigma = -0.1 * float(np.abs(K.diagonal()).max())
    try:
        n = Kx.shape[0]      # a fixed start vector: ARPACK's random one made pushes random
        w, V = spla.eigs(Kx.tocsc(), k=min(k, n - 2), sigma=sigma, which="LM",
                         v0=np.full(n, 1.0 / np.sqrt(n)))
    except (spla.ArpackNoConvergence, RuntimeError, ValueError):
        return None, None
    i = int(np.argmin(w.real))
    v = np.zeros_like(x)
    v[model.free] = np.real(V[:, i]).reshape(-1, 3)
    big = float(np.max(np.linalg.norm(v, axis=1)))
    j = np.unravel_index(np.argmax(np.abs(v)), v.shape)        # a sign of its own
    return float(w[i].real), (np.sign(v[j]) * v / big if big > 0 else v)


def _push(model, topo, x, v, E, fp, res, scale, dhat, solver):
    """The state pushed off an unstable equilibrium x along its mode v (N, 3) (unit
    largest node move) by at most ``dx_max``, with the same CCD bound and admissibility
    as every step: (x, pairs, E, F, fp, res), or None where neither side lowers the
    merit.  At an equilibrium the merit's slope is zero, so the line search accepts the
    first admissible state of lower merit; +v is tried first, then -v."""
    for sign in (1.0, -1.0):
        ok, _, _, _, out, _ = _line_search(model, topo, x, sign * v, E, fp, res, scale,
                                           0.0, False, dhat, solver)
        if ok:
            return out
    return None


def _start_failure(model, x):
    """Why no step can start from x, or None: not finite (`RESULTS.nonfinite`), a
    triangle past the material's stretch limit or collapsed (`RESULTS.stretch_limit`),
    or, without self-contact, an edge folded past `FOLD_DEG` (`RESULTS.stagnation`: the
    line search accepts only admissible states, and every short step from a folded state
    is folded too)."""
    if model.admissible(x):
        return None
    xj = jnp.asarray(x)
    if not bool(jnp.all(jnp.isfinite(xj))):
        return RESULTS.nonfinite
    if not bool(assembly.stretch_admissible(xj, model.problem, model.params, model.ref)):
        return RESULTS.stretch_limit
    return RESULTS.stagnation


# ------------------------------------------------------------------ the solve
@dataclasses.dataclass
class BarrierLog:
    """Per-iteration record: residual, step fraction alpha, CCD bound, pairs in use."""

    residual: list = dataclasses.field(default_factory=list)
    alpha: list = dataclasses.field(default_factory=list)
    ccd: list = dataclasses.field(default_factory=list)
    pairs: list = dataclasses.field(default_factory=list)
    min_gap: list = dataclasses.field(default_factory=list)
    tau: list = dataclasses.field(default_factory=list)
    #: (iteration, lowest real eigenvalue of the exact Jacobian) at each converged state
    stability: list = dataclasses.field(default_factory=list)


def solve_barrier(problem, params, x0, solver: BarrierNewton, topo: BarrierTopology,
                  progress=None):
    """Equilibrium of ``problem`` under ``params`` (contact: `BarrierContact`) from x0
    (N, 3) mm, which must be free of contact closer than 0 (every pair apart).  Returns a
    `Solution` (its ``nbrs`` is the final `BarrierPairs`) and a `BarrierLog`."""
    law = params.contact
    if law is None or not getattr(law, "barrier", False):
        raise ParameterError("solve_barrier needs params.contact = BarrierContact()")
    law.validate()
    dhat = float(law.dhat)
    if topo.self_contact and dhat > topo.self_gap:
        raise ParameterError(f"the barrier's dhat = {dhat:g} mm must not exceed the "
                             f"self-contact gap self_gap = {topo.self_gap:g} mm (pairs of "
                             "one leaflet closer than that in the template are not listed)")
    model = _Model(problem, params, topo)
    x = np.array(x0, dtype=np.float64)
    pairs = build_pairs(topo, x, dhat)
    if pairs.min_distance <= 0:
        raise ParameterError("the start state has leaflets touching or crossing (a pair "
                             "at distance 0); the barrier closure needs a separated start")
    E, F, fp = model.evaluate(x, pairs)
    evals = 1
    scale = float(np.linalg.norm(fp[model.free]))
    scale = scale if scale > 0 else 1.0
    res = float(np.linalg.norm(F)) / scale
    log = BarrierLog()
    start = _start_failure(model, x)
    if start is not None:     # every step must stay admissible: none can leave this start
        log.residual.append(res)
        stats = Stats(steps=jnp.asarray(0), force_evals=jnp.asarray(evals),
                      hvps=jnp.asarray(0), residual=jnp.asarray(res))
        return Solution(x=jnp.asarray(x), result=jnp.asarray(int(start)), stats=stats,
                        nbrs=pairs), log
    x_start, escape = x.copy(), float(escape_distance(x))
    tau = solver.tau0
    pushed = False        # since a push: every step must lower the merit (below)
    best, mark, x_mark = res, 0, x   # patience: the best residual, the step it last
    #                                  halved at, and the state then
    result = RESULTS.max_steps_reached
    n = 0
    free = model.free
    for n in range(solver.max_steps + 1):
        log.residual.append(res)
        log.pairs.append(len(pairs.pt) + len(pairs.ee))
        log.min_gap.append(pairs.min_distance)
        _progress.beacon(n, res, "BarrierNewton")
        if progress is not None:
            progress(n, res)
        if not np.isfinite(res):
            result = RESULTS.nonfinite
            break
        if res < solver.rtol:
            result = RESULTS.successful
            if solver.max_pushes == 0:
                break
            lam, vec = lowest_modes(model, x, pairs)
            log.stability.append((n, lam))
            if lam is None:      # the equilibrium stands; its stability is not known
                _log.warning("barrier Newton: ARPACK found no eigenvalues at the converged "
                             "state (step %d); its stability was not checked", n)
                break
            if lam >= 0.0:
                break
            if len(log.stability) > solver.max_pushes:
                result = RESULTS.unstable
                break
            off = _push(model, topo, x, vec, E, fp, res, scale, dhat, solver)
            if off is None:
                result = RESULTS.unstable
                break
            x, pairs, E, F, fp, res = off
            tau, result = solver.tau0, RESULTS.max_steps_reached    # not converged again yet
            pushed = True
            best, mark, x_mark = res, n, x
            continue
        if n == solver.max_steps:
            break
        # patience, once the solve has reached the Newton-Krylov regime (below
        # exact_below): above it the first steps swing the leaflets (from the open
        # placement at 3 mmHg: 41 steps at 0.19 without a halving, then converged).
        # A solve that has moved a node more than DRIFT of the escape distance since
        # then is running away (past a limit point, where the runaway test must see it
        # go), not cycling: its clock restarts.  (Table 5's mass-spring valve at E = 0.1
        # MPa, h = 0.88 mm: without this guard its solves at 80 and 41.5 mmHg, beyond the
        # limit, stopped at 74 and 62 steps and the ramp never saw a runaway.)
        if res < 0.5 * best or res < solver.exact_below <= best:
            best, mark, x_mark = res, n, x
        elif solver.patience and best < solver.exact_below and n - mark > solver.patience:
            if np.max(np.sum((x - x_mark) ** 2, axis=1)) > (DRIFT * escape) ** 2:
                mark, x_mark = n, x
            else:
                result = RESULTS.stagnation
                break
        near_eq = res < solver.exact_below
        tangents = model.tangent(x, pairs, exact=near_eq)
        K, Kx = tangents if near_eq else (tangents, None)
        diag = K.diagonal()
        damp = sp.diags(np.maximum(diag, 1e-12 * max(diag.max(), 1e-300)) / tau)
        rhs = F[free].reshape(-1)
        A = (K + damp).tocsc()
        try:
            lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", options=_SYMMETRIC)
        except RuntimeError:      # singular: shorten the pseudo-time step and retry
            tau *= 0.1
            continue
        dproj = lu.solve(rhs)
        # candidate directions, best first: near equilibrium, Newton-Krylov on the exact
        # Jacobian (wherever finite, `_krylov`); always the projected direction, whose
        # merit slope is positive (Phi is the merit of a symmetric positive semi-definite
        # model), and which takes over where the exact Jacobian's step fails its line
        # search (a nearly singular Jacobian: the coapted leaflets' sliding mode)
        directions = []
        if near_eq:
            dk = _krylov(Kx, lu, rhs, dproj, solver)
            if dk is not None:
                directions.append((dk, True))
        directions.append((dproj, False))
        accepted, alpha = False, 0.0
        for dfree, exact in directions:
            d = np.zeros_like(x)
            d[free] = dfree.reshape(-1, 3)
            slope = float(rhs @ dfree)            # -dPhi/dalpha at 0 (> 0: descent)
            # a Newton-Krylov step may also be accepted where it lowers the residual, but
            # not after a push off an unstable equilibrium: the exact Jacobian's step
            # heads for the nearest root, the saddle too, and only the merit falls away
            # from it (a compressed disk went from saddle to saddle six times otherwise)
            by_residual = exact and not pushed
            if not slope > 0 and not by_residual:   # indefinite: more pseudo-time damping
                continue
            accepted, alpha, a0, t, trial_out, n_ev = _line_search(
                model, topo, x, d, E, fp, res, scale, slope, by_residual, dhat, solver)
            evals += n_ev
            log.ccd.append(t)
            if accepted:
                xn, trial, En, Fn, fpn, res_n = trial_out
                break
        log.alpha.append(alpha if accepted else 0.0)
        log.tau.append(tau)
        if not accepted:
            if tau > 1e-8:
                tau *= 0.1
                continue
            result = RESULTS.stagnation
            break
        x, pairs, E, F, fp = xn, trial, En, Fn, fpn
        if np.max(np.sum((x - x_start) ** 2, axis=1)) > escape**2:
            res = res_n
            result = RESULTS.escaped
            break
        # pseudo-time: grown on every full step (at least 2x, faster where the residual
        # fell faster: switched evolution relaxation), cut where a step was shortened
        if alpha < a0 * t * 0.99 or t < 1.0:
            tau = max(tau * 0.5, 1e-8)
        else:
            tau = min(tau * max(2.0, min(res / res_n, 10.0)), 1e12)
        res = res_n
    stats = Stats(steps=jnp.asarray(n), force_evals=jnp.asarray(evals), hvps=jnp.asarray(0),
                  residual=jnp.asarray(res))
    return Solution(x=jnp.asarray(x), result=jnp.asarray(int(result)), stats=stats,
                    nbrs=pairs), log
