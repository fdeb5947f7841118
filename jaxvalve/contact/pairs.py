"""The barrier's pair lists inside jit: build, prune, update, overflow.

A `PairList` holds every point-triangle row [p, t0, t1, t2] and edge-edge row
[a0, a1, b0, b1] closer than its cutoff at the state it was built at, in fixed-capacity
arrays (jax-md's neighbour lists: capacities are static, overflow is a flag the host reads
after the solve and answers by growing the capacity).  The pairs are those of different
leaflets and those of one leaflet that share no node and lie at least ``self_gap`` apart
in the flat template (self-contact, as in IPC); pairs whose nodes are all sutured, and
pairs across a commissure pin (neighbouring leaflets sewn to one point, in contact by
construction), are never listed (`ContactTopology`).

Two levels keep a step's contact cheap (`Lists`):

* the *candidates*, every pair within d_hat + skin, rebuilt by the grid broad phase
  (`jaxvalve.contact.grid`) once a node has moved (skin - margin) / 2 since their build;
* the *active* pairs, those of the candidates within d_hat + margin, re-selected once a
  node has moved margin / 2 since their selection; the barrier is evaluated on them only.

`update` brings both up to date at a state before its forces are evaluated, so every pair
closer than d_hat there is active.  A solver step from such a state cannot close a pair
that is not active if no node moves more than `Lists.step_cap`; the active pairs limit
their own nodes' moves (`jaxvalve.solvers.fire`).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ..errors import NeighbourListOverflow, ParameterError
from ..geometry.mesh import unique_edges
from ..unvmap import unvmap_any, unvmap_max
from .grid import SCAN_WIDTH, ball_pairs, compact_words, words_of
from .ipc_distance import edge_edge_params, point_triangle_weights

__all__ = ["ContactTopology", "PairList", "Lists", "Capacities", "contact_topology",
           "build", "prune", "start", "stale", "allocate", "update", "overflow_flag", "overflowed",
           "check_overflow", "pt_distance2", "ee_distance2", "SELF_GAP", "min_distance"]

#: mm; elements of one leaflet whose template balls come closer than this are never a
#: contact pair (d_hat + skin of the benchmark's lists: nearer self pairs are neighbours
#: within the sheet, and a crease between them is held by the hinge's fold barrier,
#: `jaxvalve.mechanics.bending.fold_barrier`)
SELF_GAP = 1.2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ContactTopology:
    """Static data of a membrane's contact (arrays; built once per mesh on the host).

    triangles (M, 3), edges (E, 2), tri_edge (M, 3) (the edge row of each triangle's edge
    k, opposite vertex k).  For nodes, triangles and edges alike (``node_*``, ``tri_*``,
    ``edge_*``): the leaflet id, the commissure pin the element is sewn to (-1: none; an
    element touches at most one) and whether all its nodes are sutured.  self_gap (mm,
    static): elements of one leaflet whose template balls come closer than this are
    neighbours within the sheet, never contact.  edge_len (mm, static): the edges' mean
    length at the state the topology was built from, the scale of the pair lists'
    capacities (`Capacities.for_mesh`)."""

    triangles: Any
    edges: Any
    tri_edge: Any
    node_body: Any
    node_pin: Any
    node_fixed: Any
    tri_body: Any
    tri_pin: Any
    tri_fixed: Any
    edge_body: Any
    edge_pin: Any
    edge_fixed: Any
    edge_len: float = dataclasses.field(metadata=dict(static=True))
    self_gap: float = dataclasses.field(default=SELF_GAP, metadata=dict(static=True))

    @property
    def n_edges(self) -> int:
        return self.edges.shape[0]


def commissure_pins(body, fixed, x0, pin_tol: float = 1e-9):
    """(N,) int64, on the host: the commissure pin of each node (-1: none), where sutured
    nodes (fixed (N,) bool) of different bodies (N,) coincide within pin_tol mm at x0."""
    pin = np.full(body.shape[0], -1, np.int64)
    idx = np.flatnonzero(fixed)
    if idx.size:
        close = cKDTree(x0[idx]).query_pairs(pin_tol, output_type="ndarray")
        close = close[body[idx[close[:, 0]]] != body[idx[close[:, 1]]]]
        for k, (i, j) in enumerate(close):
            a, b = idx[i], idx[j]
            p = max(pin[a], pin[b])
            pin[a] = pin[b] = k if p < 0 else p
    return pin


def contact_topology(triangles, body, fixed, x0, pin_tol: float = 1e-9,
                     self_gap: float = SELF_GAP) -> ContactTopology:
    """`ContactTopology` of a membrane of several bodies: triangles (M, 3), body (N,),
    fixed (N,) bool and the start state x0 (N, 3) mm, where sutured nodes of different
    bodies that coincide (within pin_tol mm) are pinned together (a commissure)."""
    if not (np.isfinite(self_gap) and self_gap > 0):
        raise ParameterError(f"self_gap must be a positive length (mm); got {self_gap!r}")
    tri = np.asarray(triangles, np.int64)
    body = np.asarray(body, np.int64)
    fixed = np.asarray(fixed, bool)
    x0 = np.asarray(x0, float)
    edges, tri_edge = unique_edges(tri)
    pin = commissure_pins(body, fixed, x0, pin_tol)

    def element(rows):
        p = pin[rows]
        top = p.max(axis=1)
        if np.any((p >= 0) & (p != top[:, None])):
            raise ParameterError("an element touches two commissure pins; refine the mesh")
        return body[rows[:, 0]], top, np.all(fixed[rows], axis=1)

    edge_len = (float(np.mean(np.linalg.norm(x0[edges[:, 0]] - x0[edges[:, 1]], axis=1)))
                if len(edges) else 1.0)
    if not (np.isfinite(edge_len) and edge_len > 0):
        raise ParameterError(f"x0 gives the mesh's edges a mean length of {edge_len!r} mm; it "
                             "must be finite and > 0 (distinct, finite node positions)")
    i32 = lambda a: jnp.asarray(np.asarray(a, np.int32))
    tb, tp, tf = element(tri)
    eb, ep, ef = element(edges)
    return ContactTopology(triangles=i32(tri), edges=i32(edges), tri_edge=i32(tri_edge),
                           node_body=i32(body), node_pin=i32(pin),
                           node_fixed=jnp.asarray(fixed), tri_body=i32(tb), tri_pin=i32(tp),
                           tri_fixed=jnp.asarray(tf), edge_body=i32(eb), edge_pin=i32(ep),
                           edge_fixed=jnp.asarray(ef), self_gap=float(self_gap),
                           edge_len=edge_len)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PairList:
    """Pairs within ``cutoff`` (mm) of the state ``x_build`` (N, 3) mm.

    pt (P, 4) int32 rows [p, t0, t1, t2]; ee (Q, 4) int32 rows [a0, a1, b0, b1] and ee_id
    (Q, 2) their edges' rows in the topology; rows past n_pt, n_ee () are padding.
    need (4,) int32: the most [pt rows, ee rows, pt scan rows, ee scan rows] any build or
    prune of this list needed (sticky), to size a list that overflowed."""

    pt: Any
    n_pt: Any
    ee: Any
    ee_id: Any
    n_ee: Any
    x_build: Any
    cutoff: Any
    need: Any

    @property
    def pt_valid(self):
        return jnp.arange(self.pt.shape[0]) < self.n_pt

    @property
    def ee_valid(self):
        return jnp.arange(self.ee.shape[0]) < self.n_ee


@dataclasses.dataclass(frozen=True)
class Capacities:
    """Static sizes of the two levels (rows): candidates pt, ee; their broad phase's raw
    candidates raw_pt, raw_ee and scan rows scan_pt, scan_ee; the active lists' act_pt,
    act_ee; the broad phase's grid table."""

    pt: int
    ee: int
    raw_pt: int
    raw_ee: int
    scan_pt: int
    scan_ee: int
    act_pt: int
    act_ee: int
    table: int

    @classmethod
    def for_mesh(cls, topo: ContactTopology, dhat, skin, margin) -> "Capacities":
        """Sizes for a closing valve of the mesh ``topo`` and the lists' cutoffs (mm): where
        two sheets with edges of mean length l coapt, a node meets about (c / l + 1)^2
        elements of the other within a cutoff c (dhat + skin for the candidates, dhat +
        margin for the active pairs).  The factors per node (per edge for the edge-edge
        scan) hold two sheets pressed together over their whole area (tested) and the
        benchmark valve closed, with a quarter as much again to spare; an overflow later
        grows them (`grown`)."""
        n, n_edges = topo.node_body.shape[0], int(topo.n_edges)
        cand = (float(dhat + skin) / topo.edge_len + 1.0) ** 2 * n
        act = (float(dhat + margin) / topo.edge_len + 1.0) ** 2 * n
        r = lambda v, k=512: int(-(-int(v) // k) * k)
        return cls(pt=r(5.3 * cand), ee=r(13.0 * cand), raw_pt=r(6.3 * cand),
                   raw_ee=r(17.5 * cand), scan_pt=r(1.3 * cand + 64, 256),
                   scan_ee=r(2.0 * cand / n * n_edges + 64, 256), act_pt=r(3.7 * act),
                   act_ee=r(10.0 * act),
                   table=int(2 ** np.ceil(np.log2(max(16384, 16 * topo.triangles.shape[0])))))

    def grown(self, cand_need, act_need, raw) -> "Capacities":
        """These sizes grown past the needs of the candidates ``cand_need`` (4,), the active
        pairs ``act_need`` (4,) (`PairList.need`) and the broad phase's raw counts ``raw``
        (2,): every size more than half used is grown to at least twice its need (a solve
        that overflowed starts again, and the pairs grow as the leaflets close)."""
        up = lambda have, need: have if 2 * need <= have else int(2 ** np.ceil(np.log2(
            max(2 * have, 2 * need))))
        c, a, raw = np.asarray(cand_need), np.asarray(act_need), np.asarray(raw)
        return dataclasses.replace(
            self, pt=up(self.pt, c[0]), ee=up(self.ee, c[1]), raw_pt=up(self.raw_pt, raw[0]),
            raw_ee=up(self.raw_ee, raw[1]), scan_pt=up(self.scan_pt, c[2]),
            scan_ee=up(self.scan_ee, c[3]), act_pt=up(self.act_pt, a[0]),
            act_ee=up(self.act_ee, a[1]))

    def fits(self, cand_need, act_need, raw) -> bool:
        """Whether these sizes hold the needs (as `grown`)."""
        c, a, raw = np.asarray(cand_need), np.asarray(act_need), np.asarray(raw)
        return bool(c[0] <= self.pt and c[1] <= self.ee and c[2] <= self.scan_pt
                    and c[3] <= self.scan_ee and a[0] <= self.act_pt
                    and a[1] <= self.act_ee and raw[0] <= self.raw_pt
                    and raw[1] <= self.raw_ee)


def pt_distance2(x, rows):
    """Squared distances (P,) mm^2 of point-triangle rows (P, 4) at x (N, 3)."""
    return pt_distance2_of(x[rows])


def ee_distance2(x, rows):
    """Squared distances (Q,) mm^2 of edge-edge rows (Q, 4) at x (N, 3)."""
    return ee_distance2_of(x[rows])


def pt_distance2_of(xr):
    """Squared distances (P,) mm^2 of point-triangle rows of coordinates xr (P, 4, 3)."""
    p, a, b, c = xr[:, 0], xr[:, 1], xr[:, 2], xr[:, 3]
    w = point_triangle_weights(p, a, b, c)
    r = p - (w[:, 0:1] * a + w[:, 1:2] * b + w[:, 2:3] * c)
    return jnp.sum(r * r, -1)


def ee_distance2_of(xr):
    """Squared distances (Q,) mm^2 of edge-edge rows of coordinates xr (Q, 4, 3)."""
    a0, a1, b0, b1 = xr[:, 0], xr[:, 1], xr[:, 2], xr[:, 3]
    s, t = edge_edge_params(a0, a1, b0, b1)
    r = a0 + s[:, None] * (a1 - a0) - b0 - t[:, None] * (b1 - b0)
    return jnp.sum(r * r, -1)


_BLOCK = 1024            # rows a trip of `_filter`


def _filter(items, count, keep, capacity: int):
    """(rows (capacity, k) of ``items`` (K, k) int32 for which keep(block (B, k)) holds,
    among the first ``count``, in order; how many) -- a loop over blocks of the rows in
    use, each block's kept rows packed and appended, so the cost follows ``count``."""
    K, k = items.shape
    pad = -K % _BLOCK
    items = jnp.concatenate([items, jnp.zeros((pad, k), items.dtype)]) if pad else items
    lanes = jnp.arange(_BLOCK, dtype=jnp.int32)

    def trip(b, carry):
        out, n = carry
        b0 = (b * _BLOCK).astype(jnp.int32)
        blk = jax.lax.dynamic_slice(items, (b0, jnp.int32(0)), (_BLOCK, k))
        ok = ((b0 + lanes) < count) & keep(blk)
        row, lane, m = compact_words(words_of(ok.reshape(-1, SCAN_WIDTH)), _BLOCK)
        packed = blk[jnp.maximum(row, 0) * SCAN_WIDTH + lane]
        out = jax.lax.dynamic_update_slice(out, packed, (jnp.minimum(n, capacity),
                                                         jnp.int32(0)))
        return out, n + m.astype(jnp.int32)

    trips = unvmap_max(((jnp.minimum(count, K) + _BLOCK - 1) // _BLOCK).astype(jnp.int32))
    out, n = jax.lax.fori_loop(jnp.int32(0), trips, trip, (jnp.zeros((capacity + _BLOCK, k),
                                                          items.dtype), jnp.int32(0)))
    return out[:capacity], n


@jax.jit
def _element_balls(x, rows):
    """(centres (K, 3), radii (K,)) mm of the elements rows (K, n) at x."""
    xe = x[rows]
    c = jnp.mean(xe, 1)
    return c, jnp.sqrt(jnp.max(jnp.sum((xe - c[:, None]) ** 2, -1), 1))


def _static_test(body, pin, fixed, ball, gap):
    """accept(i (C,), j (C, 32)) for a pair of element sets, each given as (body, pin,
    all-sutured, template ball (centres, radii)) arrays: not both sutured, no shared pin,
    and for one leaflet, template balls at least ``gap`` apart (`ContactTopology`)."""
    (ba, bb), (pa, pb), (fa, fb), ((ca, ra), (cb, rb)) = body, pin, fixed, ball

    def accept(i, j):
        d = ca[i][:, None, :] - cb[j]
        near = jnp.sum(d * d, -1) < (gap + ra[i][:, None] + rb[j]) ** 2
        same = ba[i][:, None] == bb[j]
        return (~(fa[i][:, None] & fb[j]) & ~((pa[i][:, None] >= 0) & (pa[i][:, None] == pb[j]))
                & ~(same & near))
    return accept


def build(topo: ContactTopology, ref, x, cutoff, caps: Capacities):
    """The candidate `PairList` within ``cutoff`` (mm) at x (N, 3) mm, with the template
    ref (N, 2|3) mm for the self-contact gap, and the broad phase's raw candidate counts
    (2,) int32 [pt, ee] (overflow where above caps.raw_pt, caps.raw_ee)."""
    ref = jax.lax.stop_gradient(ref)
    ref3 = ref if ref.shape[1] == 3 else jnp.concatenate([ref, jnp.zeros_like(ref[:, :1])], 1)
    tri, edges = topo.triangles, topo.edges
    n = x.shape[0]
    zero = jnp.zeros((n,), x.dtype)
    node_ball = (ref3, zero)
    tri_ball, edge_ball = _element_balls(ref3, tri), _element_balls(ref3, edges)
    # point-triangle: nodes against the triangles' balls, then the exact distance
    tc, tr = _element_balls(x, tri)
    accept = _static_test((topo.node_body, topo.tri_body), (topo.node_pin, topo.tri_pin),
                          (topo.node_fixed, topo.tri_fixed), (node_ball, tri_ball),
                          topo.self_gap)
    raw, n_raw_pt, scan_pt = ball_pairs(x, zero, tc, tr, cutoff, capacity=caps.raw_pt,
                                        scan_rows=caps.scan_pt, table=caps.table,
                                        accept=accept)
    near = lambda b: pt_distance2(x, jnp.concatenate([b[:, :1], tri[b[:, 1]]], 1)) < cutoff ** 2
    it, n_pt = _filter(raw, jnp.minimum(n_raw_pt, caps.raw_pt), near, caps.pt)
    pt = jnp.concatenate([it[:, :1], tri[it[:, 1]]], 1)
    # edge-edge: edge balls against each other (i < j)
    ec, er = _element_balls(x, edges)
    accept = _static_test((topo.edge_body,) * 2, (topo.edge_pin,) * 2,
                          (topo.edge_fixed,) * 2, (edge_ball, edge_ball), topo.self_gap)
    raw, n_raw_ee, scan_ee = ball_pairs(ec, er, ec, er, cutoff, capacity=caps.raw_ee,
                                        scan_rows=caps.scan_ee, table=caps.table,
                                        self_pairs=True, accept=accept)
    near = lambda b: ee_distance2(x, jnp.concatenate([edges[b[:, 0]], edges[b[:, 1]]], 1)) < cutoff ** 2
    ids, n_ee = _filter(raw, jnp.minimum(n_raw_ee, caps.raw_ee), near, caps.ee)
    need = jnp.stack([n_pt, n_ee, scan_pt, scan_ee]).astype(jnp.int32)
    lst = PairList(pt=pt, n_pt=jnp.minimum(n_pt, caps.pt),
                   ee=jnp.concatenate([edges[ids[:, 0]], edges[ids[:, 1]]], 1), ee_id=ids,
                   n_ee=jnp.minimum(n_ee, caps.ee), x_build=x,
                   cutoff=jnp.asarray(cutoff, x.dtype), need=need)
    return lst, jnp.stack([n_raw_pt, n_raw_ee]).astype(jnp.int32)


def prune(src: PairList, x, cutoff, n_pt: int, n_ee: int) -> PairList:
    """The pairs of ``src`` within ``cutoff`` (mm) at x (N, 3) mm, in capacities n_pt,
    n_ee."""
    pt, c_pt = _filter(src.pt, src.n_pt, lambda b: pt_distance2(x, b) < cutoff ** 2, n_pt)
    both, c_ee = _filter(jnp.concatenate([src.ee, src.ee_id], 1), src.n_ee,
                         lambda b: ee_distance2(x, b[:, :4]) < cutoff ** 2, n_ee)
    return PairList(pt=pt, n_pt=jnp.minimum(c_pt, n_pt), ee=both[:, :4], ee_id=both[:, 4:],
                    n_ee=jnp.minimum(c_ee, n_ee), x_build=x,
                    cutoff=jnp.asarray(cutoff, x.dtype),
                    need=jnp.stack([c_pt, c_ee, 0, 0]).astype(jnp.int32))


def _moved(lst, x):
    """The largest move (mm) of a node since ``lst`` was built."""
    return jnp.sqrt(jnp.max(jnp.sum((x - lst.x_build) ** 2, -1)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lists:
    """The two levels of a solve (module docstring): ``cand`` within d_hat + skin, ``act``
    within d_hat + margin (mm), and the raw broad-phase counts ``raw`` (2,) (sticky
    maxima).  Valid at x when every pair closer than d_hat at x is in ``act``."""

    cand: PairList
    act: PairList
    raw: Any
    dhat: Any
    skin: Any
    margin: Any

    def step_cap(self, x):
        """The largest node move (mm) from x, where these lists are valid, that no pair
        outside ``act`` can close up: each is farther than d_hat + margin - 2 m apart
        there (m the largest move since ``act`` was selected), and two nodes moving at
        most 0.45 of that cannot meet."""
        return 0.45 * (self.dhat + self.margin - 2.0 * _moved(self.act, x))

    def candidate_cap(self, x):
        """The largest node move (mm) from x that no pair outside ``cand`` can close up
        (`step_cap` for the candidates: a step that longer needs CCD on them)."""
        return 0.45 * (self.dhat + self.skin - 2.0 * _moved(self.cand, x))


def _sticky(new: PairList, old: PairList) -> PairList:
    return dataclasses.replace(new, need=jnp.maximum(new.need, old.need))


def update(lists: Lists, topo, ref, x, caps: Capacities) -> Lists:
    """``lists`` valid at x (usable inside jit): the active pairs re-selected from the
    candidates once a node has moved margin / 2 since their selection, the candidates
    rebuilt first once a node has moved (skin - margin) / 2 since their build.  Under
    vmap a refresh runs for the whole batch when any member needs it (`jaxvalve.unvmap`),
    and every member takes the refreshed lists: lists built at the current state are
    valid for each, and a member that kept its old ones would ask for its own refresh a
    few steps later, so that a batch would refresh about once per member's need."""
    rebuilt = unvmap_any(_moved(lists.cand, x) >= 0.5 * (lists.skin - lists.margin))

    def rebuild(l):
        cand, raw = build(topo, ref, x, l.dhat + l.skin, caps)
        return dataclasses.replace(l, cand=_sticky(cand, l.cand), raw=jnp.maximum(raw, l.raw))

    def reselect(l):
        act = prune(l.cand, x, l.dhat + l.margin, caps.act_pt, caps.act_ee)
        return dataclasses.replace(l, act=_sticky(act, l.act))

    lists = jax.lax.cond(rebuilt, rebuild, lambda l: l, lists)
    reselected = unvmap_any(rebuilt | (_moved(lists.act, x) >= 0.5 * lists.margin))
    return jax.lax.cond(reselected, reselect, lambda l: l, lists)


def start(topo, ref, x, caps: Capacities, dhat, skin, margin) -> Lists:
    """Both levels built at x (N, 3) mm (usable inside jit)."""
    cand, raw = build(topo, ref, x, dhat + skin, caps)
    act = prune(cand, x, dhat + margin, caps.act_pt, caps.act_ee)
    return Lists(cand=cand, act=act, raw=raw, dhat=jnp.asarray(dhat, x.dtype),
                 skin=jnp.asarray(skin, x.dtype), margin=jnp.asarray(margin, x.dtype))


def stale(x, caps: Capacities, dhat, skin, margin) -> Lists:
    """Empty lists of capacities ``caps`` for states like x (N, 3), that the first
    `update` rebuilds (their build states are +inf): a solve that updates before its first
    force evaluation starts from them, so the broad phase is compiled once, inside it."""
    n, dt = x.shape[0], x.dtype

    def empty(P, Q):
        i32 = lambda *sh: jnp.zeros(sh, jnp.int32)
        return PairList(pt=i32(P, 4), n_pt=i32(), ee=i32(Q, 4), ee_id=i32(Q, 2), n_ee=i32(),
                        x_build=jnp.full((n, 3), jnp.inf, dt),
                        cutoff=jnp.zeros((), dt), need=i32(4))

    f = lambda v: jnp.asarray(v, dt)
    return Lists(cand=empty(caps.pt, caps.ee), act=empty(caps.act_pt, caps.act_ee),
                 raw=jnp.zeros((2,), jnp.int32), dhat=f(dhat), skin=f(skin),
                 margin=f(margin))


def overflow_flag(lists: Lists, caps: Capacities):
    """() bool, inside jit: whether any build or prune of ``lists`` dropped pairs."""
    c, a, raw = lists.cand.need, lists.act.need, lists.raw
    return ((c[0] > caps.pt) | (c[1] > caps.ee) | (c[2] > caps.scan_pt) | (c[3] > caps.scan_ee)
            | (a[0] > caps.act_pt) | (a[1] > caps.act_ee) | (raw[0] > caps.raw_pt)
            | (raw[1] > caps.raw_ee))


def overflowed(lists: Lists, caps: Capacities) -> bool:
    """Host side: whether any build or prune of ``lists`` dropped pairs."""
    return not caps.fits(lists.cand.need, lists.act.need, lists.raw)


def check_overflow(lists: Lists, caps: Capacities) -> None:
    """Host side: raise `NeighbourListOverflow` naming what overflowed."""
    if overflowed(lists, caps):
        raise NeighbourListOverflow(
            f"contact pair lists overflowed their capacities {caps}: needed candidates "
            f"{np.asarray(lists.cand.need).tolist()}, active {np.asarray(lists.act.need).tolist()}, "
            f"raw {np.asarray(lists.raw).tolist()}")


def allocate(topo, ref, x, dhat, skin, margin, caps: Capacities | None = None,
             tries: int = 8):
    """(Lists, Capacities) built at x on the host, growing the capacities until nothing
    overflows there (a solve grows them again where a later state needs more)."""
    x = jnp.asarray(x)
    if not bool(jnp.all(jnp.isfinite(x))):
        raise ParameterError("x holds non-finite positions; contact needs finite coordinates")
    caps = caps or Capacities.for_mesh(topo, dhat, skin, margin)
    for _ in range(tries):
        lists = _start_jit(topo, jnp.asarray(ref), x, caps, dhat, skin, margin)
        if not overflowed(lists, caps):
            return lists, caps
        caps = caps.grown(lists.cand.need, lists.act.need, lists.raw)
    check_overflow(lists, caps)


_start_jit = jax.jit(start, static_argnums=(3,))


def min_distance(topo, ref, x, cutoff: float = 1.0) -> float:
    """The smallest distance (mm) between contact pairs of x (N, 3) mm within ``cutoff``
    (inf where none is that close), on the host: a start the barrier can close from has
    every pair apart."""
    lists, _ = allocate(topo, ref, x, cutoff, 0.0, 0.0)
    return float(_min_distance(jnp.asarray(x), lists.cand))


@jax.jit
def _min_distance(x, pl):
    d_pt = jnp.where(pl.pt_valid, pt_distance2(x, pl.pt), jnp.inf)
    d_ee = jnp.where(pl.ee_valid, ee_distance2(x, pl.ee), jnp.inf)
    return jnp.sqrt(jnp.minimum(jnp.min(d_pt, initial=jnp.inf), jnp.min(d_ee, initial=jnp.inf)))
