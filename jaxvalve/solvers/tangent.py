"""The exact tangent K = -dF/dx of a membrane with barrier contact, as a sparse matrix:
the one assembly of the engine's Newton finish (`jaxvalve.solvers.finish`) and of the
adjoint (`jaxvalve.solvers.adjoint`).

`Tangent(problem, params)` sums, as a scipy CSC matrix over the free dofs:
* the 9x9 Hessians of each triangle's strain energy (`assembly._element_hessians`);
* the 9x9 Jacobian of the follower pressure load of each triangle (with its sign: the
  pressure Jacobian is not symmetric);
* the 12x12 Hessians of each bending hinge (`bending.bending_energy` on its 4 nodes);
* the 12x12 Hessians of each active barrier pair (`jaxvalve.contact.barrier`'s typed
  closed forms, whose second derivatives are exact within each distance type).
It equals -dF/dx on the free dofs (tested against the force's JVP).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..mechanics import assembly
from ..mechanics.bending import bending_energy, plate_modulus
from ..contact.barrier import ee_energies, pt_energies
from ..contact.ipc_distance import mollifier_threshold

__all__ = ["Tangent", "pressure_blocks", "hinge_hessians", "local_hinges", "BlockAssembler",
           "BlockPattern", "pair_hessians"]


class BlockAssembler:
    """Sums dense blocks over node tuples into a sparse matrix over the free dofs (3 per
    free node, node-major; entries that touch a fixed node are dropped, so the free dofs
    are numbered directly): the one sparse assembly of the project (`Tangent`).

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
        ``node_sets`` (a list of (B_i, n_i) arrays), sorted once: the membrane and hinge
        blocks, assembled at every Newton step."""
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
    D0 = plate_modulus(params.material, params.thickness)
    one = lambda xh, tl, w: bending_energy(xh, jnp.array([[0, 1, 2, 3, 0, 1]]), w[None],
                                           params.bending.scale * D0, tl, D0)
    return (jax.vmap(jax.hessian(one))(x[hinge_nodes], hinge_tris, ref.hinge_w)
            .reshape(-1, 12, 12))


def pair_hessians(law, x, pairs, weights, chunk: int = 256):
    """(pt blocks (P, 12, 12), ee blocks (Q, 12, 12)): the exact Hessians of the barrier
    energy of each row of the pair list ``pairs`` at x, computed for the rows in use
    only, a chunk at a time (the rows past them are zero)."""
    node_w, edge_w, len2 = weights
    loc = jnp.arange(4)[None]
    pt_h = jax.vmap(jax.hessian(lambda y, w: pt_energies(law, y.reshape(4, 3), loc,
                                                          w[None])[0]))
    ee_h = jax.vmap(jax.hessian(lambda y, w, e: ee_energies(law, y.reshape(4, 3), loc,
                                                             w[None], e[None])[0]))

    def run(rows, count, hess, extra):
        C = rows.shape[0]
        pad = -C % chunk
        rows = jnp.concatenate([rows, jnp.zeros((pad, rows.shape[1]), rows.dtype)]) if pad else rows

        def trip(i, out):
            k0 = (i * chunk).astype(jnp.int32)
            r = jax.lax.dynamic_slice(rows, (k0, jnp.int32(0)), (chunk, rows.shape[1]))
            valid = (k0 + jnp.arange(chunk)) < count
            H = hess(x[r[:, :4]].reshape(-1, 12), *extra(r, valid))
            return jax.lax.dynamic_update_slice(out, H, (k0, jnp.int32(0), jnp.int32(0)))

        trips = ((jnp.minimum(count, C) + chunk - 1) // chunk).astype(jnp.int32)
        out = jax.lax.fori_loop(jnp.int32(0), trips, trip,
                                jnp.zeros((C + pad, 12, 12), x.dtype))
        return out[:C]

    pt = run(pairs.pt, pairs.n_pt, pt_h,
             lambda r, ok: (jnp.where(ok, node_w[r[:, 0]], 0.0),))

    def ee_extra(r, ok):
        ea, eb = r[:, 4], r[:, 5]
        return (jnp.where(ok, edge_w[ea] + edge_w[eb], 0.0),
                mollifier_threshold(jnp.sqrt(len2[ea]), jnp.sqrt(len2[eb])))

    ee = run(jnp.concatenate([pairs.ee, pairs.ee_id], 1), pairs.n_ee, ee_h, ee_extra)
    return pt, ee


@jax.jit
def _membrane_blocks(x, problem, params, hinge_nodes, hinge_tris):
    ref = assembly.prepare(problem, params)
    tri = (assembly._element_hessians(x, problem, params, ref)
           - pressure_blocks(x, problem, params))
    if hinge_nodes is None:
        return tri, None
    return tri, hinge_hessians(x, params, ref, hinge_nodes, hinge_tris)


_pair_hessians = jax.jit(pair_hessians)


class Tangent:
    """The exact tangent of one problem, assembled at any state: ``matrix(x, params,
    pairs, weights)`` -> scipy CSC (3F x 3F, F free nodes, dofs node-major).  The
    membrane's sparsity pattern is sorted once; pair blocks that are zero (padding, pairs
    beyond d_hat) are dropped before they are summed."""

    def __init__(self, problem):
        self.problem = problem
        self.asm = BlockAssembler(~np.asarray(problem.fixed))
        if problem.hinges is not None:
            hn, ht = local_hinges(problem)
            self.hinges = (jnp.asarray(hn), jnp.asarray(ht))
            sets = [np.asarray(problem.triangles), hn]
        else:
            self.hinges = (None, None)
            sets = [np.asarray(problem.triangles)]
        self.pattern = self.asm.pattern(sets)

    @property
    def nf(self) -> int:
        return self.asm.nf

    def blocks(self, x, params, pairs=None, weights=None):
        """The dense blocks of the tangent at x (traceable): (triangle blocks (M, 9, 9),
        hinge blocks (K, 12, 12) or None, pair blocks (P, 12, 12) and (Q, 12, 12) or
        None); ``weights`` the collision weights of the barrier ``pairs``."""
        bending = params.bending is not None and self.hinges[0] is not None
        hn, ht = self.hinges if bending else (None, None)
        tri, hin = _membrane_blocks(x, self.problem, params, hn, ht)
        if pairs is None:
            return tri, hin, None, None
        pt, ee = _pair_hessians(params.contact, x, pairs, weights)
        return tri, hin, pt, ee

    def assemble(self, tri, hin, pt=None, ee=None, pt_rows=None, ee_rows=None,
                 counts=(0, 0)):
        """scipy CSC of the blocks (NumPy only, on the host): the pair blocks over their
        rows (P, 4), (Q, 4), the first ``counts`` of each in use."""
        if hin is not None:
            K = self.pattern.matrix([tri, hin])
        else:
            K = self.asm.coo(tri, np.asarray(self.problem.triangles))
        if pt is not None:
            for H, rows, n in zip((pt, ee), (pt_rows, ee_rows), counts):
                H, rows = np.asarray(H)[:int(n)], np.asarray(rows)[:int(n)]
                keep = np.any(H.reshape(len(H), -1) != 0.0, axis=1)
                if keep.any():
                    K = K + self.asm.coo(H[keep], rows[keep])
        return K.tocsc()

    def matrix(self, x, params, pairs=None, weights=None):
        """The tangent at x as scipy CSC (3F x 3F)."""
        b = jax.device_get(self.blocks(jnp.asarray(x), params, pairs, weights))
        if pairs is None:
            return self.assemble(*b)
        return self.assemble(*b, pairs.pt, pairs.ee, (int(pairs.n_pt), int(pairs.n_ee)))
