"""Fixed-capacity broad phase: candidate (node, triangle) contact pairs between bodies.

Shapes: ``x`` (N, 3) node positions (mm), ``triangles`` (M, 3) int32, ``body`` (N,) int32
with values in [0, n_bodies).  The body of a triangle is the body of its vertex 0.  A pair
(i, T) is a *candidate* when body[i] != body[T] and node i lies within ``cutoff`` of the
bounding sphere of T (centre the barycentre r_T, radius R_T = max_k |x_k - r_T|), i.e.
|x_i - r_T| < cutoff + R_T.  This is conservative: every pair with point-triangle distance
< cutoff is a candidate, and so is every pair with |x_i - r_T| < cutoff (the vicinity test
of the paper's law).

Layout ("chunked dense").  Candidates are grouped by (node i, body B of T): the smooth law
needs the nearest triangle of each group.  Each group occupies one or more consecutive
*rows* of ``ROW_WIDTH`` (8) triangle slots; groups are numbered 0, 1, ... in (node, body)
order and rows [0, ``n_rows``) hold them all.  ``cand`` (R, ROW_WIDTH) holds triangle ids
(padding: M); ``row_group`` (R,) the group of each row; ``group_node`` (R,) the node of
each group (padding: N); ``group_row`` (R,) the first row of each group.  A per-row
reduction is a dense reduction over the minor axis (no scatter), and consumers loop over
the rows in use only (`smooth.nearest_triangles`), so their cost follows the pairs found,
not the capacity.  ``capacity`` = R * ROW_WIDTH pair slots; `pairs`, `group` and `valid`
give the previous flat (capacity, ...) view.

Algorithm (O(N + M) work apart from sorting M keys; never N x M):

1. a grid of cells h (y, z) by h / 4 (x), h >= cutoff + max_T R_T (coarser if the
   ``grid_size`` table would not hold n_bodies x cells); triangles are sorted by the key
   (body, cell) and a table of the first sorted triangle of every key is built (a scan
   over ``grid_size`` entries), so the triangles of one body in x-consecutive cells form
   one contiguous run;
2. every (node, other body) group reads 9 runs (y, z offsets in {-1, 0, 1}^2, x cells
   meeting [x_i - h, x_i + h]) from the table, and its scan length L;
3. the groups' scans are laid out in rows of ``SCAN_WIDTH`` (32) slots, ceil(L / 32) rows
   a group (``scan_capacity`` slots in all); the rows in use are visited SCAN_CHUNK at a
   time in a loop with a dynamic trip count, each slot testing the bounding sphere
   (structure-of-arrays, fused elementwise code) into a 32-bit mask per row;
4. compaction into the row layout: popcounts and small scans over groups give each
   accepted slot its rank in its group and its row; a second loop writes the ids.

Capacities are static Python ints.  Overflow is never silent: ``overflow`` is set when the
rows needed exceed the capacity (``count`` says how many pair slots are needed), when the
scan needed more than ``scan_capacity`` slots (``n_scan``), or when a group holds more than
``MAX_GROUP`` candidates (``max_group_count``).  Check on the host with `check_overflow`,
or build with `build_neighbours_checked`, which retries with larger capacities.  By
default ``scan_capacity`` = ``DEFAULT_SCAN_RATIO`` x ``capacity``, so a retry at a larger
``capacity`` also grows the scan.

Verlet skin: build with ``cutoff = interaction range + skin``; the list stays valid while
no node has moved more than skin / 2 since the build (`needs_rebuild`, `update`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import threading

import numpy as np
import jax
import jax.numpy as jnp

from ..vmap_control import batch_any, batch_max, cond_each
from ..errors import NeighbourListOverflow, ParameterError
from .geometry import point_triangle_distance_np
from ..quick_jit import quick_jit

__all__ = [
    "NeighbourList",
    "build_neighbours",
    "build_neighbours_checked",
    "needs_rebuild",
    "update",
    "check_overflow",
    "default_capacity",
    "default_scan_capacity",
    "default_grid_size",
    "bucket_sizes",
    "bucket_index",
    "DEFAULT_CELL_CAPACITY",
    "DEFAULT_SCAN_RATIO",
    "ROW_WIDTH",
    "SCAN_WIDTH",
    "MAX_GROUP",
    "brute_force_pairs",
    "triangle_body",
]

ROW_WIDTH = 8          # triangle slots per row of the pair list
SCAN_WIDTH = 32        # slots per row of the grid scan (bits of one uint32 mask)
SCAN_CHUNK = 256       # scan rows per loop iteration of the build
SLOT_BITS = 10         # a group's candidates are numbered in SLOT_BITS bits (contact keys)
MAX_GROUP = 1 << SLOT_BITS  # most candidates of one (node, body) group
DEFAULT_SCAN_RATIO = 8  # default scan_capacity / capacity
DEFAULT_CELL_CAPACITY = DEFAULT_SCAN_RATIO  # legacy name (exported by jaxvalve.contact)

_RUNS = [(dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1)]  # 9 (y, z) neighbour offsets


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["cand", "row_group", "group_node", "group_row", "x_build", "cutoff",
                 "overflow", "count", "n_rows", "n_pairs", "n_scan", "max_group_count"],
    meta_fields=["capacity", "scan_capacity", "n_bodies", "grid_size", "n_triangles"],
)
@dataclasses.dataclass(frozen=True)
class NeighbourList:
    """Candidate contact pairs in the chunked dense layout (a pytree; capacities static).

    cand:       (R, ROW_WIDTH) int32 triangle ids; padding slots hold M (= n_triangles).
    row_group:  (R,) int32 group of each row (groups numbered in (node, body) order);
                padding rows get R - 1.
    group_node: (R,) int32 node of each group; N for unused group slots.
    group_row:  (R,) int32 first row of each group.
    x_build:    (N, 3) positions (mm) at the last build.
    cutoff:     () float, candidate radius used (mm).
    overflow:   () bool, True if pairs were dropped (in `update`: at any rebuild).
    count:      () int32, pair slots needed (rows needed x ROW_WIDTH, >= pairs found);
                overflow when > capacity.  Sticky (max) in `update`.
    n_rows:     () int32, rows in use (min(rows needed, R)); rows [0, n_rows) hold every
                group, so consumers loop over them only.
    n_pairs:    () int32, candidate pairs found at the last build.
    n_scan:     () int32, grid-scan slots needed (overflow when > scan_capacity).
    max_group_count: () int32, most candidates in one (node, body) group.
    capacity:   R * ROW_WIDTH pair slots (static).
    scan_capacity, n_bodies, grid_size, n_triangles: static build parameters.
    """

    cand: jax.Array
    row_group: jax.Array
    group_node: jax.Array
    group_row: jax.Array
    x_build: jax.Array
    cutoff: jax.Array
    overflow: jax.Array
    count: jax.Array
    n_rows: jax.Array
    n_pairs: jax.Array
    n_scan: jax.Array
    max_group_count: jax.Array
    capacity: int
    scan_capacity: int
    n_bodies: int
    grid_size: int
    n_triangles: int

    @property
    def row_width(self) -> int:
        return self.cand.shape[1]

    @property
    def rows(self) -> int:
        return self.cand.shape[0]

    @property
    def slot_valid(self):
        """(R, ROW_WIDTH) bool mask of real (non-padding) slots."""
        return self.cand < self.n_triangles

    @property
    def valid(self):
        """(capacity,) bool mask of real (non-padding) rows of `pairs`."""
        return self.slot_valid.reshape(-1)

    @property
    def pairs(self):
        """(capacity, 2) int32 rows [node i, triangle T], grouped by (node, body of T);
        padding rows are [N, M]."""
        n = self.x_build.shape[0]
        node = jnp.broadcast_to(self.group_node[self.row_group][:, None], self.cand.shape)
        node = jnp.where(self.slot_valid, node, n)
        return jnp.stack([node.reshape(-1), self.cand.reshape(-1)], axis=1)

    @property
    def group(self):
        """(capacity,) int32 group id of each row of `pairs`; padding gets capacity - 1."""
        g = jnp.broadcast_to(self.row_group[:, None], self.cand.shape)
        return jnp.where(self.slot_valid, g, self.capacity - 1).reshape(-1)


def triangle_body(triangles, body):
    """Body (M,) of each triangle: the body of its vertex 0."""
    return body[triangles[:, 0]]


def _round_up(n: int, k: int) -> int:
    return int(-(-int(n) // k) * k)


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


_ONE_PREFIX = threading.local()


@contextlib.contextmanager
def whole_lists():
    """While tracing inside this context, `bucket_sizes` gives the whole list only: one
    branch instead of a `lax.switch` over prefixes.  For programs run at one state many
    times, such as the adjoint's products at a closed valve (`jaxvalve.solvers.tangent`), where the
    longest prefix is in use anyway and the other branches only cost compilation."""
    old = getattr(_ONE_PREFIX, "on", False)
    _ONE_PREFIX.on = True
    try:
        yield
    finally:
        _ONE_PREFIX.on = old


def bucket_sizes(n: int, smallest: int = 64, most: int = 4, factor: int = 4) -> tuple:
    """Static prefix lengths n, n/factor, n/factor^2, ... (rounded up, >= `smallest`, at
    most `most` of them): work on rows [0, used) is done on the shortest prefix that holds
    them, chosen at run time with `lax.switch` (`bucket_index`), so its cost follows the
    rows in use rather than the static capacity (within `factor`).  Only n inside
    `whole_lists`."""
    if getattr(_ONE_PREFIX, "on", False):
        return (int(n),)
    out = [int(n)]
    while len(out) < most and -(-out[-1] // factor) >= smallest:
        out.append(-(-out[-1] // factor))
    return tuple(out)


def bucket_index(sizes, used):
    """Index of the shortest prefix in `sizes` (descending) holding `used` rows.  Under
    vmap, the prefix that holds every member's rows (`vmap_control.batch_max`): a longer prefix
    gives the same values (its extra slots are padding), and the `lax.switch` it drives
    then runs one branch instead of all of them."""
    used = batch_max(used)
    return jnp.clip(jnp.sum(jnp.asarray(sizes) >= used) - 1, 0, len(sizes) - 1)


def _materialise(pred, *arrays):
    """`arrays`, computed once into memory.  XLA's CPU fusion otherwise recomputes cheap
    producers for every element of a gather that reads them (here ~10x the cost of the
    gather), and on CPU `optimization_barrier` does not prevent it; the results of a
    conditional are always materialised.  `pred` must be a traced True."""
    return jax.lax.cond(batch_any(pred), lambda a: a,
                        lambda a: jax.tree_util.tree_map(jnp.zeros_like, a), arrays)


def _cumsum(a):
    """Inclusive int32 cumsum of a 1-D array.  `lax.associative_scan` unrolls log2(n)
    levels of slices: with it the builder compiled in 3.7 s instead of 1.8 s and ran no
    faster (4.25 against 4.29 ms on the closed benchmark valve), and the builder is
    compiled in every fresh process."""
    return jnp.cumsum(a.astype(jnp.int32), dtype=jnp.int32)


def _cummax(a):
    """Inclusive running maximum of a 1-D int array (see `_cumsum`)."""
    return jax.lax.cummax(a)


def default_capacity(n_nodes: int, pairs_per_node: int = 24) -> int:
    """A starting pair capacity (slots) for a mesh of `n_nodes` nodes.

    A closed valve (3 x 1313 triangles of ~0.87 mm, cutoff = gap + 1 mm skin = 1.2 mm) has
    ~16 candidate pairs per node on average (60 % of its nodes near another leaflet, ~25
    triangles of it in range), ~19 pair slots per node with the row padding: 24 leaves
    headroom, so a closure does not overflow and restart.  The cost of the contact
    energy and of a rebuild follows the pairs in use, not the capacity, so headroom is
    cheap.  (`Valve.skin`, the median edge, gives the smaller cutoff 1.08 mm there.)
    Rounded up to a multiple of 256.
    """
    cap = max(256, int(pairs_per_node) * int(n_nodes))
    return _round_up(cap, 256)


def default_scan_capacity(capacity: int) -> int:
    """Default grid-scan slots for a pair capacity: DEFAULT_SCAN_RATIO x capacity."""
    return _round_up(max(DEFAULT_SCAN_RATIO * int(capacity), 4096), 128 * SCAN_WIDTH)


def default_grid_size(n_triangles: int, n_bodies: int = 1) -> int:
    """Default (body, cell) table size: the power of two >= max(16384, 16 M, 8192 n_bodies).
    The cells grow when the table is too small (x refinement first), so this never
    overflows; it only trades table work against scan work."""
    return _next_pow2(max(16384, 16 * int(n_triangles), 8192 * int(n_bodies)))


# ---------------------------------------------------------------------------- building
@quick_jit(static_argnames=("capacity", "scan_capacity", "n_bodies", "grid_size"))
def _build(x, triangles, body, cutoff, capacity, scan_capacity, n_bodies, grid_size):
    x = jnp.asarray(x)
    tri = jnp.asarray(triangles, dtype=jnp.int32)
    body = jnp.asarray(body, dtype=jnp.int32)
    cutoff = jnp.asarray(cutoff, dtype=x.dtype)
    n, m, nb = x.shape[0], tri.shape[0], int(n_bodies)
    W, WS = ROW_WIDTH, SCAN_WIDTH
    R, S = capacity // W, scan_capacity // WS
    G = int(grid_size)
    i32 = jnp.int32

    # bounding spheres of the triangles
    v0, v1, v2 = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    centre = (v0 + v1 + v2) / 3.0
    r2 = jnp.maximum(jnp.maximum(jnp.sum((v0 - centre) ** 2, -1),
                                 jnp.sum((v1 - centre) ** 2, -1)),
                     jnp.sum((v2 - centre) ** 2, -1))
    radius = jnp.sqrt(r2)
    tbody = jnp.clip(body[tri[:, 0]], 0, nb - 1)

    # grid: cells of h in y and z and h / f in x (f = 4, 2 or 1), h >= cutoff + max R_T;
    # the finest choice whose nb * cells fits the table, else h grown by 1.25 until it does
    h0 = (cutoff + jnp.max(radius)) * (1.0 + 1e-9) + 1e-12
    xmin, xmax = jnp.min(x, axis=0), jnp.max(x, axis=0)
    ext = xmax - xmin
    cand_f = jnp.asarray([4.0, 2.0] + [1.0] * 64, dtype=x.dtype)
    cand_h = h0 * jnp.asarray([1.0, 1.0] + [1.25 ** k for k in range(64)], dtype=x.dtype)
    dims_all = jnp.stack([jnp.floor((ext[0] + 2 * cand_h) * cand_f / cand_h) + 2,
                          jnp.floor(ext[1] / cand_h) + 4, jnp.floor(ext[2] / cand_h) + 4], 1)
    fits = nb * jnp.prod(dims_all, axis=1) + 4 <= G
    j = jnp.argmax(fits)
    h, hx = cand_h[j], cand_h[j] / cand_f[j]
    dims = jnp.clip(dims_all[j], 2, G).astype(i32)
    ncell = dims[0] * dims[1] * dims[2]
    lo = xmin - h

    def xcell(px):
        return jnp.clip(jnp.floor((px - lo[0]) / hx), 0, dims[0] - 1).astype(i32)

    def yzcells(p):
        c = jnp.floor((p[..., 1:] - lo[1:]) / h)
        return jnp.clip(c, 1, (dims[1:] - 2).astype(p.dtype)).astype(i32)

    def lin(ix, iyz):
        return ix + dims[0] * (iyz[..., 0] + dims[1] * iyz[..., 1])

    # triangles sorted by (body, cell); cs[k] = number of triangles with key < k
    tkey = tbody * ncell + lin(xcell(centre[:, 0]), yzcells(centre))
    packed = jnp.sort(tkey.astype(jnp.int64) * m + jnp.arange(m, dtype=jnp.int64))
    order = (packed % m).astype(i32)
    counts = jnp.zeros((G,), i32).at[tkey].add(1, mode="drop")
    cs = jnp.concatenate([jnp.zeros((1,), i32), _cumsum(counts)])
    cx, cy, cz = centre[order, 0], centre[order, 1], centre[order, 2]
    reach2 = ((cutoff + radius) ** 2)[order]

    # per (node, other body) group: 9 runs, (y, z) cell offsets in {-1, 0, 1}^2, each run
    # the x cells meeting [x - h, x + h] (contiguous keys).  The other bodies of node i
    # are b + (b >= body[i]), b < nb - 1, so groups come in (node, body) order.
    nbo = max(nb - 1, 1)
    ix_lo, ix_hi = xcell(x[:, 0] - h), xcell(x[:, 0] + h)
    iyz = yzcells(x)
    dyz = jnp.asarray(_RUNS, dtype=i32)                                  # (9, 2)
    row = dims[0] * ((iyz[:, 0:1] + dyz[None, :, 0]) + dims[1] * (iyz[:, 1:2] + dyz[None, :, 1]))
    ob = jnp.arange(nbo, dtype=i32)[None, :]
    ob = ob + (ob >= body[:, None])                                      # (N, nbo)
    kb = row[:, None, :] + (ob * ncell)[:, :, None]                      # (N, nbo, 9)
    k0 = jnp.clip(kb + ix_lo[:, None, None], 0, G)
    k1 = jnp.clip(kb + ix_hi[:, None, None] + 1, 0, G)
    cs, k0, k1 = _materialise(xmax[0] >= xmin[0], cs, k0, k1)
    G0 = n * nbo
    start = cs[k0].reshape(G0, 9)
    length = jnp.where((ob < nb)[:, :, None], cs[k1] - cs[k0], 0).reshape(G0, 9)
    L = jnp.sum(length, axis=1, dtype=i32)                               # (G0,)

    # scan rows: ceil(L / WS) consecutive rows per group, processed CS rows at a time
    nr = (L + WS - 1) // WS
    off = _cumsum(nr) - nr
    n_scan_rows = jnp.sum(nr, dtype=i32)
    gidx = jnp.arange(G0, dtype=i32)
    mark = jnp.zeros((S,), i32).at[jnp.where(nr > 0, off, S)].set(gidx, mode="drop")
    sg = _cummax(mark)                                            # (S,) group
    CS = min(S, SCAN_CHUNK)
    # under vmap, the batch's largest trip count (`vmap_control`): the extra trips of a member
    # visit rows past its own (no slot accepted) or redo its last chunk (same values)
    n_chunks = batch_max(((jnp.minimum(n_scan_rows, S) + CS - 1) // CS).astype(i32))
    lane = jnp.arange(WS, dtype=i32)
    ulane = lane.astype(jnp.uint32)
    one = jnp.ones((), jnp.uint32)

    def chunk(i):
        """Scan rows [r0, r0 + CS): their groups, valid slots and sorted positions."""
        r0 = jnp.minimum(i * CS, S - CS).astype(i32)
        srow = r0 + jnp.arange(CS, dtype=i32)
        g = jax.lax.dynamic_slice(sg, (r0,), (CS,))
        st = start[g]                                                    # (CS, 9)
        ln = length[g]
        pre = [jnp.zeros_like(ln[:, 0])]                                 # run offsets
        for r in range(8):
            pre.append(pre[-1] + ln[:, r])
        jump = st[:, 1:] - st[:, :-1] - ln[:, :-1]                       # (CS, 8)
        jj = (srow - off[g])[:, None] * WS + lane[None, :]
        ok = (srow < n_scan_rows)[:, None] & (jj < L[g][:, None])
        pos = st[:, 0:1] + jj
        for r in range(1, 9):
            pos = pos + jnp.where(jj >= pre[r][:, None], jump[:, r - 1:r], 0)
        return r0, srow, g, ok, jnp.clip(pos, 0, m - 1)

    def sphere_pass(i, carry):
        words, spos = carry
        r0, srow, g, ok, pos = chunk(i)
        node = g // nbo
        ex, ey, ez = (x[:, k][node][:, None] - tdata[k][pos] for k in range(3))
        acc = ok & (ex * ex + ey * ey + ez * ez < tdata[3][pos])
        w = jnp.sum(jnp.where(acc, jnp.left_shift(one, ulane), 0).astype(jnp.uint32),
                    axis=1, dtype=jnp.uint32)
        return (jax.lax.dynamic_update_slice(words, w, (r0,)),
                jax.lax.dynamic_update_slice(spos, pos, (r0, jnp.int32(0))))

    tdata = (cx, cy, cz, reach2)
    words, spos = jax.lax.fori_loop(
        jnp.int32(0), n_chunks, sphere_pass,
        (jnp.zeros((S,), jnp.uint32), jnp.zeros((S, WS), i32)))

    # compaction: pairs per group, output rows per group, rank of each accepted slot
    a_ex = jnp.concatenate([jnp.zeros((1,), i32),
                            _cumsum(jax.lax.population_count(words).astype(i32))])
    g_lo = jnp.clip(off, 0, S)
    n_g = a_ex[jnp.clip(off + nr, 0, S)] - a_ex[g_lo]                    # (G0,)
    orows = (n_g + W - 1) // W
    oo = _cumsum(orows) - orows                            # first row
    rows = jnp.sum(orows, dtype=i32)
    has = n_g > 0
    gid = _cumsum(has) - has
    dst = jnp.where(has, gid, R)
    group_node = jnp.full((R,), n, i32).at[dst].set(gidx // nbo, mode="drop")
    group_row = jnp.zeros((R,), i32).at[dst].set(oo, mode="drop")
    rmark = jnp.zeros((R,), i32).at[jnp.where(has, oo, R)].set(gid, mode="drop")
    row_group = jnp.where(jnp.arange(R) < rows, _cummax(rmark), R - 1)
    low = jnp.left_shift(one, ulane) - one                               # bits below k

    def write_pass(i, flat):
        r0 = jnp.minimum(i * CS, S - CS).astype(i32)
        srow = r0 + jnp.arange(CS, dtype=i32)
        g = jax.lax.dynamic_slice(sg, (r0,), (CS,))
        pos = jax.lax.dynamic_slice(spos, (r0, jnp.int32(0)), (CS, WS))
        w = jax.lax.dynamic_slice(words, (r0,), (CS,))[:, None]
        acc = (jnp.right_shift(w, ulane[None, :]) & one) == one
        rank = ((a_ex[srow] - a_ex[g_lo[g]])[:, None]
                + jax.lax.population_count(w & low[None, :]).astype(i32))
        dest = jnp.where(acc, oo[g][:, None] * W + rank, R * W)
        return flat.at[dest.reshape(-1)].set(pos.reshape(-1), mode="drop")

    cand_pos = jax.lax.fori_loop(jnp.int32(0), n_chunks, write_pass,
                                 jnp.full((R * W,), m, i32)).reshape(R, W)
    order_ext = jnp.concatenate([order, jnp.full((1,), m, i32)])
    cand = order_ext[cand_pos]
    n_pairs = jnp.sum(n_g, dtype=i32)
    max_g = jnp.max(n_g).astype(i32)

    count = rows * W
    n_scan = n_scan_rows * WS
    overflow = (count > capacity) | (n_scan > scan_capacity) | (max_g > MAX_GROUP)
    return NeighbourList(
        cand=cand, row_group=row_group, group_node=group_node, group_row=group_row,
        x_build=x, cutoff=cutoff, overflow=overflow, count=count,
        n_rows=jnp.minimum(rows, R).astype(i32), n_pairs=n_pairs,
        n_scan=n_scan, max_group_count=max_g, capacity=int(capacity),
        scan_capacity=int(scan_capacity), n_bodies=nb, grid_size=G, n_triangles=m)


def _static_n_bodies(body, n_bodies):
    if n_bodies is not None:
        return int(n_bodies)
    if isinstance(body, jax.core.Tracer):
        raise ParameterError("n_bodies must be given when body is traced (under jit, pass "
                             "n_bodies=int(body.max()) + 1 computed outside)")
    return int(np.max(np.asarray(body))) + 1 if np.size(body) else 1


def build_neighbours(x, triangles, body, cutoff, capacity: int,
                     scan_capacity: int | None = None, *, n_bodies: int | None = None,
                     grid_size: int | None = None) -> NeighbourList:
    """Build a `NeighbourList` of candidate pairs within `cutoff` (mm). Jit-compatible.

    capacity: pair slots (rounded up to a multiple of ROW_WIDTH); scan_capacity: grid-scan
    slots (default `default_scan_capacity`); n_bodies: number of bodies (default from
    `body`, which must then be concrete); grid_size: (body, cell) table entries (default
    `default_grid_size`).  All static.
    """
    m = int(np.shape(triangles)[0])
    if m == 0:
        raise ParameterError("triangles is empty; contact needs at least one triangle")
    capacity = _round_up(max(int(capacity), ROW_WIDTH), ROW_WIDTH)
    scan_capacity = (default_scan_capacity(capacity) if scan_capacity is None
                     else _round_up(max(int(scan_capacity), SCAN_WIDTH), 128 * SCAN_WIDTH))
    nb = _static_n_bodies(body, n_bodies)
    grid_size = default_grid_size(m, nb) if grid_size is None else int(grid_size)
    grid_size = max(grid_size, 64 * nb + 8)
    return _build(x, triangles, body, cutoff, capacity, scan_capacity, nb, grid_size)


def filled(shape, value, dtype) -> jax.Array:
    """An array of ``shape`` full of ``value``, made on the host and put on the device:
    `jnp.full` would trace and compile a program for each new shape (the empty lists of
    each mesh: 14 s of the test suite's Python time, in a profile of the suite)."""
    return jnp.asarray(np.full(shape, value, np.dtype(dtype)), dtype=dtype)


def stale_list(n_nodes: int, triangles, body, cutoff, capacity: int | None = None,
               dtype=jnp.float64) -> NeighbourList:
    """An empty list with the capacities `build_neighbours` would use, that `update`
    rebuilds at its first call (its build positions are +inf).  A solve that calls
    `update` before its first force evaluation can start from it: the builder is then
    compiled once, inside the solve, instead of once more for a build on the host."""
    m = int(np.shape(triangles)[0])
    if m == 0:
        raise ParameterError("triangles is empty; contact needs at least one triangle")
    nb = _static_n_bodies(body, None)
    capacity = _round_up(max(int(capacity or default_capacity(n_nodes)), ROW_WIDTH), ROW_WIDTH)
    R = capacity // ROW_WIDTH
    i32 = np.int32
    zero = filled((), 0, i32)
    return NeighbourList(
        cand=filled((R, ROW_WIDTH), m, i32), row_group=filled((R,), R - 1, i32),
        group_node=filled((R,), n_nodes, i32), group_row=filled((R,), 0, i32),
        x_build=filled((n_nodes, 3), np.inf, dtype), cutoff=jnp.asarray(cutoff, dtype),
        overflow=filled((), False, bool), count=zero, n_rows=zero, n_pairs=zero, n_scan=zero,
        max_group_count=zero, capacity=capacity,
        scan_capacity=default_scan_capacity(capacity), n_bodies=nb,
        grid_size=max(default_grid_size(m, nb), 64 * nb + 8), n_triangles=m)


def needs_rebuild(nbrs: NeighbourList, x, skin):
    """True () if some node moved more than skin / 2 (mm) since the list was built."""
    d2 = jnp.sum((x - nbrs.x_build) ** 2, axis=-1)
    return jnp.max(d2) > (0.5 * skin) ** 2


def update(nbrs: NeighbourList, x, triangles, body, skin) -> NeighbourList:
    """Rebuild (same cutoff and capacities) under `lax.cond` when `needs_rebuild` (under
    vmap: only for the members that need it, `vmap_control.cond_each`).

    Usable inside `lax.while_loop`.  ``overflow``, ``count``, ``n_scan`` and
    ``max_group_count`` are sticky (or / max over all rebuilds), so one host-side
    `check_overflow` after a solve tells whether any list along the way dropped pairs.
    """
    def rebuild(old, x, triangles, body):
        new = _build(x, triangles, body, old.cutoff, old.capacity, old.scan_capacity,
                     old.n_bodies, old.grid_size)
        return dataclasses.replace(
            new,
            overflow=new.overflow | old.overflow,
            count=jnp.maximum(new.count, old.count),
            n_scan=jnp.maximum(new.n_scan, old.n_scan),
            max_group_count=jnp.maximum(new.max_group_count, old.max_group_count),
        )

    return cond_each(needs_rebuild(nbrs, x, skin), rebuild, lambda old, *_: old, nbrs, x,
                     triangles, body)


def check_overflow(nbrs: NeighbourList) -> None:
    """Host-side: raise `NeighbourListOverflow` naming the capacity to increase."""
    if not bool(nbrs.overflow):
        return
    msgs = []
    count, n_scan, mg = int(nbrs.count), int(nbrs.n_scan), int(nbrs.max_group_count)
    if count > nbrs.capacity:
        msgs.append(f"capacity={nbrs.capacity} is too small: the pair list needs {count} "
                    f"slots ({int(nbrs.n_pairs)} candidate pairs found); increase capacity "
                    f"to at least {count}")
    if n_scan > nbrs.scan_capacity:
        msgs.append(f"scan_capacity={nbrs.scan_capacity} is too small: the grid scan needs "
                    f"{n_scan} slots; increase scan_capacity to at least {n_scan}")
    if mg > MAX_GROUP:
        msgs.append(f"a node has {mg} candidate triangles of one other body, more than "
                    f"MAX_GROUP={MAX_GROUP}: reduce the cutoff (skin)")
    if not msgs:
        msgs.append("the neighbour list overflowed (flag set)")
    raise NeighbourListOverflow("contact neighbour list overflow: " + "; ".join(msgs)
                                + " (or use build_neighbours_checked)")


def build_neighbours_checked(x, triangles, body, cutoff, capacity: int | None = None,
                             scan_capacity: int | None = None, max_tries: int = 12, *,
                             grid_size: int | None = None) -> NeighbourList:
    """Host-side `build_neighbours` that retries, doubling whichever capacity overflowed
    (at least up to the count found, rounded up to a power of two), until nothing is
    dropped; raises `NeighbourListOverflow` after `max_tries` (or at once when a group
    exceeds MAX_GROUP, which no capacity fixes).  Not jit-compatible."""
    x_np = np.asarray(x)
    if not np.all(np.isfinite(x_np)):
        raise ParameterError("x holds non-finite positions; contact needs finite coordinates")
    if not float(cutoff) > 0:
        raise ParameterError(f"cutoff must be > 0 mm; got {cutoff}")
    body_np = np.asarray(body)
    if body_np.size and body_np.min() < 0:
        raise ParameterError(f"body ids must be >= 0; got {body_np.min()}")
    n_bodies = int(body_np.max()) + 1 if body_np.size else 1
    if capacity is None:
        capacity = default_capacity(x_np.shape[0])
    capacity = int(capacity)
    scan = None if scan_capacity is None else int(scan_capacity)
    for _ in range(max_tries):
        nbrs = build_neighbours(x, triangles, body, cutoff, capacity, scan,
                                n_bodies=n_bodies, grid_size=grid_size)
        if not bool(nbrs.overflow):
            return nbrs
        if int(nbrs.max_group_count) > MAX_GROUP:
            break
        # grow to powers of two: few distinct static shapes, so few recompilations
        if int(nbrs.count) > nbrs.capacity:
            capacity = _next_pow2(max(2 * nbrs.capacity, int(nbrs.count)))
        if int(nbrs.n_scan) > nbrs.scan_capacity:
            scan = _next_pow2(max(2 * nbrs.scan_capacity, int(nbrs.n_scan)))
        elif scan is not None:
            scan = max(scan, default_scan_capacity(capacity))
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
