"""In-jit broad phase: every pair of balls closer than a cutoff, on a sorted grid.

`ball_pairs(qc, qr, tc, tr, cutoff, ...)` lists the pairs (query i, target j) with
|qc_i - tc_j| < qr_i + tr_j + cutoff (and an optional test of the caller's), inside jit,
in arrays of fixed size, for the barrier's pair lists (`jaxvalve.contact.pairs`: nodes
against triangle balls, edge balls against each other).  Work follows the candidates,
never Q x T:

1. Cells of h = max(qr + cutoff) + max(tr) in y and z and h / 4 in x (coarser where the
   static ``table`` would not hold the grid); targets sorted by cell key, and a table of
   the first sorted target of every key.
2. Each query reads 9 runs of consecutive keys (the (y, z) cells around it, each across
   the x cells within h), so its candidates are 9 contiguous slices of the sorted targets.
3. The candidates are laid out in scan rows of 32 slots and tested a chunk of rows at a
   time, in a loop whose trip count is the number of rows in use; each row's hits become
   one 32-bit word.
4. `compact_words` turns the words into the list: output slot k finds its row from the
   running count of hits and its lane by a binary search over the word's bits, so the
   cost follows the hits, not the slots scanned (XLA's CPU scatter costs every slot).

Capacities are static; overflow is reported, never silent: ``count`` > capacity (pairs
dropped) or ``rows`` > scan_rows (candidates not tested).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ..unvmap import unvmap_max

__all__ = ["ball_pairs", "compact_words", "words_of", "SCAN_WIDTH"]

SCAN_WIDTH = 32          # slots per scan row: the bits of one uint32 word
_CHUNK = 256             # scan rows per loop trip
_RUNS = [(dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1)]
_LANES = jnp.arange(SCAN_WIDTH, dtype=jnp.uint32)


def _cumsum(a):
    return jnp.cumsum(a.astype(jnp.int32), dtype=jnp.int32)


def words_of(mask):
    """(R,) uint32 words of a boolean mask (R, 32): bit k set where mask[:, k]."""
    bits = jnp.left_shift(jnp.uint32(1), _LANES)
    return jnp.sum(jnp.where(mask, bits, 0).astype(jnp.uint32), -1, dtype=jnp.uint32)


def _select_bit(w, k):
    """The lane (int32) of the k-th set bit (k from 0) of the words w (uint32), by
    binary search over bit ranges."""
    lo = jnp.zeros(w.shape, jnp.uint32)
    k = k.astype(jnp.uint32)
    for b in (16, 8, 4, 2, 1):
        span = jnp.left_shift(jnp.uint32((1 << b) - 1), lo)
        c = jax.lax.population_count(w & span)
        go = k >= c
        k = jnp.where(go, k - c, k)
        lo = jnp.where(go, lo + b, lo)
    return lo.astype(jnp.int32)


def compact_words(words, capacity: int):
    """(row (capacity,) int32, lane (capacity,) int32, count () int32) of the set bits
    of words (R,) uint32, in row-major order; slots past count hold row -1."""
    i32 = jnp.int32
    pc = jax.lax.population_count(words).astype(i32)
    before = _cumsum(pc) - pc
    count = jnp.sum(pc, dtype=i32)
    # each row with hits marks the output slot of its first hit; the running count of
    # marks gives every output slot its place among the rows with hits
    has = pc > 0
    nonempty = jnp.zeros((words.shape[0],), i32).at[jnp.where(has, _cumsum(has) - 1,
                                                              words.shape[0])].set(
        jnp.arange(words.shape[0], dtype=i32), mode="drop")
    mark = jnp.zeros((capacity,), i32).at[jnp.where(has, before, capacity)].add(1, mode="drop")
    row = nonempty[jnp.maximum(_cumsum(mark) - 1, 0)]
    k = jnp.arange(capacity, dtype=i32)
    lane = _select_bit(words[row], k - before[row])
    ok = k < count
    return jnp.where(ok, row, -1), jnp.where(ok, lane, 0), count


def _grid(points, h0, table):
    """(cell size h in y, z; in x; dims (3,) int32; lower corner (3,)): the finest of x
    cells h0 / 4, h0 / 2, h0 whose grid fits ``table`` keys, else h0 grown by 1.25 until
    it does."""
    lo, hi = jnp.min(points, 0), jnp.max(points, 0)
    ext = hi - lo
    f = jnp.asarray([4.0, 2.0] + [1.0] * 48, points.dtype)
    hh = h0 * jnp.asarray([1.0, 1.0] + [1.25 ** k for k in range(48)], points.dtype)
    dims = jnp.stack([jnp.floor((ext[0] + 2 * hh) * f / hh) + 2,
                      jnp.floor(ext[1] / hh) + 4, jnp.floor(ext[2] / hh) + 4], 1)
    k = jnp.argmax(jnp.prod(dims, 1) + 2 <= table)
    return hh[k], hh[k] / f[k], dims[k].astype(jnp.int32), lo - hh[k]


def ball_pairs(qc, qr, tc, tr, cutoff, *, capacity: int, scan_rows: int, table: int,
               self_pairs: bool = False, accept=None):
    """Pairs of query balls (centres qc (Q, 3) mm, radii qr (Q,)) and target balls (tc
    (T, 3), tr (T,)) with |qc_i - tc_j| < qr_i + tr_j + cutoff.  self_pairs: the queries
    are the targets, and only i < j is listed.  accept(i (C,), j (C, 32)) -> bool (C, 32):
    a further test of the caller's on candidate pairs (e.g. leaflet ids), applied before
    the list is written.

    Returns (pairs (capacity, 2) int32 [i, j], in no particular order, rows past count
    -1; count () int32, the pairs found; rows () int32, the scan rows needed).  Pairs past
    ``capacity`` are dropped (count > capacity) and candidates past ``scan_rows`` rows
    are not tested (rows > scan_rows): both are the caller's overflow.  For use inside
    jit (capacity, scan_rows, table, self_pairs and accept static)."""
    i32 = jnp.int32
    nq, nt = qc.shape[0], tc.shape[0]
    S = scan_rows
    reach = qr + cutoff
    h0 = (jnp.max(reach) + jnp.max(tr)) * (1.0 + 1e-9) + 1e-12
    h, hx, dims, lo = _grid(jnp.concatenate([qc, tc]), h0, table)

    def xcell(px):
        return jnp.clip(jnp.floor((px - lo[0]) / hx), 0, dims[0] - 1).astype(i32)

    def yzcell(p):
        c = jnp.floor((p[:, 1:] - lo[1:]) / h)
        return jnp.clip(c, 1, (dims[1:] - 2).astype(p.dtype)).astype(i32)

    # targets sorted by cell key; cs[k] = number of targets with key < k
    tyz = yzcell(tc)
    tkey = xcell(tc[:, 0]) + dims[0] * (tyz[:, 0] + dims[1] * tyz[:, 1])
    order = jnp.argsort(tkey).astype(i32)
    tkey_sorted = tkey[order]
    counts = jnp.zeros((table,), i32).at[tkey].add(1)
    cs = jnp.concatenate([jnp.zeros((1,), i32), _cumsum(counts)])
    tx, ty, tz, trs = tc[order, 0], tc[order, 1], tc[order, 2], tr[order]

    # 9 runs per query: its (y, z) neighbour columns, x cells within h.  Slot jj of a
    # query is sorted position start_0 + jj plus the jumps of the runs it has passed
    qyz = yzcell(qc)
    off = jnp.asarray(_RUNS, i32)
    col = dims[0] * ((qyz[:, None, 0] + off[None, :, 0])
                     + dims[1] * (qyz[:, None, 1] + off[None, :, 1]))
    x_lo = xcell(qc[:, 0] - h)[:, None]
    if self_pairs:
        # each pair once: from the query whose cell key is lower (or, in one cell, whose
        # index is lower), so a query scans the columns above its own (dz, dy) and its
        # own column from its own cell up
        above = jnp.asarray([(dz, dy) > (0, 0) for dy, dz in _RUNS])
        own = jnp.asarray([(dz, dy) == (0, 0) for dy, dz in _RUNS])
        qcell = xcell(qc[:, 0])[:, None]
        x_lo = jnp.where(own, qcell, x_lo)
    start = cs[col + x_lo]                                              # (Q, 9)
    length = cs[col + xcell(qc[:, 0] + h)[:, None] + 1] - start
    if self_pairs:
        length = jnp.where(above | own, length, 0)
    L = jnp.sum(length, 1)
    pre = jnp.cumsum(length, axis=1, dtype=i32) - length
    jump = start[:, 1:] - start[:, :-1] - length[:, :-1]                 # (Q, 8)
    nr = (L + SCAN_WIDTH - 1) // SCAN_WIDTH
    first = _cumsum(nr) - nr                                            # first scan row
    rows = jnp.sum(nr)
    mark = jnp.zeros((S,), i32).at[jnp.where(nr > 0, first, S)].set(
        jnp.arange(nq, dtype=i32), mode="drop")
    row_query = jax.lax.cummax(mark)
    CS = min(S, _CHUNK)
    trips = unvmap_max(((jnp.minimum(rows, S) + CS - 1) // CS).astype(i32))
    lane = jnp.arange(SCAN_WIDTH, dtype=i32)

    def slots(r0, q):
        srow = r0 + jnp.arange(CS, dtype=i32)
        jj = (srow - first[q])[:, None] * SCAN_WIDTH + lane
        ok = (srow < rows)[:, None] & (jj < L[q][:, None])
        pq, jq = pre[q], jump[q]
        pos = start[q, 0][:, None] + jj
        for r in range(1, 9):
            pos = pos + jnp.where(jj >= pq[:, r:r + 1], jq[:, r - 1:r], 0)
        return ok, jnp.clip(pos, 0, nt - 1).astype(i32)

    qkey = tkey if self_pairs else None

    def test(i, carry):
        words, where = carry
        r0 = jnp.minimum(i * CS, S - CS).astype(i32)
        q = jax.lax.dynamic_slice(row_query, (r0,), (CS,))
        ok, pos = slots(r0, q)
        dx = qc[q, 0][:, None] - tx[pos]
        dy = qc[q, 1][:, None] - ty[pos]
        dz = qc[q, 2][:, None] - tz[pos]
        hit = ok & (dx * dx + dy * dy + dz * dz < (reach[q][:, None] + trs[pos]) ** 2)
        t = order[pos]
        if self_pairs:
            hit = hit & ((tkey_sorted[pos] != qkey[q][:, None]) | (t > q[:, None]))
        if accept is not None:
            hit = hit & accept(q, t)
        return (jax.lax.dynamic_update_slice(words, words_of(hit), (r0,)),
                jax.lax.dynamic_update_slice(where, t, (r0, i32(0))))

    words, where = jax.lax.fori_loop(0, trips, test, (jnp.zeros((S,), jnp.uint32),
                                                      jnp.zeros((S, SCAN_WIDTH), i32)))
    row, ln, count = compact_words(words, capacity)
    r = jnp.maximum(row, 0)
    i, j = row_query[r], where[r, ln]
    if self_pairs:                     # listed as (lower index, higher index)
        i, j = jnp.minimum(i, j), jnp.maximum(i, j)
    out = jnp.where((row >= 0)[:, None], jnp.stack([i, j], 1), -1)
    return out, count, rows
