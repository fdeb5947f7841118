"""Smooth (C1) penalty contact energy between membrane bodies: the differentiable default.

Energy (N mm), with d_{i,B} = unsigned distance (mm) from node i to the surface of body B
(the minimum over B's triangles in the neighbour list) and a_i the lumped reference area of
node i (mm^2, sum of A_T / 3 over its triangles):

    E = sum_i sum_{B != body(i)} (1/2) a_i phi(d_{i,B}),    phi(d) = (k/2) (g0 - d)_+^2.

* phi and phi' vanish at d = g0: no jump in value or force at the activation distance; phi
  is C1 (phi'' jumps by k at g0).
* Mesh independence: a node is pushed by the *nearest* point of each other body, once per
  body, so a flat sheet at distance d < g0 from a flat sheet feels d E / d d = a_i k (g0 -
  d) whatever the triangle sizes (summing over all triangles in range would count a node
  above a shared edge twice, and ~ (g0 / h)^2 triangles on a fine mesh).  The minimum of
  point-triangle distances of one surface is C1 across shared edges and vertices (the
  minimisers coincide there); it has kinks only on the surface's medial axis, e.g. a node
  equidistant from two distinct folds of the same leaflet.
* The node-to-surface term is evaluated in both directions (nodes of A against the surface
  of B and nodes of B against A) with weight 1/2, so that the pressure between two sheets
  is p = k (g0 - d) (MPa) on each, symmetric in A and B; a lone node over a sheet feels
  half of it.  Forces are -grad E: they sum to zero (translation invariance) and have zero
  net torque (rotation invariance); the reaction acts on the triangle's vertices with the
  barycentric weights of the closest point.

Defaults: g0 = 0.2 mm (well below the coaptation threshold g_c = 0.5 mm, so touching
leaflets are counted as coapting: their gap is <= g0 < g_c), k = 1 MPa/mm.  Two sheets
pressed at the diastolic 80 mmHg = 0.010666 MPa settle at g0 - P/k = 0.189 mm: the
penetration into the layer is 5 % of g0, and sheets reach d = 0 (where an unsigned-distance
penalty loses its sense of side) only above P = k g0 = 0.2 MPa = 1500 mmHg.  The nodal
contact stiffness k a_i ~ 1 N/mm for ~1 mm^2 nodes is of the order of the membrane stiffness
E H ~ 0.3 N/mm, which keeps the equilibrium solve well conditioned.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from ..vmap_control import batch_max
from ..errors import ParameterError
from .geometry import (closest_point_soa, nearest_search_soa, point_triangle_distance_soa,
                       triangle_table)
from .soft_pairs import SoftPairs, build_soft_pairs
from .neighbours import MAX_GROUP, SLOT_BITS, NeighbourList, bucket_index, bucket_sizes

__all__ = ["SmoothContact", "pair_distances", "node_areas", "nearest_triangles"]

_INT64_MAX = (1 << 63) - 1


def node_areas(x_ref, triangles):
    """Lumped node areas (N,) in mm^2: sum of A_T / 3 over the triangles of each node."""
    xt = x_ref[triangles]
    e1, e2 = xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]
    if x_ref.shape[1] == 2:
        area = 0.5 * jnp.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    else:
        area = 0.5 * jnp.linalg.norm(jnp.cross(e1, e2), axis=-1)
    return jnp.zeros(x_ref.shape[0], x_ref.dtype).at[triangles].add(area[:, None] / 3.0)


def _columns(x, idx):
    """x[idx] as a tuple of 3 component arrays (structure of arrays)."""
    return tuple(x[:, k][idx] for k in range(3))


def pair_distances(x, triangles, nbrs: NeighbourList, signed: bool = False):
    """Node-triangle distances (capacity,) in mm for the rows of ``nbrs.pairs``; padding
    rows get +inf.  With ``signed``, also the side (capacity,): -1 where the node lies over
    the triangle's face on its -n side (n = (b - a) x (c - a)), else +1."""
    n = x.shape[0]
    valid = nbrs.slot_valid
    node = jnp.clip(nbrs.group_node[nbrs.row_group], 0, n - 1)[:, None]
    t = triangles[jnp.where(valid, nbrs.cand, 0)]
    p = tuple(jnp.broadcast_to(c, valid.shape) for c in _columns(x, node))
    a, b, c = (_columns(x, t[..., k]) for k in range(3))
    d, _, _, side = point_triangle_distance_soa(p, a, b, c, side=True)
    d = jnp.where(valid, d, jnp.inf).reshape(-1)
    if not signed:
        return d
    return d, side.reshape(-1)


