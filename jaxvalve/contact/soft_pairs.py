"""Second-level pair list for the soft-min contact law: the few triangles that matter.

The soft minimum of `SmoothContact(soft_min=True)` weighs a candidate triangle T of a
(node, body) group by exp(-(d_T - d_min) / softness).  A triangle more than
``PRUNE_REACH`` softness lengths (0.25 mm at the default 0.01 mm) further than the nearest
one weighs < exp(-25) = 1.4e-11 of it: far below the rounding of the sums.  Of the ~30
candidates a group of the Verlet list holds (cutoff g0 + skin), ~5 pass this test in a
closed valve, so evaluating only them is ~5x cheaper per force evaluation.

`SoftPairs` holds the Verlet list (``base``) and, built at positions x_b, the pairs
(group, T) of the groups that can touch (nearest distance < g0 + margin, or the node on the
back of its nearest triangle) whose T satisfies d_T(x_b) <= d_min(x_b) + reach + margin.

Validity.  When no node has moved more than margin / 4 since x_b, every distance moved by
at most margin / 2 (the node and the triangle each by margin / 4), so every T with
d_T(x) <= d_min(x) + reach is in the list, and every group with a gap below g0 was
listed (its distance at x_b was < g0 + margin / 2).  `refresh` rebuilds the list when
that no longer holds, and whenever the Verlet list is rebuilt (the group ids refer to its
layout).  The one case a stale list misses is a node far (> g0 + margin / 2) from the
other sheet whose nearest triangle turns from front to back within one refresh interval (a
node that slid behind a free edge); the next refresh lists it.

Capacities are static; ``overflow`` is set (sticky) when the pairs needed exceed it, and
is checked on the host like the Verlet list's (`equilibrium.solve` retries larger).
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..vmap_control import cond_each
from .geometry import point_triangle_distance_soa
from .neighbours import NeighbourList, bucket_index, bucket_sizes, filled, needs_rebuild
from .neighbours import update as update_verlet

__all__ = ["SoftPairs", "PRUNE_REACH", "DEFAULT_MARGIN", "build_soft_pairs", "refresh",
           "default_soft_capacity", "stale_soft_pairs"]

#: Candidates further than PRUNE_REACH softness lengths beyond the nearest are dropped.
PRUNE_REACH = 25.0
#: Extra distance (mm) kept at a build; the list is rebuilt after a move of margin / 4
#: (0.1-0.4 mm measured within the timing noise on the benchmark valve).
DEFAULT_MARGIN = 0.25


def default_soft_capacity(n_nodes: int) -> int:
    """Pair slots: 8 per node (a closed valve needs ~5 per coapting node)."""
    return max(1024, 8 * int(n_nodes))


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["base", "tri", "group", "n", "x_build", "margin",
                                "soft_overflow", "soft_count"],
                   meta_fields=["soft_capacity"])
@dataclasses.dataclass(frozen=True)
class SoftPairs:
    """Pruned (group, triangle) pairs over a Verlet list (a pytree; capacity static).

    base: the `NeighbourList` (groups, candidates).
    tri, group: (P,) int32 triangle and base-group of each pair; pairs [0, n) in use.
    n: () int32 pairs in use (min(needed, P)).
    x_build: (N, 3) mm, positions at the build; margin: () mm.
    soft_overflow: () bool, sticky: some build needed more than P pairs.
    soft_count: () int32, sticky max of the pairs needed.
    """

    base: NeighbourList
    tri: jax.Array
    group: jax.Array
    n: jax.Array
    x_build: jax.Array
    margin: jax.Array
    soft_overflow: jax.Array
    soft_count: jax.Array
    soft_capacity: int

    @property
    def overflow(self):
        return self.base.overflow | self.soft_overflow

    @property
    def count(self):
        return self.base.count

    @property
    def capacity(self):
        return self.base.capacity


def _row_prefix(base: NeighbourList, want, b):
    """The rows of the wanted groups gathered to the front, first b of them: (cand (b, W)
    with padding M, group (b,))."""
    R = base.rows
    m = base.n_triangles
    row_want = want[base.row_group] & (jnp.arange(R) < base.n_rows)
    rank = jnp.cumsum(row_want, dtype=jnp.int32) - 1
    pick = jnp.full((R,), R - 1, jnp.int32).at[jnp.where(row_want, rank, R)].set(
        jnp.arange(R, dtype=jnp.int32), mode="drop")[:b]
    keep = jnp.arange(b) < jnp.sum(row_want)
    return jnp.where(keep[:, None], base.cand[pick], m), base.row_group[pick]


def _select(x, want, dmin, limit, *, triangles, base, capacity, b):
    """Pairs of the first b wanted rows with d_T <= dmin + limit, compacted into
    (tri (P,), group (P,), needed)."""
    m = triangles.shape[0]
    W = base.row_width
    cand, grp = _row_prefix(base, want, b)
    valid = cand < m
    node = jnp.clip(base.group_node[grp], 0, x.shape[0] - 1)
    v = triangles[jnp.where(valid, cand, 0)]
    p = tuple(x[:, k][node][:, None] for k in range(3))
    abc = [tuple(x[:, k][v[..., j]] for k in range(3)) for j in range(3)]
    d = point_triangle_distance_soa(p, *abc)[0]
    close = valid & (d <= (dmin[grp] + limit)[:, None])
    flat = close.reshape(-1)
    order = jnp.cumsum(flat, dtype=jnp.int32) - 1
    dest = jnp.where(flat & (order < capacity), order, capacity)
    tri = jnp.full((capacity,), m, jnp.int32).at[dest].set(cand.reshape(-1), mode="drop")
    group = jnp.zeros((capacity,), jnp.int32).at[dest].set(
        jnp.broadcast_to(grp[:, None], (b, W)).reshape(-1), mode="drop")
    return tri, group, jnp.sum(flat, dtype=jnp.int32)


def build_soft_pairs(base: NeighbourList, x, triangles, law, capacity: int,
                     margin=None, *, old: SoftPairs | None = None) -> SoftPairs:
    """The pruned pair list of `law` (a soft-min `SmoothContact`) at x (jit-compatible).
    ``old``: the list it replaces (its sticky overflow and count carry over)."""
    from .smooth import nearest_triangles
    x = jax.lax.stop_gradient(x)
    _, side, found, dist = nearest_triangles(x, triangles, base, law.one_sided)
    gap = jax.lax.stop_gradient(law.gap)
    margin = jnp.asarray(DEFAULT_MARGIN if margin is None else margin, x.dtype)
    back = (side < 0) if law.one_sided else jnp.zeros_like(found)
    want = found & ((dist < gap + margin) | back)
    limit = jax.lax.stop_gradient(PRUNE_REACH * law.softness) + margin
    R = base.rows
    n_rows = jnp.sum(want[base.row_group] & (jnp.arange(R) < base.n_rows))
    sizes = bucket_sizes(R, smallest=64, most=2, factor=4)
    branches = [functools.partial(_select, triangles=triangles, base=base,
                                  capacity=capacity, b=b) for b in sizes]
    tri, group, needed = jax.lax.switch(bucket_index(sizes, n_rows), branches, x, want,
                                        jnp.where(want, dist, jnp.inf), limit)
    over = needed > capacity
    count = needed
    if old is not None:
        over = over | old.soft_overflow
        count = jnp.maximum(count, old.soft_count)
    return SoftPairs(base=base, tri=tri, group=group, n=jnp.minimum(needed, capacity),
                     x_build=x, margin=margin, soft_overflow=over, soft_count=count,
                     soft_capacity=capacity)


def stale_soft_pairs(base: NeighbourList, capacity: int, margin=None) -> SoftPairs:
    """An empty pruned list over `base` that `refresh` rebuilds at its first call (with
    `neighbours.stale_list` as base, both levels are built inside the solve)."""
    n = base.x_build.shape[0]
    dtype = base.x_build.dtype
    zero = filled((), 0, jnp.int32)
    return SoftPairs(base=base, tri=filled((capacity,), base.n_triangles, jnp.int32),
                     group=filled((capacity,), 0, jnp.int32), n=zero,
                     x_build=filled((n, 3), np.inf, dtype),
                     margin=jnp.asarray(DEFAULT_MARGIN if margin is None else margin, dtype),
                     soft_overflow=filled((), False, bool), soft_count=zero,
                     soft_capacity=int(capacity))


def refresh(pairs: SoftPairs, x, triangles, body, skin, law) -> SoftPairs:
    """Bring both levels up to date at x (usable in `lax.while_loop`): the Verlet list is
    rebuilt when a node moved more than skin / 2, the pruned list when it was or when a
    node moved more than margin / 4 since its build."""
    x = jax.lax.stop_gradient(x)
    rebuilt = needs_rebuild(pairs.base, x, skin)
    base = update_verlet(pairs.base, x, triangles, body, skin)
    moved = jnp.max(jnp.sum((x - pairs.x_build) ** 2, axis=-1)) > (0.25 * pairs.margin) ** 2
    # under vmap, rebuilt only for the members that need it (`vmap_control.cond_each`)
    return cond_each(
        rebuilt | moved,
        lambda pairs, base, x, tri, law: build_soft_pairs(base, x, tri, law,
                                                          pairs.soft_capacity, pairs.margin,
                                                          old=pairs),
        lambda pairs, base, *_: dataclasses.replace(pairs, base=base),
        pairs, base, x, triangles, law)
