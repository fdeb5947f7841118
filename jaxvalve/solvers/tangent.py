"""An assembled sparse approximation of the valve's stiffness K = -dR/dx (the
preconditioner of the LU adjoint, `jaxvalve.solvers.adjoint.solve_lu`).

`assemble(problem, params, x, nbrs)` sums, as a scipy CSC matrix over the free dofs:
* the 9x9 Hessians of each triangle's strain energy (`assembly._element_hessians`);
* the 12x12 Hessians of each bending hinge (`bending.bending_energy` on the hinge's 4 nodes);
* the 9x9 Jacobian of the follower pressure load of each triangle (with its sign: the
  pressure Jacobian is not symmetric);
* a Gauss-Newton term k * omega * A_i/2 * g g^T per pruned soft-min contact pair (node i to a
  triangle, g the gradient of the distance), leaving out the distance's curvature.
It is close to K, not equal: it serves as a preconditioner, and every solve here runs GMRES on
the exact operator (Jacobian-vector products of the residual by autodiff).
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
from ..contact.smooth import _columns
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

    def _entries(self, nodes):
        """Row and column free dof ids (B, 3n, 3n) of the blocks over ``nodes`` (B, n),
        and the mask of entries between free dofs."""
        nodes = np.asarray(nodes)
        dofs = self.red[(3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), -1)]
        rows = np.broadcast_to(dofs[:, :, None], dofs.shape + (dofs.shape[1],))
        cols = np.broadcast_to(dofs[:, None, :], rows.shape)
        return rows, cols, (rows >= 0) & (cols >= 0)

    def coo(self, blocks, nodes):
        """CSR (nf, nf) of the blocks (B, 3n, 3n) over the node tuples (B, n); repeated
        entries are summed."""
        blocks = np.asarray(blocks)
        rows, cols, keep = self._entries(nodes)
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


def _contact_blocks(x, problem, params, ref, pairs: SoftPairs):
    """(P, 12, 12) Gauss-Newton contact blocks and their node ids (P, 4)."""
    c, base, tri, N = params.contact, pairs.base, problem.triangles, problem.n_nodes
    ok = jnp.arange(pairs.soft_capacity) < pairs.n
    g = jnp.where(ok, pairs.group, 0)
    t = jnp.where(ok, pairs.tri, 0)
    node = jnp.clip(base.group_node, 0, N - 1)[g]
    v = tri[t]
    idx = jnp.stack([node, v[:, 0], v[:, 1], v[:, 2]])
    cols = [_columns(x, idx[k]) for k in range(4)]
    d, _, _, side_p = point_triangle_distance_soa(*cols, side=True)
    d = jnp.where(ok, d, jnp.inf)
    R = base.rows
    dmin = jax.ops.segment_min(d, g, num_segments=R)
    side = jax.ops.segment_max(jnp.where(ok & (d <= dmin[g]), side_p, -1.0), g,
                               num_segments=R)
    w = jnp.where(ok, jnp.exp(-(d - jnp.where(ok, dmin[g], 0.0)) / c.softness), 0.0)
    den = jax.ops.segment_sum(w, g, num_segments=R)
    num = jax.ops.segment_sum(jnp.where(ok, w * d, 0.0), g, num_segments=R)
    s = side * num / jnp.where(den > 0, den, 1.0)
    live = (side * dmin < c.gap) & (den > 0) & (s < c.gap)
    om = w / jnp.where(den[g] > 0, den[g], 1.0)
    u, vv, ww = closest_point_soa(*cols)
    p, a, b, cc = cols
    e = jnp.stack([p[k] - (u * a[k] + vv * b[k] + ww * cc[k]) for k in range(3)], -1)
    n = e / jnp.where(d > 0, d, 1.0)[:, None]
    coef = jnp.stack([jnp.ones_like(u), -u, -vv, -ww], -1)
    gv = (coef[:, :, None] * n[:, None, :]).reshape(-1, 12)
    wt = jnp.where(ok & live[g], 0.5 * ref.node_area[node] * c.stiffness * om, 0.0)
    return wt[:, None, None] * gv[:, :, None] * gv[:, None, :], idx.T


@quick_jit
def _blocks(x, problem, params, nbrs, hinge_nodes, hinge_tris):
    ref = assembly.prepare(problem, params)
    out = [(assembly._element_hessians(x, problem, params, ref)
            - pressure_blocks(x, problem, params), problem.triangles)]
    if ref.hinge_w is not None and params.bending is not None:
        out.append((hinge_hessians(x, params, ref, hinge_nodes, hinge_tris), hinge_nodes))
    if isinstance(nbrs, SoftPairs) and params.contact is not None:
        out.append(_contact_blocks(x, problem, params, ref, nbrs))
    return out


def _hinge_args(problem):
    hn, ht = local_hinges(problem) if problem.hinges is not None else (None, None)
    return (None if hn is None else jnp.asarray(hn)), (None if ht is None else jnp.asarray(ht))


def assemble(problem, params, x, nbrs=None):
    """The approximate stiffness K (3F x 3F scipy CSC, F free nodes, dofs node-major).

    Blocks that are zero (contact slots without a live pair) are dropped, and entries that
    touch a fixed node are dropped before the matrix is built (`BlockAssembler`)."""
    parts = jax.device_get(_blocks(jnp.asarray(x), problem, params, nbrs,
                                   *_hinge_args(problem)))
    asm = BlockAssembler(problem.free)
    K = sp.csr_matrix((asm.nf, asm.nf))
    for H, nodes in parts:
        H = np.asarray(H)
        keep = np.any(H.reshape(len(H), -1) != 0.0, axis=1)
        K = K + asm.coo(H[keep], np.asarray(nodes)[keep])
    return K.tocsc()