def soft_distance(x, triangles, nbrs: NeighbourList, live, *, softness):
    """Soft-min distance (R,) mm per group of `nbrs` (see `SmoothContact`), over every
    candidate triangle T of the group: sum_T w_T d_T / sum_T w_T, with
    w_T = exp(-(d_T - min d) / softness); differentiable.  live (R,) bool: the groups
    wanted; the others get +inf.

    This is the definition.  The energy evaluates it on a pruned list
    (`soft_pairs.SoftPairs`, only the T with w_T > exp(-PRUNE_REACH)); the tests check
    the two against each other."""
    R = nbrs.cand.shape[0]
    rows = live[nbrs.row_group] & (jnp.arange(R) < nbrs.n_rows)
    cand = jnp.where(rows[:, None], nbrs.cand, triangles.shape[0])
    valid = cand < triangles.shape[0]
    grp = nbrs.row_group
    node = jnp.clip(nbrs.group_node[grp], 0, x.shape[0] - 1)
    v = triangles[jnp.where(valid, cand, 0)]                          # (R, W, 3)
    idx = jnp.stack([jnp.broadcast_to(node[:, None], valid.shape), v[..., 0], v[..., 1],
                     v[..., 2]]).reshape(4, -1)
    d = _distance_rows(x, idx).reshape(valid.shape)
    dd = jax.lax.stop_gradient(jnp.where(valid, d, jnp.inf))
    shift = jax.ops.segment_min(jnp.min(dd, 1), grp, num_segments=R)[grp][:, None]
    z = jnp.where(valid, -(d - jnp.where(jnp.isfinite(shift), shift, 0.0)) / softness, -jnp.inf)
    w = jnp.where(valid, jnp.exp(z), 0.0)            # <= 1; the nearest has w = 1
    num = jax.ops.segment_sum(jnp.sum(w * d, 1), grp, num_segments=R)
    den = jax.ops.segment_sum(jnp.sum(w, 1), grp, num_segments=R)
    ok = (den > 0) & live
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), jnp.inf)


def soft_energy_reference(law, x, triangles, nbrs: NeighbourList, node_area):
    """The soft-min contact energy (N mm) of `law` from its definition: `soft_distance`
    over every candidate of each live group.  For checks and benchmarks of the pruned
    evaluation that `SmoothContact.energy` uses."""
    _, side, found, dist = nearest_triangles(x, triangles, nbrs, law.one_sided)
    s_hard = side * dist if law.one_sided else dist
    live = found & (s_hard < jax.lax.stop_gradient(law.gap))
    d = soft_distance(x, triangles, nbrs, live, softness=law.softness)
    s = jnp.minimum(jnp.where(live, side * d if law.one_sided else d, law.gap), law.gap)
    node = jnp.clip(nbrs.group_node, 0, x.shape[0] - 1)
    return 0.5 * jnp.sum(jnp.where(live, node_area[node], 0.0) * law.potential(s))


#: Static prefixes of the pruned pair list that the soft-min energy chooses from, each
#: half the last (`SmoothContact._energy_pairs`).
SOFT_PREFIXES = 5

CHUNK_ROWS = 256  # rows (x ROW_WIDTH slots) per loop iteration of the nearest search


