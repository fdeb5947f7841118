"""Fixed-capacity broad phase: candidate (node, triangle) contact pairs between bodies.

Shapes: ``x`` (N, 3) node positions (mm), ``triangles`` (M, 3) int32, ``body`` (N,) int32.
The body of a triangle is the body of its vertex 0.  A pair (i, T) is a *candidate* when
body[i] != body[T] and node i lies within ``cutoff`` of the bounding sphere of T (centre
the barycentre r_T, radius R_T = max_k |x_k - r_T|), i.e. |x_i - r_T| < cutoff + R_T.  This
is conservative: every pair with point-triangle distance < cutoff is a candidate, and so is
every pair with |x_i - r_T| < cutoff (the vicinity test of the paper's law).

Algorithm (O((N + M) log M + N * 27 * cell_capacity) work, never N x M): a uniform cell
grid of size h = cutoff + max_T R_T over the bounding box of x; triangles are sorted by
the linear index of the cell holding their barycentre; each node looks up its 27
neighbouring cells with ``searchsorted`` and tests at most ``cell_capacity`` triangles per
cell.  The grid is never allocated, so its size is free to be traced (linear cell indices
are int64 under ``jax_enable_x64``, which this package requires).

Capacities are static Python ints.  Overflow is never silent: ``overflow`` is set when
more than ``capacity`` pairs were found (``count`` says how many) or when a cell held more
than ``cell_capacity`` triangles (``max_cell_count`` says how many).  Check on the host with
`check_overflow`, or build with `build_neighbours_checked`, which retries with larger
capacities.

Verlet skin: build with ``cutoff = interaction range + skin``; the list stays valid while
no node has moved more than skin / 2 since the build (`needs_rebuild`, `update`).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools

import numpy as np
import jax
import jax.numpy as jnp

from ..errors import NeighbourListOverflow, ParameterError
from .geometry import point_triangle_distance_np

__all__ = [
    "NeighbourList",
    "build_neighbours",
    "build_neighbours_checked",
    "needs_rebuild",
    "update",
    "check_overflow",
    "default_capacity",
    "DEFAULT_CELL_CAPACITY",
    "brute_force_pairs",
    "triangle_body",
]

DEFAULT_CELL_CAPACITY = 32

_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)  # (27,3)


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["pairs", "group", "x_build", "cutoff", "overflow", "count", "max_cell_count"],
    meta_fields=["capacity", "cell_capacity"],
)
@dataclasses.dataclass(frozen=True)
class NeighbourList:
    """Candidate contact pairs (a pytree; capacities are static).

    pairs:  (capacity, 2) int32 rows [node i, triangle T], sorted by (node, body of T).
            Padding rows are [N, M] (out of range): use `valid`.
    group:  (capacity,) int32 id of the (node, body of T) group of each row; groups are
            numbered 0, 1, ... in row order; padding rows get id capacity - 1.
    x_build: (N, 3) positions (mm) at the last build.
    cutoff: () float, candidate radius used (mm).
    overflow: () bool, True if pairs or a cell were dropped (in `update`: at any rebuild).
    count:  () int32, candidate pairs found (may exceed capacity).
    max_cell_count: () int32, most triangles found in one queried cell.
    """

    pairs: jax.Array
    group: jax.Array
    x_build: jax.Array
    cutoff: jax.Array
    overflow: jax.Array
    count: jax.Array
    max_cell_count: jax.Array
    capacity: int
    cell_capacity: int

    @property
    def valid(self):
        """(capacity,) bool mask of real (non-padding) rows."""
        return self.pairs[:, 0] < self.x_build.shape[0]


def triangle_body(triangles, body):
    """Body (M,) of each triangle: the body of its vertex 0."""
    return body[triangles[:, 0]]


def default_capacity(n_nodes: int, pairs_per_node: int = 8) -> int:
    """A starting pair capacity for a mesh of `n_nodes` nodes.

    About 40 % of a closed valve's nodes lie in a coaptation zone, and with cutoff ~ 0.5 mm
    on ~1 mm triangles a node sees ~10 triangles of each of at most two other leaflets:
    ~8 pairs per node on average.  Rounded up to a multiple of 256.
    """
    cap = max(256, int(pairs_per_node) * int(n_nodes))
    return int(-(-cap // 256) * 256)


@functools.partial(jax.jit, static_argnames=("capacity", "cell_capacity"))
def build_neighbours(x, triangles, body, cutoff, capacity: int,
                     cell_capacity: int = DEFAULT_CELL_CAPACITY) -> NeighbourList:
    """Build a `NeighbourList` of candidate pairs within `cutoff` (mm). Jit-compatible."""
    x = jnp.asarray(x)
    triangles = jnp.asarray(triangles, dtype=jnp.int32)
    body = jnp.asarray(body, dtype=jnp.int32)
    cutoff = jnp.asarray(cutoff, dtype=x.dtype)
    n, m = x.shape[0], triangles.shape[0]
    K = int(cell_capacity)
    itype = jnp.int64 if jax.config.jax_enable_x64 else jnp.int32

    xt = x[triangles]                                    # (M,3,3)
    centre = jnp.mean(xt, axis=1)                        # (M,3)
    radius = jnp.max(jnp.linalg.norm(xt - centre[:, None], axis=-1), axis=1)  # (M,)
    tbody = body[triangles[:, 0]]
    h = cutoff + jnp.max(radius)
    h = jnp.where(h > 0, h, 1.0)
    lo = jnp.min(x, axis=0) - 1.5 * h
    dims = jnp.floor((jnp.max(x, axis=0) - lo) / h).astype(itype) + 3  # margin >= 1 cell

    def cell(p):
        return jnp.floor((p - lo) / h).astype(itype)

    def linear(ijk):
        return ijk[..., 0] + dims[0] * (ijk[..., 1] + dims[1] * ijk[..., 2])

    tcell = linear(cell(centre))
    order = jnp.argsort(tcell)
    sorted_cells = tcell[order]
    ncells = linear(cell(x)[:, None, :] + jnp.asarray(_OFFSETS, dtype=itype))  # (N,27)
    start = jnp.searchsorted(sorted_cells, ncells, side="left")
    stop = jnp.searchsorted(sorted_cells, ncells, side="right")
    occ = (stop - start).astype(jnp.int32)
    max_cell = jnp.max(occ)

    k = jnp.arange(K)
    slot = start[..., None] + k                                       # (N,27,K)
    in_cell = k < occ[..., None]
    tri = order[jnp.clip(slot, 0, m - 1)].astype(jnp.int32)
    diff = x[:, None, None, :] - centre[tri]
    reach = cutoff + radius[tri]
    ok = (in_cell
          & (jnp.sum(diff * diff, axis=-1) < reach * reach)
          & (body[:, None, None] != tbody[tri]))

    ok = ok.reshape(-1)
    node = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None, None], tri.shape).reshape(-1)
    tri = tri.reshape(-1)
    pos = jnp.cumsum(ok) - 1
    count = jnp.sum(ok).astype(jnp.int32)
    dest = jnp.where(ok, pos, capacity)
    pair_node = jnp.full((capacity,), n, jnp.int32).at[dest].set(node, mode="drop")
    pair_tri = jnp.full((capacity,), m, jnp.int32).at[dest].set(tri, mode="drop")

    # sort rows by (node, body of triangle) and number the groups
    valid = pair_node < n
    nb = jnp.max(body).astype(itype) + 1
    key = jnp.where(valid,
                    pair_node.astype(itype) * nb + tbody[jnp.clip(pair_tri, 0, m - 1)],
                    jnp.iinfo(itype).max)
    perm = jnp.argsort(key, stable=True)
    key, pair_node, pair_tri, valid = key[perm], pair_node[perm], pair_tri[perm], valid[perm]
    new = jnp.concatenate([jnp.ones((1,), bool), key[1:] != key[:-1]])
    group = (jnp.cumsum(new) - 1).astype(jnp.int32)
    group = jnp.where(valid, group, capacity - 1)

    overflow = (count > capacity) | (max_cell > K)
    return NeighbourList(
        pairs=jnp.stack([pair_node, pair_tri], axis=1),
        group=group,
        x_build=x,
        cutoff=cutoff,
        overflow=overflow,
        count=count,
        max_cell_count=max_cell,
        capacity=int(capacity),
        cell_capacity=K,
    )


def needs_rebuild(nbrs: NeighbourList, x, skin):
    """True () if some node moved more than skin / 2 (mm) since the list was built."""
    d2 = jnp.sum((x - nbrs.x_build) ** 2, axis=-1)
    return jnp.max(d2) > (0.5 * skin) ** 2


def update(nbrs: NeighbourList, x, triangles, body, skin) -> NeighbourList:
    """Rebuild (same cutoff and capacities) under `lax.cond` when `needs_rebuild`.

    Usable inside `lax.while_loop`.  ``overflow``, ``count`` and ``max_cell_count`` are
    sticky (or / max over all rebuilds), so one host-side `check_overflow` after a solve
    tells whether any list along the way dropped pairs.
    """
    def rebuild(old):
        new = build_neighbours(x, triangles, body, old.cutoff, old.capacity, old.cell_capacity)
        return dataclasses.replace(
            new,
            overflow=new.overflow | old.overflow,
            count=jnp.maximum(new.count, old.count),
            max_cell_count=jnp.maximum(new.max_cell_count, old.max_cell_count),
        )

    return jax.lax.cond(needs_rebuild(nbrs, x, skin), rebuild, lambda old: old, nbrs)


def check_overflow(nbrs: NeighbourList) -> None:
    """Host-side: raise `NeighbourListOverflow` naming the capacity to increase."""
    if not bool(nbrs.overflow):
        return
    msgs = []
    count, mcc = int(nbrs.count), int(nbrs.max_cell_count)
    if count > nbrs.capacity:
        msgs.append(f"capacity={nbrs.capacity} is too small: {count} candidate pairs were "
                    f"found; increase capacity to at least {count}")
    if mcc > nbrs.cell_capacity:
        msgs.append(f"cell_capacity={nbrs.cell_capacity} is too small: a grid cell holds "
                    f"{mcc} triangles; increase cell_capacity to at least {mcc}")
    if not msgs:
        msgs.append("the neighbour list overflowed (flag set)")
    raise NeighbourListOverflow("contact neighbour list overflow: " + "; ".join(msgs)
                                + " (or use build_neighbours_checked)")


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


def build_neighbours_checked(x, triangles, body, cutoff, capacity: int | None = None,
                             cell_capacity: int = DEFAULT_CELL_CAPACITY,
                             max_tries: int = 12) -> NeighbourList:
    """Host-side `build_neighbours` that retries, doubling whichever capacity overflowed
    (at least up to the count found, rounded up to a power of two), until nothing is
    dropped; raises `NeighbourListOverflow` after `max_tries`.  Not jit-compatible."""
    x_np = np.asarray(x)
    if not np.all(np.isfinite(x_np)):
        raise ParameterError("x holds non-finite positions; contact needs finite coordinates")
    if not float(cutoff) > 0:
        raise ParameterError(f"cutoff must be > 0 mm; got {cutoff}")
    if capacity is None:
        capacity = default_capacity(x_np.shape[0])
    capacity, cell_capacity = int(capacity), int(cell_capacity)
    for _ in range(max_tries):
        nbrs = build_neighbours(x, triangles, body, cutoff, capacity, cell_capacity)
        if not bool(nbrs.overflow):
            return nbrs
        # grow to powers of two: few distinct static shapes, so few recompilations
        if int(nbrs.count) > capacity:
            capacity = _next_pow2(max(2 * capacity, int(nbrs.count)))
        if int(nbrs.max_cell_count) > cell_capacity:
            cell_capacity = _next_pow2(max(2 * cell_capacity, int(nbrs.max_cell_count)))
    check_overflow(nbrs)
    return nbrs


def brute_force_pairs(x, triangles, body, cutoff):
    """NumPy reference (tests only): set of (node, triangle) pairs of different bodies
    whose exact point-triangle distance is < cutoff.  O(N * M)."""
    x = np.asarray(x, dtype=np.float64)
    tri = np.asarray(triangles)
    body = np.asarray(body)
    n, m = x.shape[0], tri.shape[0]
    ii, tt = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    ii, tt = ii.ravel(), tt.ravel()
    keep = body[ii] != body[tri[tt, 0]]
    ii, tt = ii[keep], tt[keep]
    d = point_triangle_distance_np(x[ii], x[tri[tt, 0]], x[tri[tt, 1]], x[tri[tt, 2]])
    sel = d < cutoff
    return set(zip(ii[sel].tolist(), tt[sel].tolist()))
