"""IPC log-barrier contact between leaflets (Li et al. 2020): smooth, and never crossed.

Energy (N mm) over the collisions of a pair list (`jaxvalve.contact.pairs.PairList`):

    E = kappa * d_hat * sum_k w_k m_k B(d_k^2 / d_hat^2),    B(z) = -(z - 1)^2 ln z  (z < 1)

with d_k the unsigned distance of collision k (`ipc_distance`), w_k its area weight (mm^2),
m_k the edge-edge mollifier (1 for point-triangle collisions) and B = 0 for d_k >= d_hat.
B, B' and B'' vanish at z = 1, so the energy is C2 in the positions where a
pair enters the range d_hat (within one distance type), and B grows to +inf as d -> 0: a
state of finite energy has no contact and no crossing.  This is the IPC toolkit's
"physical" barrier (``BarrierPotential(dhat, kappa, use_physical_barrier=True)``), so the
tests can compare with it term by term.

Collisions.  Every node against every triangle of another leaflet, and every edge against
every edge of another leaflet (and of one leaflet beyond its self-contact gap), within
d_hat (`jaxvalve.contact.pairs`), each with its own unsigned distance: IPC's constraint set
as the 2020 paper sums it.  A term's distance is the distance to a convex set, C1 in the
positions, so the energy is C1 everywhere and C2 within each distance type.  A node near
an edge of a sheet is counted once for each triangle at that edge: dropping the repeats
would switch terms on and off where the closest feature changes, and make the energy jump.
The edge-edge terms carry a mollifier (`ipc_distance.mollifier`: IPC's, made C2 and over a
wider angle), which removes them smoothly as the edges turn parallel (where the line-line
distance is undefined).  They stop two sheets from passing through each other edge first,
between nodes.

Weights.  A point-triangle collision of node p weighs a_p / 2 (a_p its lumped reference
area): both leaflets' nodes see the other's faces, so two parallel sheets at distance d
press each other with p(d) = -dE/dd per unit area = -2 kappa (d / d_hat) B'(z), plus the
edge-edge terms.  An edge-edge collision weighs (A_a + A_b) / 4 with A_e a third of the
reference area of the triangles at edge e.  With these weights kappa is a pressure (MPa)
and the law does not change with the mesh size.

Defaults.  d_hat = 0.2 mm, inside the coaptation distance g_c = 0.5 mm, so the zone is
measured on touching tissue; kappa = 1e-3 MPa, so that sheets pressed at 80 mmHg settle
well inside d_hat with a contact stiffness of the membrane's order
(docs/barrier-contact.md, "Defaults").
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from ..unvmap import unvmap_max
from .ipc_distance import (edge_edge_cross2, edge_edge_distance2, edge_edge_params, mollifier,
                           mollifier_d,
                           mollifier_threshold, point_triangle_distance2,
                           point_triangle_weights)

__all__ = ["BarrierContact", "barrier", "pt_energies", "ee_energies", "collision_weights",
           "pair_weights", "forces", "barrier_d", "CHUNK"]

DEFAULT_DHAT = 0.2        # mm
DEFAULT_KAPPA = 1e-3      # MPa


def barrier(z):
    """B(z) = -(z - 1)^2 ln z for 0 < z < 1, else 0 (z = d^2 / d_hat^2)."""
    return barrier_d(z)[0]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BarrierContact:
    """IPC barrier contact law (traced parameters).

    dhat: activation distance d_hat (mm, > 0).  stiffness: kappa (MPa, > 0), the pressure
    scale of the barrier (two sheets at distance d << d_hat press each other with about
    2 kappa d_hat / d)."""

    dhat: Any = DEFAULT_DHAT
    stiffness: Any = DEFAULT_KAPPA

    #: marks this law for the valve's closure driver and `equilibrium`: it needs the
    #: barrier pair lists (`jaxvalve.contact.pairs`) and filtered steps
    barrier = True

    @property
    def gap(self):
        """Interaction range (mm)."""
        return self.dhat

    def validate(self):
        for name in ("dhat", "stiffness"):
            v = getattr(self, name)
            if isinstance(v, jax.core.Tracer):
                continue
            a = np.asarray(v, float)
            if not (np.all(np.isfinite(a)) and np.all(a > 0)):
                unit = "mm" if name == "dhat" else "MPa"
                raise ParameterError(f"barrier contact: {name} must be finite and > 0 "
                                     f"({unit}); got {v}")
        return self

    def energy_pairs(self, x, pt, pt_w, ee, ee_w, ee_eps):
        """Total barrier energy (N mm) of the point-triangle rows ``pt`` (P, 4) [p, t0, t1,
        t2] and edge-edge rows ``ee`` (Q, 4) [a0, a1, b0, b1] at positions x (N, 3); rows of
        weight 0 are padding."""
        return (jnp.sum(pt_energies(self, x, pt, pt_w))
                + jnp.sum(ee_energies(self, x, ee, ee_w, ee_eps)))


def collision_weights(ref, triangles, tri_edge, n_edges, xp=jnp):
    """(node_w (N,) mm^2, edge_w (E,) mm^2, edge_len2 (E,) mm^2) of the reference
    coordinates ref (N, 2|3) mm: a node's weight a_p / 2 (a_p a third of the area of its
    triangles), an edge's A_e / 4 (A_e a third of the area of the triangles at it), and
    the edges' squared rest lengths (the mollifier's thresholds).  triangles (M, 3),
    tri_edge (M, 3) the edge row of each triangle's edge k (opposite vertex k,
    `mesh.unique_edges`).  Differentiable in ref (the optimiser's adjoint: the weights
    move with the template).  xp: the array module, jax.numpy or numpy (the host's
    topology, where jax.numpy would compile a program for each operation of each mesh)."""
    X = ref if ref.shape[1] == 3 else xp.concatenate([ref, xp.zeros_like(ref[:, :1])], 1)
    Y = X[triangles]
    area = 0.5 * xp.linalg.norm(xp.cross(Y[:, 1] - Y[:, 0], Y[:, 2] - Y[:, 0]), axis=1)
    third = xp.repeat(area[:, None] / 3.0, 3, axis=1)
    # edge k of a triangle joins its vertices k+1 and k+2
    d = Y[:, [2, 0, 1]] - Y[:, [1, 2, 0]]
    d2 = xp.sum(d * d, axis=-1)
    if xp is np:
        node_a = np.zeros(X.shape[0], X.dtype)
        np.add.at(node_a, triangles, third)
        edge_a = np.zeros(n_edges, X.dtype)
        np.add.at(edge_a, tri_edge, third)
        len2 = np.zeros(n_edges, X.dtype)
        len2[tri_edge] = d2
    else:
        node_a = jnp.zeros(X.shape[0], X.dtype).at[triangles].add(third)
        edge_a = jnp.zeros(n_edges, X.dtype).at[tri_edge].add(third)
        len2 = jnp.zeros(n_edges, X.dtype).at[tri_edge].set(d2)
    return node_a / 2.0, edge_a / 4.0, len2


def pair_weights(node_w, edge_w, edge_len2, pt_node, ee_edges):
    """(pt_w (P,), ee_w (Q,), ee_eps (Q,)) of point-triangle pairs of nodes pt_node (P,)
    and edge-edge pairs of edge rows ee_edges (Q, 2), from `collision_weights`."""
    ea, eb = ee_edges[:, 0], ee_edges[:, 1]
    return (node_w[pt_node], edge_w[ea] + edge_w[eb],
            mollifier_threshold(jnp.sqrt(edge_len2[ea]), jnp.sqrt(edge_len2[eb])))


def _rows(x, idx):
    return tuple(x[idx[..., k]] for k in range(4))


#: the coordinates a padding row (weight 0) is evaluated at: a point 2 mm above a unit
#: triangle, and two crossed unit edges 2 mm apart, so that its value and derivatives are
#: finite (and then zeroed) whatever nodes the row holds
_PT_SAFE = ((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
_EE_SAFE = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 2.0), (0.0, 1.0, 2.0))


def _safe(corners, on, safe):
    return tuple(jnp.where(on[:, None], c, jnp.asarray(v, c.dtype)) for c, v in zip(corners, safe))


def pt_energies(law, x, pt, pt_w):
    """Energy (P,) N mm of each point-triangle row (typed closed forms: exact second
    derivatives, `tangent`); rows of weight 0 are padding."""
    on = pt_w > 0
    p, t0, t1, t2 = _safe(_rows(x, pt), on, _PT_SAFE)
    d2 = point_triangle_distance2(p, t0, t1, t2)
    z = jnp.where(on, d2 / (law.dhat * law.dhat), 1.0)
    return law.stiffness * law.dhat * pt_w * barrier(z)


def ee_energies(law, x, ee, ee_w, ee_eps):
    """Energy (Q,) N mm of each edge-edge row, mollified (typed closed forms); rows of
    weight 0 are padding."""
    on = ee_w > 0
    a0, a1, b0, b1 = _safe(_rows(x, ee), on, _EE_SAFE)
    d2 = edge_edge_distance2(a0, a1, b0, b1)
    z = jnp.where(on, d2 / (law.dhat * law.dhat), 1.0)
    m = mollifier(edge_edge_cross2(a0, a1, b0, b1), jnp.where(on, ee_eps, 1.0))
    return law.stiffness * law.dhat * ee_w * m * barrier(z)


# ----------------------------------------------------------------- forces, chunk by chunk
#: rows of a pair list evaluated per trip of the force loop (`forces`)
CHUNK = 512


def barrier_d(z):
    """(B(z), B'(z), B''(z)) for z = d^2 / d_hat^2 (zero from z = 1 on)."""
    on = z < 1.0
    zs = jnp.where(on, jnp.maximum(z, 1e-300), 1.0)
    lg = jnp.log(zs)
    b = -(zs - 1.0) ** 2 * lg
    b1 = -2.0 * (zs - 1.0) * lg - (zs - 1.0) ** 2 / zs
    b2 = -2.0 * lg - 4.0 * (zs - 1.0) / zs + (zs - 1.0) ** 2 / zs ** 2
    return (jnp.where(on, b, 0.0), jnp.where(on, b1, 0.0), jnp.where(on, b2, 0.0))


def _stiffness(law, d2, dEdz, d2Edz2):
    """An upper estimate (K,) N/mm of a pair's stiffness along its distance: |E''(d)| +
    |E'(d)| / d with E as a function of d (z = d^2 / d_hat^2), for FIRE's masses."""
    h2 = law.dhat * law.dhat
    d = jnp.sqrt(jnp.maximum(d2, 1e-300))
    dz = 2.0 * d / h2
    return jnp.abs(d2Edz2 * dz * dz + dEdz * 2.0 / h2) + jnp.abs(dEdz * dz) / d


def _pt_chunk(law, xr, w):
    """(energy, gradient (C, 4, 3), squared distance (C,), stiffness (C,)) of point-
    triangle rows with coordinates xr (C, 4, 3) and weights w (C,) (0: padding).  The
    gradient with the closest point held fixed is the exact one (envelope theorem)."""
    p, a, b, c = xr[:, 0], xr[:, 1], xr[:, 2], xr[:, 3]
    W = point_triangle_weights(p, a, b, c)
    r = p - (W[:, 0:1] * a + W[:, 1:2] * b + W[:, 2:3] * c)
    d2 = jnp.sum(r * r, -1)
    scale = law.stiffness * law.dhat * w
    B, B1, B2 = barrier_d(jnp.where(w > 0, d2 / (law.dhat * law.dhat), 1.0))
    gp = (scale * B1 * 2.0 / (law.dhat * law.dhat))[:, None] * r
    g = jnp.stack([gp, -W[:, 0:1] * gp, -W[:, 1:2] * gp, -W[:, 2:3] * gp], 1)
    return (jnp.sum(scale * B), g, jnp.where(w > 0, d2, jnp.inf),
            _stiffness(law, d2, scale * B1, scale * B2))


def _ee_chunk(law, xr, w, eps):
    """`_pt_chunk` for edge-edge rows [a0, a1, b0, b1] with mollifier thresholds eps."""
    a0, a1, b0, b1 = xr[:, 0], xr[:, 1], xr[:, 2], xr[:, 3]
    s, t = edge_edge_params(a0, a1, b0, b1)
    u, v = a1 - a0, b1 - b0
    r = a0 + s[:, None] * u - b0 - t[:, None] * v
    d2 = jnp.sum(r * r, -1)
    cr = jnp.cross(u, v)
    x = jnp.sum(cr * cr, -1)
    m, dm = mollifier_d(x, jnp.where(w > 0, eps, 1.0))
    scale = law.stiffness * law.dhat * w
    B, B1, B2 = barrier_d(jnp.where(w > 0, d2 / (law.dhat * law.dhat), 1.0))
    gd = (scale * m * B1 * 2.0 / (law.dhat * law.dhat))[:, None] * r   # d E / d r
    gx = (scale * B * dm * 2.0)[:, None]                                 # d E / d x / 2
    gu = gx * jnp.cross(v, cr)
    gv = gx * jnp.cross(cr, u)
    g = jnp.stack([(1.0 - s)[:, None] * gd - gu, s[:, None] * gd + gu,
                   -(1.0 - t)[:, None] * gd - gv, -t[:, None] * gd + gv], 1)
    return (jnp.sum(scale * m * B), g, jnp.where(w > 0, d2, jnp.inf),
            _stiffness(law, d2, scale * m * B1, scale * m * B2))


def forces(law, x, pairs, weights):
    """(energy N mm, gradient (N, 3) N, nearest pair distance per node (N,) mm (+inf: in
    no pair), stiffness estimate per node (N,) N/mm) of the barrier over the pairs in use
    of ``pairs`` (`jaxvalve.contact.pairs.PairList`) at x (N, 3) mm.  weights: the
    collision weights (`collision_weights`).  A loop over chunks of `CHUNK` rows with a
    trip count set by the rows in use, so the cost follows the pairs, not the capacity;
    gradients are written out by hand (no reverse pass through the loop)."""
    node_w, edge_w, len2 = weights
    n = x.shape[0]

    def run(rows, count, extra, kernel, carry):
        C = rows.shape[0]
        pad = -C % CHUNK
        rows = jnp.concatenate([rows, jnp.zeros((pad, rows.shape[1]), rows.dtype)]) if pad else rows

        def trip(i, carry):
            E, g, dmin, kb = carry
            k0 = (i * CHUNK).astype(jnp.int32)
            blk = jax.lax.dynamic_slice(rows, (k0, jnp.int32(0)), (CHUNK, rows.shape[1]))
            r = blk[:, :4]
            valid = (k0 + jnp.arange(CHUNK)) < count
            e, gr, d2, k = kernel(x[r], *extra(blk, valid))
            g = g.at[r].add(gr)
            dmin = dmin.at[r].min(jnp.broadcast_to(d2[:, None], r.shape))
            kb = kb.at[r].add(jnp.broadcast_to(k[:, None], r.shape))
            return E + e, g, dmin, kb

        trips = unvmap_max(((jnp.minimum(count, C) + CHUNK - 1) // CHUNK).astype(jnp.int32))
        return jax.lax.fori_loop(jnp.int32(0), trips, trip, carry)

    carry = (jnp.zeros((), x.dtype), jnp.zeros_like(x), jnp.full((n,), jnp.inf, x.dtype),
             jnp.zeros((n,), x.dtype))
    carry = run(pairs.pt, pairs.n_pt,
                lambda b, ok: (jnp.where(ok, node_w[b[:, 0]], 0.0),),
                lambda xr, w: _pt_chunk(law, xr, w), carry)

    def ee_extra(b, ok):
        ea, eb = b[:, 4], b[:, 5]
        return (jnp.where(ok, edge_w[ea] + edge_w[eb], 0.0),
                mollifier_threshold(jnp.sqrt(len2[ea]), jnp.sqrt(len2[eb])))

    E, g, dmin2, kb = run(jnp.concatenate([pairs.ee, pairs.ee_id], 1), pairs.n_ee, ee_extra,
                          lambda xr, w, eps: _ee_chunk(law, xr, w, eps), carry)
    return E, g, jnp.sqrt(dmin2), kb

