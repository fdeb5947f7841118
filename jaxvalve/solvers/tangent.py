"""The assembled sparse stiffness K = -dR/dx of the valve (the preconditioner of the LU
adjoint, `jaxvalve.solvers.adjoint.solve_lu`).

`assemble(problem, params, x, nbrs)` sums, as a scipy CSC matrix over the free dofs:
* the 9x9 Hessians of each triangle's strain energy (`assembly._element_hessians`);
* the 12x12 Hessians of each bending hinge (`bending.bending_energy` on the hinge's 4 nodes);
* the 9x9 Jacobian of the follower pressure load of each triangle (with its sign: the
  pressure Jacobian is not symmetric);
* with a soft-min contact pair list (`SoftPairs`), the exact Hessian of the contact energy:
  12x12 blocks per pair (node to triangle) and the soft minimum's coupling of each node's
  listed triangles (`_contact_terms`, `_group_outer`).
With these it is the exact -dR/dx on the free dofs (tested against the residual's VJP), so
the adjoint's GMRES, which runs on the exact operator (products of the residual by
autodiff), stops after one iteration.  A hard-minimum contact list gets no contact term.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..mechanics import assembly
from ..mechanics.bending import bending_energy, plate_modulus
from ..contact.geometry import closest_point_soa, point_triangle_distance_soa
from ..contact.smooth import _columns, _distance_rows
from ..contact.soft_pairs import SoftPairs
from ..quick_jit import quick_jit

__all__ = ["assemble", "pressure_blocks", "hinge_hessians", "local_hinges", "BlockAssembler",
           "BlockPattern"]


class BlockAssembler:
    """Sums dense blocks over node tuples into a sparse matrix over the free dofs (3 per
    free node, node-major; entries that touch a fixed node are dropped, so the free dofs
    are numbered directly).  The one sparse assembly of the project: `assemble` (the
    adjoint's preconditioner) and the barrier Newton solver's projected tangent use it.

    free: (N,) bool.  ``nf``: the number of free dofs."""

    def __init__(self, free):
        dof_free = np.repeat(np.asarray(free, bool), 3)
        self.red = np.where(dof_free, np.cumsum(dof_free) - 1, -1)   # free dof id or -1
        self.nf = int(dof_free.sum())

    def _dofs(self, nodes):
        nodes = np.asarray(nodes)
        return self.red[(3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), -1)]

    def _entries(self, nodes, col_nodes=None):
        """Row and column free dof ids (B, 3n, 3m) of the blocks with rows over ``nodes``
        (B, n) and columns over ``col_nodes`` (B, m; default ``nodes``), and the mask of
        entries between free dofs."""
        r = self._dofs(nodes)
        c = r if col_nodes is None else self._dofs(col_nodes)
        rows = np.broadcast_to(r[:, :, None], r.shape + (c.shape[1],))
        cols = np.broadcast_to(c[:, None, :], rows.shape)
        return rows, cols, (rows >= 0) & (cols >= 0)

    def coo(self, blocks, nodes, col_nodes=None):
        """CSR (nf, nf) of the blocks (B, 3n, 3n) over the node tuples (B, n), or, with
        ``col_nodes`` (B, m), of the blocks (B, 3n, 3m) coupling the rows of ``nodes`` to
        the columns of ``col_nodes`` (e.g. the soft minimum's group terms); repeated
        entries are summed."""
        blocks = np.asarray(blocks)
        rows, cols, keep = self._entries(nodes, col_nodes)
        return sp.csr_matrix((blocks[keep], (rows[keep], cols[keep])),
                             shape=(self.nf, self.nf))

    def pattern(self, node_sets):
        """The fixed sparsity pattern (`BlockPattern`) of blocks over the node tuples of
        ``node_sets`` (a list of (B_i, n_i) arrays), sorted once: the barrier solver's
        membrane and hinge blocks, assembled at every Newton step."""
        rows, cols, keeps = zip(*(self._entries(n) for n in node_sets))
        rows, cols, keep = (np.concatenate([a.reshape(-1) for a in arrs])
                            for arrs in (rows, cols, keeps))
        key = rows[keep].astype(np.int64) * self.nf + cols[keep]
        uniq, slot = np.unique(key, return_inverse=True)
        return BlockPattern(self.nf, keep, slot,
                            np.searchsorted(uniq // self.nf, np.arange(self.nf + 1)),
                            (uniq % self.nf).astype(np.int32), int(uniq.size))


@dataclasses.dataclass(frozen=True)
class BlockPattern:
    """The CSR pattern of `BlockAssembler.pattern`; ``matrix(blocks)`` sums blocks given
    in the pattern's order (a list of (B_i, k_i, k_i) arrays) into it."""

    nf: int
    keep: np.ndarray
    slot: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    nnz: int

    def matrix(self, blocks):
        data = np.concatenate([np.asarray(b).reshape(-1) for b in blocks])
        vals = np.bincount(self.slot, weights=data[self.keep], minlength=self.nnz)
        return sp.csr_matrix((vals, self.indices, self.indptr), shape=(self.nf, self.nf))


def local_hinges(problem):
    """Per hinge: its 4 nodes (K, 4) and its two triangles in local (0..3) indices
    (K, 2, 3), on the host."""
    hin = np.asarray(problem.hinges)
    tri = np.asarray(problem.triangles)
    nodes = hin[:, :4]
    loc = np.empty((hin.shape[0], 2, 3), np.int32)
    for s, col in enumerate((4, 5)):
        t = tri[hin[:, col]]                                     # (K, 3) global ids
        loc[:, s] = np.argmax(t[:, :, None] == nodes[:, None, :], axis=2)
    return nodes, loc


def pressure_blocks(x, problem, params):
    """(M, 9, 9) Jacobian d(F_pressure)/dx of each triangle, F = P A n / 3 at each node."""
    def f(xe):
        xe = xe.reshape(3, 3)
        an = 0.5 * jnp.cross(xe[1] - xe[0], xe[2] - xe[0])
        return jnp.tile(params.pressure / 3.0 * an, 3)
    return jax.vmap(jax.jacfwd(f))(x[problem.triangles].reshape(-1, 9))


def hinge_hessians(x, params, ref, hinge_nodes, hinge_tris):
    """(K, 12, 12) Hessians of the bending energy of each hinge (N mm / mm^2), from
    `local_hinges` (hinge_nodes (K, 4), hinge_tris (K, 2, 3))."""
    D = params.bending.scale * plate_modulus(params.material, params.thickness)
    one = lambda xh, tl, w: bending_energy(xh, jnp.array([[0, 1, 2, 3, 0, 1]]), w[None], D,
                                           tl)
    return (jax.vmap(jax.hessian(one))(x[hinge_nodes], hinge_tris, ref.hinge_w)
            .reshape(-1, 12, 12))


def _distance_hessians(x, idx):
    """(P, 12, 12) Hessians of the node-triangle distances of the rows idx (4, P) (node,
    then the triangle's vertices), by forward-over-forward autodiff of the function the
    energy uses (`contact.smooth._distance_rows`); it compiled in 1.1 s against 1.7 s for
    `jax.hessian`, and ran in half the time."""
    one = lambda y: _distance_rows(y, jnp.arange(4)[:, None])[0]
    hess = jax.vmap(jax.jacfwd(jax.jacfwd(one)))
    return hess(jnp.moveaxis(x[idx], 0, 1)).reshape(-1, 12, 12)


def _contact_terms(x, problem, params, ref, pairs: SoftPairs):
    """The Hessian of the soft-min contact energy (`SmoothContact._energy_pairs`) on the
    pair list, in two parts.  Per live group (a node against the other sheet) the energy is
    E = (a k / 4) (g0 - sigma S)^2, S = sum_j om_j d_j the soft minimum of the pair
    distances d_j (om_j = w_j / sum w, w_j = exp(-d_j / c)), sigma the side; with
    u_j = dS/dd_j = om_j (1 - (d_j - S) / c), A = sum_j u_j grad d_j, B = sum_j om_j grad d_j,
    psi1 = dE/dS and psi2 = d2E/dS2:

        d2E/dx2 = sum_j psi1 (u_j H_j - (u_j + om_j) / c  grad d_j grad d_j^T)
                  + psi2 A A^T + psi1 / c (A B^T + B A^T),

    H_j the Hessian of d_j.  Returns the per-pair blocks ((P, 12, 12), nodes (P, 4)) and
    the group terms (group (P,), nodes (P, 4), u_j grad d_j (P, 12), om_j grad d_j (P, 12),
    psi2 (R,), psi1 / c (R,)) that `_group_outer` sums over each group's nodes."""
    c, base, tri, N = params.contact, pairs.base, problem.triangles, problem.n_nodes
    ok = jnp.arange(pairs.soft_capacity) < pairs.n
    g = jnp.where(ok, pairs.group, 0)
    t = jnp.where(ok, pairs.tri, 0)
    node_of = jnp.clip(base.group_node, 0, N - 1)
    node = node_of[g]
    v = tri[t]
    idx = jnp.stack([node, v[:, 0], v[:, 1], v[:, 2]])
    cols = [_columns(x, idx[k]) for k in range(4)]
    d, _, _, side_p = point_triangle_distance_soa(*cols, side=True)
    d = jnp.where(ok, d, jnp.inf)
    R = base.rows
    dmin = jax.ops.segment_min(d, g, num_segments=R)
    found = jnp.isfinite(dmin)
    if c.one_sided:
        side = jax.ops.segment_max(jnp.where(ok & (d <= dmin[g]), side_p, -1.0), g,
                                   num_segments=R)
        side = jnp.where(found, side, 1.0)
    else:
        side = jnp.ones((R,), x.dtype)
    w = jnp.where(ok, jnp.exp(-(d - jnp.where(ok, dmin[g], 0.0)) / c.softness), 0.0)
    den = jax.ops.segment_sum(w, g, num_segments=R)
    num = jax.ops.segment_sum(jnp.where(ok, w * d, 0.0), g, num_segments=R)
    good = found & (side * dmin < c.gap) & (den > 0)
    S = jnp.where(good, num / jnp.where(good, den, 1.0), 0.0)
    act = good & (side * S < c.gap)           # the groups with energy
    a = ref.node_area[node_of]
    psi2 = jnp.where(act, 0.5 * a * c.stiffness, 0.0)
    psi1 = jnp.where(act, -0.5 * a * c.stiffness * (c.gap - side * S) * side, 0.0)
    on = ok & act[g]
    dj = jnp.where(on, d, 0.0)
    om = jnp.where(on, w / jnp.where(den[g] > 0, den[g], 1.0), 0.0)
    u = om * (1.0 - (dj - S[g]) / c.softness)
    bu, bv, bw = closest_point_soa(*cols)
    p, pa, pb, pc = cols
    e = jnp.stack([p[k] - (bu * pa[k] + bv * pb[k] + bw * pc[k]) for k in range(3)], -1)
    n = e / jnp.where(dj > 0, dj, 1.0)[:, None]
    coef = jnp.stack([jnp.ones_like(bu), -bu, -bv, -bw], -1)
    gd = jnp.where(on[:, None], (coef[:, :, None] * n[:, None, :]).reshape(-1, 12), 0.0)
    H = jnp.where(on[:, None, None], _distance_hessians(x, idx), 0.0)
    s1 = psi1[g]
    blocks = s1[:, None, None] * (u[:, None, None] * H - ((u + om) / c.softness)[:, None, None]
                                  * gd[:, :, None] * gd[:, None, :])
    return (blocks, idx.T), (g, idx.T, u[:, None] * gd, om[:, None] * gd, psi2,
                             psi1 / c.softness)


def _group_outer(asm: "BlockAssembler", n_nodes: int, g, nodes, A, B, alpha, beta):
    """Sum over groups of alpha A A^T + beta (A B^T + B A^T) (scipy CSR over the free dofs),
    A and B the sums over each group's pairs of the 12-vectors A (P, 12), B (P, 12) on the
    pairs' nodes (P, 4), g (P,) the group of each pair (`_contact_terms`)."""
    g, nodes, A, B, alpha, beta = (np.asarray(v) for v in (g, nodes, A, B, alpha, beta))
    keep = alpha[g] > 0
    if not keep.any():
        return sp.csr_matrix((asm.nf, asm.nf))
    key = (g[keep, None].astype(np.int64) * n_nodes + nodes[keep]).reshape(-1)
    uk, inv = np.unique(key, return_inverse=True)          # sorted: by group, then node
    Av, Bv = np.zeros((len(uk), 3)), np.zeros((len(uk), 3))
    np.add.at(Av, inv, A[keep].reshape(-1, 3))
    np.add.at(Bv, inv, B[keep].reshape(-1, 3))
    grp, nd = uk // n_nodes, uk % n_nodes
    starts = np.flatnonzero(np.r_[True, grp[1:] != grp[:-1]])
    counts = np.diff(np.r_[starts, len(uk)])
    sq = counts * counts
    which = np.repeat(np.arange(len(starts)), sq)
    loc = np.arange(int(sq.sum())) - np.repeat(np.cumsum(sq) - sq, sq)
    i = starts[which] + loc // counts[which]
    j = starts[which] + loc % counts[which]
    ga, gb = alpha[grp[i]][:, None, None], beta[grp[i]][:, None, None]
    outer = lambda P, Q: P[i][:, :, None] * Q[j][:, None, :]
    blocks = ga * outer(Av, Av) + gb * (outer(Av, Bv) + outer(Bv, Av))
    return asm.coo(blocks, nd[i][:, None], nd[j][:, None])


@quick_jit
def _blocks(x, problem, params, nbrs, hinge_nodes, hinge_tris):
    ref = assembly.prepare(problem, params)
    out = [(assembly._element_hessians(x, problem, params, ref)
            - pressure_blocks(x, problem, params), problem.triangles)]
    if ref.hinge_w is not None and params.bending is not None:
        out.append((hinge_hessians(x, params, ref, hinge_nodes, hinge_tris), hinge_nodes))
    groups = None
    if isinstance(nbrs, SoftPairs) and params.contact is not None:
        pair, groups = _contact_terms(x, problem, params, ref, nbrs)
        out.append(pair)
    return out, groups


def _hinge_args(problem):
    hn, ht = local_hinges(problem) if problem.hinges is not None else (None, None)
    return (None if hn is None else jnp.asarray(hn)), (None if ht is None else jnp.asarray(ht))


def assemble(problem, params, x, nbrs=None):
    """The approximate stiffness K (3F x 3F scipy CSC, F free nodes, dofs node-major).

    Blocks that are zero (contact slots without a live pair) are dropped, and entries that
    touch a fixed node are dropped before the matrix is built (`BlockAssembler`)."""
    parts, groups = jax.device_get(_blocks(jnp.asarray(x), problem, params, nbrs,
                                           *_hinge_args(problem)))
    asm = BlockAssembler(problem.free)
    K = (sp.csr_matrix((asm.nf, asm.nf)) if groups is None
         else _group_outer(asm, problem.n_nodes, *groups))
    for H, nodes in parts:
        H = np.asarray(H)
        keep = np.any(H.reshape(len(H), -1) != 0.0, axis=1)
        K = K + asm.coo(H[keep], np.asarray(nodes)[keep])
    return K.tocsc()
