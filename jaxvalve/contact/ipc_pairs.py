"""The host reference of the barrier's pair lists: point-triangle and edge-edge pairs of
the leaflets, by NumPy and scipy's k-d tree (the tests compare the in-jit lists of
`jaxvalve.contact.pairs` with it).
`barrier_topology` is built once per valve; `build_pairs(topo, x, cutoff)` lists every
node-triangle and edge-edge pair closer than ``cutoff`` (mm) in the state x (N, 3), with
its squared distance: exact, not a bounding-volume superset.  The pairs are those of
different leaflets and, with ``self_contact`` (the default), those of one leaflet that
share no node (IPC's self-contact): a leaflet that creases sharply (in an asymmetric
root the free edge's centre can pinch flat between its neighbours) then cannot fold
through itself, for the same reason two leaflets cannot cross.  Two elements of one
leaflet that lie closer than ``self_gap`` (0.5 mm) in the flat template are neighbours
within the sheet, not contact, and are never paired: without that, a fine mesh (a
right-angled grid of 0.25 mm puts a node 0.18 mm from a triangle it does not touch)
would feel the barrier in its flat, stress-free state.  The barrier closure requires
d_hat <= self_gap, so that every pair it lists is farther than d_hat in the template.

Excluded pairs: those whose nodes are all sutured (fixed; they exert no force on a free
node), and those whose two sides share a *pin*, a sutured point where two leaflets are sewn
to the same commissure: such elements touch by construction (distance 0) and their contact
is the suture's, not the barrier's.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ParameterError
from ..geometry.broad_phase import ball_pairs
from ..geometry.mesh import unique_edges
from .barrier import collision_weights
from .ipc_distance import (mollifier_threshold, point_triangle_distance2_np,
                           segment_distance2_np)

__all__ = ["BarrierTopology", "BarrierPairs", "barrier_topology", "build_pairs",
           "pair_distances2"]


@dataclasses.dataclass(frozen=True)
class BarrierTopology:
    """Static data of the barrier contact (NumPy).

    triangles (M, 3), edges (E, 2) int, tri_edge (M, 3) the edge row of each triangle's
    edge k; body (N,), tri_body (M,), edge_body (E,) leaflet ids; node_w (N,) mm^2
    (a_p / 2) and edge_w (E,) mm^2 (A_e / 4) the collision weights, edge_len2 (E,) mm^2
    the edges' squared rest lengths (the mollifier threshold of a pair is 1e-3 la^2 lb^2),
    all three from `jaxvalve.contact.barrier.collision_weights`; pin (N,) int, the
    commissure point a sutured node is sewn to, or -1; fixed (N,) bool; self_contact:
    whether pairs of one leaflet that share no node are listed too, less those closer
    than self_gap (mm) in the template ref3 (N, 3) (module docstring); those, found once
    (`_template_neighbours`), are kept as sorted keys: near_pt (node * M + triangle) and
    near_ee (a * E + b, a < b, edge rows)."""

    triangles: np.ndarray
    edges: np.ndarray
    tri_edge: np.ndarray
    body: np.ndarray
    tri_body: np.ndarray
    edge_body: np.ndarray
    node_w: np.ndarray
    edge_w: np.ndarray
    edge_len2: np.ndarray
    pin: np.ndarray
    fixed: np.ndarray
    self_contact: bool = True
    self_gap: float = 0.5
    ref3: np.ndarray | None = None
    near_pt: np.ndarray | None = None
    near_ee: np.ndarray | None = None

    @property
    def n_nodes(self):
        return self.body.shape[0]


@dataclasses.dataclass(frozen=True)
class BarrierPairs:
    """Pairs within a cutoff at one state (NumPy).

    pt (P, 4) [node, t0, t1, t2]; pt_w (P,) mm^2; pt_d2 (P,) mm^2 squared distance at the
    state of the build.  ee (Q, 4) [a0, a1, b0, b1]; ee_w (Q,) mm^2; ee_eps (Q,) mm^4
    mollifier thresholds; ee_d2 (Q,) mm^2.  cutoff (mm).  ee_edges (Q, 2): the rows of
    the two edges in the topology's edge list (the weights' sources,
    `jaxvalve.contact.barrier.pair_weights`)."""

    pt: np.ndarray
    pt_w: np.ndarray
    pt_d2: np.ndarray
    ee: np.ndarray
    ee_w: np.ndarray
    ee_eps: np.ndarray
    ee_d2: np.ndarray
    cutoff: float
    ee_edges: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros((0, 2), np.int64))

    @property
    def min_distance(self) -> float:
        """Smallest distance (mm) of any pair, +inf without pairs."""
        d2 = np.concatenate([self.pt_d2, self.ee_d2, [np.inf]])
        return float(np.sqrt(np.min(d2)))

    def within(self, d2_pt, d2_ee, cutoff):
        """The pairs whose squared distances (given, at another state) are < cutoff^2."""
        a, b = d2_pt < cutoff * cutoff, d2_ee < cutoff * cutoff
        return BarrierPairs(self.pt[a], self.pt_w[a], d2_pt[a], self.ee[b], self.ee_w[b],
                            self.ee_eps[b], d2_ee[b], float(cutoff), self.ee_edges[b])


def barrier_topology(triangles, body, ref, fixed, x0, pin_tol=1e-9,
                     self_contact: bool = True, self_gap: float = 0.5) -> BarrierTopology:
    """`BarrierTopology` of a membrane of several bodies: triangles (M, 3), body (N,),
    reference coordinates ref (N, 2|3) mm (the weights and rest lengths), fixed (N,) bool,
    and the initial state x0 (N, 3) mm, where sutured nodes of different bodies that
    coincide (within pin_tol mm) are pinned together.  self_contact: list the pairs of
    one body that share no node too, less those closer than self_gap (mm) in ref."""
    if not (np.isfinite(self_gap) and self_gap > 0):
        raise ParameterError(f"self_gap must be a positive length (mm); got {self_gap!r}")
    tri = np.asarray(triangles, np.int64)
    body = np.asarray(body, np.int64)
    ref = np.asarray(ref, float)
    fixed = np.asarray(fixed, bool)
    x0 = np.asarray(x0, float)
    edges, tri_edge = unique_edges(tri)
    edges, tri_edge = edges.astype(np.int64), tri_edge.astype(np.int64)
    node_w, edge_w, len2 = collision_weights(ref, tri, tri_edge, len(edges), xp=np)
    from .pairs import commissure_pins
    pin = commissure_pins(body, fixed, x0, pin_tol)
    ref3 = np.pad(ref, ((0, 0), (0, 3 - ref.shape[1])))
    near_pt, near_ee = _template_neighbours(tri, edges, body, ref3, float(self_gap))
    return BarrierTopology(triangles=tri, edges=edges, tri_edge=tri_edge, body=body,
                           tri_body=body[tri[:, 0]], edge_body=body[edges[:, 0]],
                           node_w=node_w, edge_w=edge_w, edge_len2=len2, pin=pin,
                           fixed=fixed, self_contact=bool(self_contact),
                           self_gap=float(self_gap), ref3=ref3, near_pt=near_pt,
                           near_ee=near_ee)


def _template_neighbours(tri, edges, body, ref3, gap):
    """Sorted int64 keys of the pairs of one body closer than gap (mm) in the template
    ref3 (N, 3), shared nodes included (distance 0): node-triangle (node * M + t) and
    edge-edge (a * E + b, a < b).  Such pairs are never listed (module docstring)."""
    m, ne = len(tri), len(edges)
    rt = ref3[tri]
    cen = rt.mean(axis=1)
    rad_t = np.sqrt(np.max(np.sum((rt - cen[:, None]) ** 2, axis=2), axis=1))
    c = ball_pairs(ref3, 0.0, cen, rad_t, gap)
    c = c[body[c[:, 0]] == body[tri[c[:, 1], 0]]]
    d2 = point_triangle_distance2_np(ref3[c[:, 0]], rt[c[:, 1], 0], rt[c[:, 1], 1],
                                     rt[c[:, 1], 2])
    c = c[d2 < gap * gap]
    near_pt = np.unique(c[:, 0] * m + c[:, 1])
    a, b = ref3[edges[:, 0]], ref3[edges[:, 1]]
    c = ball_pairs(0.5 * (a + b), 0.5 * np.sqrt(np.sum((b - a) ** 2, axis=1)), gap=gap)
    c = c[body[edges[c[:, 0], 0]] == body[edges[c[:, 1], 0]]]
    d2 = segment_distance2_np(a[c[:, 0]], b[c[:, 0]], a[c[:, 1]], b[c[:, 1]])
    c = c[d2 < gap * gap]
    return near_pt, np.unique(c[:, 0] * ne + c[:, 1])


def _member(keys, table):
    """(K,) True where keys (K,) int64 are in the sorted table."""
    if len(table) == 0:
        return np.zeros(len(keys), bool)
    at = np.minimum(np.searchsorted(table, keys), len(table) - 1)
    return table[at] == keys


def _shares_pin(pin, a, b):
    """(K,) True where some pinned node of the rows a (K, i) is pinned with one of b (K, j)."""
    pa, pb = pin[a], pin[b]
    out = np.zeros(len(pa), bool)
    i = np.flatnonzero(np.any(pa >= 0, axis=1) & np.any(pb >= 0, axis=1))
    pa, pb = pa[i], pb[i]
    out[i] = np.any((pa[:, :, None] == pb[:, None, :]) & (pa[:, :, None] >= 0), axis=(1, 2))
    return out


def pair_distances2(x, pt, ee):
    """Squared distances (mm^2) of point-triangle rows pt (P, 4) and edge-edge rows ee
    (Q, 4) at the state x (N, 3)."""
    x = np.asarray(x, float)
    d_pt = point_triangle_distance2_np(x[pt[:, 0]], x[pt[:, 1]], x[pt[:, 2]], x[pt[:, 3]])
    d_ee = segment_distance2_np(x[ee[:, 0]], x[ee[:, 1]], x[ee[:, 2]], x[ee[:, 3]])
    return d_pt, d_ee


def build_pairs(topo: BarrierTopology, x, cutoff: float, dx=None) -> BarrierPairs:
    """Every point-triangle and edge-edge pair closer than cutoff (mm) in the state x
    (N, 3), of different bodies or (``topo.self_contact``) of one body and sharing no node,
    less the excluded ones (module docstring).

    dx (N, 3) mm: the move the list is for (the broad phase of CCD, cutoff = d_hat +
    2 max |dx|).  A pair of one body then needs only to be closer than d_hat plus the
    largest relative move of its nodes, max |dx_a - dx_b| (its distance cannot shrink by
    more along the move): the neighbours within a sheet, which move nearly together,
    drop out, where the bound 2 max |dx| would list them all.

    The pairs come sorted (point-triangle by node, then triangle; edge-edge by their edge
    rows), whatever order the broad phase found them in."""
    x = np.asarray(x, float)
    if not np.all(np.isfinite(x)):
        raise ParameterError("x holds non-finite positions; contact needs finite coordinates")
    cutoff = float(cutoff)
    if not cutoff > 0:
        raise ParameterError(f"cutoff must be > 0 mm; got {cutoff}")
    tri, edges = topo.triangles, topo.edges
    xt = x[tri]
    cen = xt.mean(axis=1)
    rad_t = np.sqrt(np.max(np.sum((xt - cen[:, None]) ** 2, axis=2), axis=1))   # (M,)
    if dx is not None:
        dx = np.asarray(dx, float)
        reach = max(cutoff - 2.0 * float(np.max(np.linalg.norm(dx, axis=1))), 0.0)

    def motion(rows):
        """Each element's nodes' moves as a ball: (centre (K, 3), radius (K,)) mm."""
        if dx is None:
            return None
        m = dx[rows]
        c = m.mean(axis=1)
        return c, np.max(np.linalg.norm(m - c[:, None], axis=2), axis=1)

    def limit(ma, ia, mb, ib):
        """For pairs of one body, elements ia and ib with motion balls ma, mb: the
        distance under which the pair is listed; with dx, d_hat plus a bound on the
        largest relative move of their nodes (docstring)."""
        if dx is None:
            return np.full(len(ia), cutoff)
        rel = np.linalg.norm(ma[0][ia] - mb[0][ib], axis=1) + ma[1][ia] + mb[1][ib]
        return np.minimum(cutoff, reach + 1.001 * rel + 1e-9)

    # point-triangle: nodes against the triangles' bounding balls, then the exact distance
    cand = ball_pairs(x, 0.0, cen, rad_t, cutoff)
    node, t = cand[:, 0], cand[:, 1]
    other = topo.body[node] != topo.tri_body[t]
    lim = np.full(len(node), cutoff)
    if topo.self_contact:            # within a body: apart in the template
        i = np.flatnonzero(~other)
        i = i[~_member(node[i] * len(tri) + t[i], topo.near_pt)]
        lim[i] = limit(motion(np.arange(len(x))[:, None]), node[i], motion(tri), t[i])
        other[i] = True
    node, t, lim = node[other], t[other], lim[other]
    # a node is no nearer a triangle than its distance to the centroid less the radius
    rel = x[node] - cen[t]
    near = np.einsum("ij,ij->i", rel, rel) < (lim + rad_t[t]) ** 2
    node, t, lim = node[near], t[near], lim[near]
    rows = np.column_stack([node, tri[t]])
    keep = ~(topo.fixed[node] & np.all(topo.fixed[tri[t]], axis=1))
    keep &= ~_shares_pin(topo.pin, rows[:, :1], rows[:, 1:])
    rows, lim, t = rows[keep], lim[keep], t[keep]
    d2 = point_triangle_distance2_np(x[rows[:, 0]], x[rows[:, 1]], x[rows[:, 2]],
                                     x[rows[:, 3]])
    sel = np.flatnonzero(d2 < lim * lim)
    sel = sel[np.argsort(rows[sel, 0] * len(tri) + t[sel], kind="stable")]   # (node, t)
    pt, pt_d2 = rows[sel], d2[sel]
    # edge-edge: every pair of edges whose bounding balls (about the midpoints) come
    # within cutoff (pairs i < j), of different bodies or, with self-contact (the valve's
    # setting), of one; without it the pairs of one body are listed and dropped
    mid = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    half_e = 0.5 * np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)      # (E,)
    ea_eb = ball_pairs(mid, half_e, gap=cutoff)
    own = topo.edge_body[ea_eb[:, 0]] == topo.edge_body[ea_eb[:, 1]]
    if not topo.self_contact:
        ea_eb, own = ea_eb[~own], own[~own]
    # two edges are no nearer than their midpoints' distance less their half-lengths
    dm = mid[ea_eb[:, 0]] - mid[ea_eb[:, 1]]
    dm2 = np.einsum("ij,ij->i", dm, dm)
    reach_ab = half_e[ea_eb[:, 0]] + half_e[ea_eb[:, 1]]
    near = dm2 < (cutoff + reach_ab) ** 2
    ea_eb, own = ea_eb[near], own[near]
    lb = np.sqrt(dm2[near]) - reach_ab[near]
    lim = np.full(len(ea_eb), cutoff)
    if topo.self_contact:
        i = np.flatnonzero(own)
        apart = ~_member(ea_eb[i, 0] * len(edges) + ea_eb[i, 1], topo.near_ee)
        near = np.ones(len(ea_eb), bool)
        near[i[~apart]] = False
        i = i[apart]
        me = motion(edges)
        lim[i] = limit(me, ea_eb[i, 0], me, ea_eb[i, 1])
        near &= lb < lim
        ea_eb, lim = ea_eb[near], lim[near]
    rows = np.column_stack([edges[ea_eb[:, 0]], edges[ea_eb[:, 1]]])
    keep = ~np.all(topo.fixed[rows], axis=1)
    keep &= ~_shares_pin(topo.pin, rows[:, :2], rows[:, 2:])
    rows, ea_eb, lim = rows[keep], ea_eb[keep], lim[keep]
    d2 = segment_distance2_np(x[rows[:, 0]], x[rows[:, 1]], x[rows[:, 2]], x[rows[:, 3]])
    sel = np.flatnonzero(d2 < lim * lim)
    sel = sel[np.argsort(ea_eb[sel, 0] * len(edges) + ea_eb[sel, 1], kind="stable")]
    ee, ee_d2, ea_eb = rows[sel], d2[sel], ea_eb[sel]
    return BarrierPairs(
        pt=pt, pt_w=topo.node_w[pt[:, 0]], pt_d2=pt_d2, ee=ee,
        ee_w=topo.edge_w[ea_eb[:, 0]] + topo.edge_w[ea_eb[:, 1]],
        ee_eps=mollifier_threshold(np.sqrt(topo.edge_len2[ea_eb[:, 0]]),
                                   np.sqrt(topo.edge_len2[ea_eb[:, 1]])),
        ee_d2=ee_d2, cutoff=cutoff, ee_edges=ea_eb)