def nearest_triangles(x, triangles, nbrs: NeighbourList, one_sided: bool = False):
    """The nearest candidate triangle of every group of `nbrs` (not differentiated).

    Returns ``(tri, side, found, dist)``, each (R,) over the group slots: the triangle,
    the side (+1 / -1, see `pair_distances`) of the node as seen from it, whether the group
    exists (groups are [0, number of groups)), and the distance to it (to ~1e-12, from the
    key; +inf where not found).

    The rows in use ([0, ``nbrs.n_rows``)) are visited CHUNK_ROWS at a time in a loop
    with a dynamic trip count, so the cost follows the pairs in use, not the capacity.
    One fused pass per chunk evaluates every slot and packs (squared distance, side, slot)
    into one int64 key, whose minimum is taken per row (a dense reduction) and then per
    group (a scatter-min over the chunk's rows).  The key keeps the top 52 - SLOT_BITS - 1
    mantissa bits of the squared distance, so distances within ~1e-12 (relative) count as
    ties, which go to the + side (with ``one_sided``) and then to the first candidate.
    """
    x = jax.lax.stop_gradient(x)
    n, m = x.shape[0], triangles.shape[0]
    R, W = nbrs.cand.shape
    C = min(R, CHUNK_ROWS)
    table = triangle_table(x, triangles)                              # (16, M)
    xc = tuple(x[:, k] for k in range(3))
    lane = jnp.arange(W, dtype=jnp.int32)[None, :]
    clear = ~jnp.int64((2 << SLOT_BITS) - 1)

    def body(i, gkey):
        r0 = jnp.minimum(i * C, R - C).astype(jnp.int32)
        cand = jax.lax.dynamic_slice(nbrs.cand, (r0, jnp.int32(0)), (C, W))
        rg = jax.lax.dynamic_slice(nbrs.row_group, (r0,), (C,))
        valid = cand < m
        t = jnp.where(valid, cand, 0)
        cols = tuple(table[k][t] for k in range(table.shape[0]))      # 16 x (C, W)
        node = jnp.clip(nbrs.group_node[rg], 0, n - 1)
        d2, back = nearest_search_soa(tuple(c[node][:, None] for c in xc), cols)
        # the key packs a float64 (a float32 solve's distances are widened exactly)
        key = jax.lax.bitcast_convert_type(d2.astype(jnp.float64), jnp.int64) & clear
        if one_sided:
            key = key | jnp.left_shift(back.astype(jnp.int64), SLOT_BITS)
        local = (r0 + jnp.arange(C, dtype=jnp.int32) - nbrs.group_row[rg])[:, None] * W + lane
        key = key | jnp.clip(local, 0, MAX_GROUP - 1).astype(jnp.int64)
        key = jnp.where(valid, key, _INT64_MAX)
        return gkey.at[rg].min(jnp.min(key, axis=1), mode="drop")

    # under vmap the batch's largest trip count (`vmap_control`); extra trips see padding rows
    n_chunks = batch_max(((nbrs.n_rows + C - 1) // C).astype(jnp.int32))
    gkey = jax.lax.fori_loop(jnp.int32(0), n_chunks, body, jnp.full((R,), _INT64_MAX, jnp.int64))
    found = gkey != _INT64_MAX
    slot = (gkey & (MAX_GROUP - 1)).astype(jnp.int32)
    row = jnp.clip(nbrs.group_row + slot // W, 0, R - 1)
    tri = jnp.clip(nbrs.cand[row, slot % W], 0, m - 1)
    side = jnp.where((gkey >> SLOT_BITS) & 1 == 1, -1.0, 1.0).astype(x.dtype)
    d2 = jax.lax.bitcast_convert_type(jnp.where(found, gkey & clear, 0),
                                      jnp.float64).astype(x.dtype)
    return tri, side, found, jnp.where(found, jnp.sqrt(d2), jnp.inf)


@jax.custom_jvp
def _distance_rows(x, idx):
    """Distances (B,) from nodes idx[0] to triangles (idx[1], idx[2], idx[3]), x (N, 3).

    Custom derivative (envelope theorem, as `distance_soa`): d' = (e / d) . (p' - u a' -
    v b' - w c'), with e = p - q and (u, v, w) the barycentric weights of the closest point
    q; 0 at d = 0.  The coefficients are functions of x, so second derivatives are exact
    too.  Written on structure-of-arrays columns: its transpose is 12 scalar scatters,
    ~10x faster on CPU than the transpose of autodiff through the region selection."""
    p, a, b, c = (_columns(x, idx[k]) for k in range(4))
    return point_triangle_distance_soa(p, a, b, c)[0]


@_distance_rows.defjvp
def _distance_rows_jvp(primals, tangents):
    x, idx = primals
    x_dot = tangents[0]
    p, a, b, c = (_columns(x, idx[k]) for k in range(4))
    u, v, w = closest_point_soa(p, a, b, c)
    e = tuple(p[k] - (u * a[k] + v * b[k] + w * c[k]) for k in range(3))
    s = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    pos = s > 0
    d = jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)
    inv = jnp.where(pos, 1.0 / jnp.where(pos, d, 1.0), 0.0)
    pd, ad, bd, cd = (_columns(x_dot, idx[k]) for k in range(4))
    d_dot = sum(e[k] * inv * (pd[k] - u * ad[k] - v * bd[k] - w * cd[k]) for k in range(3))
    return d, d_dot


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["stiffness", "gap", "softness"],
                   meta_fields=["one_sided", "soft_min"])
@dataclasses.dataclass(frozen=True)
class SmoothContact:
    """C1 penalty contact: pressure k (g0 - d)_+ between sheets (see module docstring).

    stiffness: k, contact pressure per unit penetration into the layer (MPa/mm).
    gap: g0, activation distance (mm); build the neighbour list with cutoff >= gap + skin.
    Both are traced (differentiable) fields.
    one_sided: (static) measure the gap as a signed distance s = +-d, positive on the +n
    side of the nearest triangle of the other body, and penalise (k/2)(g0 - s)_+^2.  A node
    that crossed the other sheet is then pushed back, never further through.  Use it when
    the bodies face each other with their +n sides, as valve leaflets do (their normals
    point from the aortic to the ventricular side, and their ventricular sides coapt).
    soft_min: (static) replace the distance to the nearest triangle of the other body by
    the soft minimum over its candidate triangles T (`soft_distance`),
        d_soft = sum_T w_T d_T / sum_T w_T,   w_T = exp(-(d_T - min_T d_T) / softness),
    which equals the nearest distance where candidates tie (a node above a shared edge or
    vertex of a flat sheet: no double counting) and is C-infinity where the nearest
    triangle switches.  The hard minimum has a kink there; a node pressed into a crease
    of the other leaflet (two faces at equal distance) then has no point of zero force
    and no solver can drive the residual down.  softness: mm, traced (default 0.01).
    Over a flat sheet the soft minimum exceeds the true distance by at most ~softness / e
    near edges (the weights of the neighbours of the nearest triangle).  With one_sided
    the sign comes from the nearest triangle, so the signed gap side * d_soft jumps where a
    node under a sheet passes its edge (a crossed node; not at equilibrium).
    """

    stiffness: float | jax.Array = 1.0
    gap: float | jax.Array = 0.2
    softness: float | jax.Array = 0.01
    one_sided: bool = False
    soft_min: bool = False

    def validate(self) -> "SmoothContact":
        """Host-side check; raises `ParameterError` naming the parameter and its range."""
        for name, hi in (("stiffness", math.inf), ("gap", 0.5), ("softness", 0.1)):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v <= 0 or v >= hi:
                rng = "> 0 and finite" if hi == math.inf else f"in (0, {hi}) mm"
                unit = "MPa/mm" if name == "stiffness" else "mm"
                if name == "softness" and not self.soft_min:
                    continue
                raise ParameterError(f"SmoothContact.{name} must be {rng}; got {v} {unit}"
                                     + (" (g0 must stay below the coaptation threshold "
                                        "g_c = 0.5 mm)" if name == "gap" else ""))
        return self

    def potential(self, d):
        """phi(d) = (k/2) (g0 - d)_+^2 in MPa mm = N/mm (energy per unit area)."""
        s = jnp.maximum(self.gap - d, 0.0)
        return 0.5 * self.stiffness * s * s

    def energy(self, x, triangles, nbrs: NeighbourList, node_area):
        """Contact energy (N mm) for positions x (N,3) mm, node_area (N,) mm^2; nbrs: a
        `NeighbourList`, or for the soft minimum also a `soft_pairs.SoftPairs` (which a
        solve keeps; from a `NeighbourList` the pruned list is built here, at x).

        Hard minimum: the nearest triangle of each (node, body) group is found without
        derivatives (`nearest_triangles`).  Only the groups within the gap (s < g0) carry
        energy: they are gathered to the front, and the distance to their nearest triangle is
        recomputed differentiably (exact first and second derivatives, `_distance_rows`)
        on the shortest of a few static prefixes that holds them (`lax.switch`)."""
        if self.soft_min:
            if not isinstance(nbrs, SoftPairs):   # prune at x itself (no margin needed)
                nbrs = build_soft_pairs(nbrs, x, triangles, self, nbrs.capacity, margin=0.0)
            return self._energy_pairs(x, triangles, nbrs, node_area)
        tri, side, found, dist = nearest_triangles(x, triangles, nbrs, self.one_sided)
        R = found.shape[0]
        s = side * dist if self.one_sided else dist
        gap = jax.lax.stop_gradient(self.gap)
        active = found & (s < gap * (1.0 + 1e-9) + 1e-12)   # margin >> key truncation
        rank = jnp.cumsum(active, dtype=jnp.int32) - 1
        live = jnp.zeros((R,), jnp.int32).at[jnp.where(active, rank, R)].set(
            jnp.arange(R, dtype=jnp.int32), mode="drop")
        n_live = jnp.sum(active, dtype=jnp.int32)
        sizes = bucket_sizes(R, smallest=256, most=3, factor=4)
        branches = [functools.partial(self._energy_groups, b) for b in sizes]
        return jax.lax.switch(bucket_index(sizes, n_live), branches, x, triangles,
                              tri[live], side[live], jnp.arange(R) < n_live,
                              nbrs.group_node[live], node_area)

    def _energy_pairs(self, x, triangles, pairs, node_area):
        """Soft-min energy on a pruned pair list (`soft_pairs.SoftPairs`): the soft
        distance of `soft_distance` over the listed triangles of each group (every
        triangle that weighs more than exp(-PRUNE_REACH) of the nearest; tested equal to
        the sum over all candidates), whose nearest one gives the side and the liveness.
        Only the groups with a (signed) gap below g0 carry energy.  Evaluated on the
        shortest static prefix of the list that holds its pairs (`lax.switch`).

        The prefixes halve down to 1/16 of the capacity (`SOFT_PREFIXES`): a force costs
        about 0.06-0.09 us per slot of its prefix, and the pairs in use range from a few
        while the leaflets swing shut to about 2000 of 6144 slots at 80 mmHg (the
        benchmark valve at h = 1.5 mm), so with three prefixes (down to 1/4) the
        swing-shut paid for 1536 slots.  Five prefixes closed it 1.05-1.09x faster for
        1.4-3.4 s more compilation (`benchmarks/step_savings.py`; docs/benchmark-notes.md,
        "A FIRE step's cost")."""
        base = pairs.base
        R = base.rows
        sizes = bucket_sizes(pairs.soft_capacity, smallest=256, most=SOFT_PREFIXES, factor=2)
        node_of = jnp.clip(base.group_node, 0, x.shape[0] - 1)

        def branch(q, x):
            ok = jnp.arange(q) < pairs.n
            g = jnp.where(ok, pairs.group[:q], 0)
            t = jnp.where(ok, pairs.tri[:q], 0)
            node = node_of[g]
            v = triangles[t]
            idx = jnp.stack([node, v[:, 0], v[:, 1], v[:, 2]])
            d = _distance_rows(x, idx)
            cols = [_columns(jax.lax.stop_gradient(x), idx[k]) for k in range(4)]
            d0, _, _, side_p = point_triangle_distance_soa(*cols, side=True)   # no grad
            d0 = jnp.where(ok, d0, jnp.inf)
            dmin = jax.ops.segment_min(d0, g, num_segments=R)
            found = jnp.isfinite(dmin)
            if self.one_sided:
                at_min = ok & (d0 <= dmin[g])
                side = jax.ops.segment_max(jnp.where(at_min, side_p, -1.0), g, num_segments=R)
                # a group without pairs has side -inf (empty max): its energy term is
                # masked, but 0 * inf would put NaN into the gradient w.r.t. the gap
                side = jnp.where(found, side, 1.0)
                s_hard = side * dmin
            else:
                side, s_hard = 1.0, dmin
            live = found & (s_hard < jax.lax.stop_gradient(self.gap))
            z = jnp.where(ok, -(d - jnp.where(ok, dmin[g], 0.0)) / self.softness, -jnp.inf)
            w = jnp.where(ok, jnp.exp(z), 0.0)
            num = jax.ops.segment_sum(jnp.where(ok, w * d, 0.0), g, num_segments=R)
            den = jax.ops.segment_sum(w, g, num_segments=R)
            good = live & (den > 0)
            ds = jnp.where(good, num / jnp.where(good, den, 1.0), self.gap)
            s = jnp.minimum(jnp.where(good, side * ds, self.gap), self.gap)
            return 0.5 * jnp.sum(jnp.where(good, node_area[node_of], 0.0) * self.potential(s))

        branches = [functools.partial(branch, q) for q in sizes]
        return jax.lax.switch(bucket_index(sizes, pairs.n), branches, x)

    def _energy_groups(self, b, x, triangles, tri, side, live, group_node, node_area):
        node = jnp.clip(group_node[:b], 0, x.shape[0] - 1)
        v = triangles[tri[:b]]
        d = _distance_rows(x, jnp.stack([node, v[:, 0], v[:, 1], v[:, 2]]))
        s = side[:b] * d if self.one_sided else d
        s = jnp.minimum(jnp.where(live[:b], s, self.gap), self.gap)    # others: no energy
        return 0.5 * jnp.sum(node_area[node] * self.potential(s))

    def forces(self, x, triangles, nbrs: NeighbourList, node_area):
        """Contact forces (N,3) in N: -grad energy."""
        return -jax.grad(self.energy)(x, triangles, nbrs, node_area)
