"""Exact triangle-triangle intersection tests (NumPy, vectorised) and leaflet checks.

`triangles_intersect` is Moller's interval-overlap test (T. Moller, "A fast triangle-
triangle intersection test", J. Graphics Tools 2(2), 1997), vectorised over pairs:

1. signed distances of each triangle's vertices to the other's plane; all of one sign
   (strictly) -> disjoint;
2. all zero -> coplanar: project to 2D (drop the dominant normal axis); they intersect iff
   an edge of one meets an edge of the other or a vertex of one lies in the other;
3. otherwise each triangle meets the line L = plane1 x plane2 in an interval (from its
   edges crossing the other plane and its vertices on it); they intersect iff the two
   intervals overlap.

Convention: triangles are *closed* sets; touching counts as intersecting (a shared vertex,
a vertex on the other's face or edge, an edge along the other's edge).  Distances to a
plane below ``tol * |n| * l`` (l the longest edge of the two triangles) are snapped to 0,
so a vertex within ~tol * l of the other plane is treated as lying on it.  Decisions for
configurations that touch only within rounding may go either way.

`leaflets_intersect` checks all pairs of triangles of different leaflets behind a
bounding-sphere / axis-aligned-box broad phase (`jaxvalve.geometry.broad_phase` on
barycentres);
`self_intersections` does the same for triangles of one leaflet that share no vertex.
Lengths in mm.  This module is independent of `jaxvalve.contact`.
"""
from __future__ import annotations

import numpy as np
from ..errors import MeshError
from ..geometry.broad_phase import ball_pairs

__all__ = ["triangles_intersect", "leaflets_intersect", "self_intersections",
           "candidate_triangle_pairs"]


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _plane_distances(P, Q, tol, scale):
    """Snapped signed distances (K, 3) (times |n_Q|) of P's vertices to Q's plane."""
    n = np.cross(Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0])
    d = _dot(P - Q[:, None, 0], n[:, None])
    d[np.abs(d) <= (tol * np.linalg.norm(n, axis=1) * scale)[:, None]] = 0.0
    return d, n


def _interval(P, s, D):
    """Interval (lo, hi) of triangle P (K,3,3) on the line of direction D, given its
    vertices' signed distances s (K,3) to the other plane (not all of one strict sign)."""
    p = _dot(P, D[:, None])                                     # (K, 3)
    lo = np.where(s == 0, p, np.inf)
    hi = np.where(s == 0, p, -np.inf)
    for k in range(3):
        m = (k + 1) % 3
        cross = s[:, k] * s[:, m] < 0
        den = np.where(cross, s[:, k] - s[:, m], 1.0)
        v = p[:, k] + (p[:, m] - p[:, k]) * (s[:, k] / den)
        lo[:, k] = np.where(cross, np.minimum(lo[:, k], v), lo[:, k])
        hi[:, k] = np.where(cross, np.maximum(hi[:, k], v), hi[:, k])
    return lo.min(axis=1), hi.max(axis=1)


def _orient(a, b, c):
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - \
        (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _segments_meet(p1, p2, q1, q2):
    """Closed 2D segments p1p2 and q1q2 (..., 2) intersect."""
    o1, o2 = _orient(p1, p2, q1), _orient(p1, p2, q2)
    o3, o4 = _orient(q1, q2, p1), _orient(q1, q2, p2)
    collinear = (o1 == 0) & (o2 == 0) & (o3 == 0) & (o4 == 0)
    boxes = np.all((np.minimum(p1, p2) <= np.maximum(q1, q2))
                   & (np.minimum(q1, q2) <= np.maximum(p1, p2)), axis=-1)
    return np.where(collinear, boxes, (o1 * o2 <= 0) & (o3 * o4 <= 0))


def _point_in(p, T):
    """Closed 2D point-in-triangle for p (K,2), T (K,3,2) (either orientation)."""
    o = np.stack([_orient(T[:, k], T[:, (k + 1) % 3], p) for k in range(3)], axis=1)
    return np.all(o >= 0, axis=1) | np.all(o <= 0, axis=1)


def _coplanar(P, Q, n):
    """Closed coplanar triangles P, Q (K,3,3) with plane normal n (K,3) intersect."""
    drop = np.argmax(np.abs(n), axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[drop]             # (K, 2)
    p = np.take_along_axis(P, keep[:, None, :], axis=2)
    q = np.take_along_axis(Q, keep[:, None, :], axis=2)
    hit = _point_in(p[:, 0], q) | _point_in(q[:, 0], p)
    for i in range(3):
        for j in range(3):
            hit |= _segments_meet(p[:, i], p[:, (i + 1) % 3], q[:, j], q[:, (j + 1) % 3])
    return hit


def triangles_intersect(P, Q, tol: float = 1e-12):
    """Whether closed triangles P[k] and Q[k] intersect: bool (K,).

    P, Q: (K, 3, 3) vertex coordinates (or (3, 3) for one pair, returning a bool).
    tol: relative snapping tolerance for "vertex on the other plane" (see module doc)."""
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    if P.shape != Q.shape or P.ndim not in (2, 3) or P.shape[-2:] != (3, 3):
        raise MeshError(f"P and Q must both have shape (K, 3, 3) or (3, 3); got {P.shape}, "
                        f"{Q.shape}")
    single = P.ndim == 2
    P, Q = P.reshape(-1, 3, 3), Q.reshape(-1, 3, 3)
    edges = np.concatenate([P - np.roll(P, 1, axis=1), Q - np.roll(Q, 1, axis=1)], axis=1)
    scale = np.sqrt(np.max(_dot(edges, edges), axis=1))
    dq, n1 = _plane_distances(Q, P, tol, scale)                 # Q's vertices vs plane P
    dp, n2 = _plane_distances(P, Q, tol, scale)
    apart = (np.all(dq > 0, 1) | np.all(dq < 0, 1) | np.all(dp > 0, 1) | np.all(dp < 0, 1))
    coplanar = ~apart & (np.all(dq == 0, 1) | np.all(dp == 0, 1))
    general = ~apart & ~coplanar
    out = np.zeros(P.shape[0], dtype=bool)
    if np.any(general):
        g = np.flatnonzero(general)
        D = np.cross(n1[g], n2[g])
        lo1, hi1 = _interval(P[g], dp[g], D)
        lo2, hi2 = _interval(Q[g], dq[g], D)
        out[g] = np.maximum(lo1, lo2) <= np.minimum(hi1, hi2)
    if np.any(coplanar):
        c = np.flatnonzero(coplanar)
        out[c] = _coplanar(P[c], Q[c], n1[c])
    return bool(out[0]) if single else out


# ------------------------------------------------------------------------------ meshes
def _check(x, triangles, body=None):
    x = np.asarray(x, dtype=np.float64)
    tri = np.asarray(triangles)
    if x.ndim != 2 or x.shape[1] != 3:
        raise MeshError(f"x must have shape (N, 3); got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise MeshError("x holds a non-finite coordinate (NaN or inf)")
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise MeshError(f"triangles must be an integer array of shape (M, 3); got "
                        f"{tri.dtype} {tri.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= x.shape[0]):
        raise MeshError(f"triangle indices must lie in [0, {x.shape[0] - 1}]")
    if body is not None:
        body = np.asarray(body)
        if body.shape != (x.shape[0],):
            raise MeshError(f"body must have shape ({x.shape[0]},); got {body.shape}")
    return x, tri.astype(np.int64), body


def _boxes_overlap(lo, hi, i, j):
    return np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)


def candidate_triangle_pairs(x, triangles, body=None, same_body=False):
    """Broad phase: triangle pairs (P, 2), i < j, whose bounding spheres (about the
    barycentre) and axis-aligned boxes overlap.  With body (N,): pairs of different
    bodies (same_body False) or of the same body sharing no vertex (same_body True);
    without body: all pairs sharing no vertex."""
    x, tri, body = _check(x, triangles, body)
    if tri.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    xt = x[tri]
    c = xt.mean(axis=1)
    R = np.sqrt(np.max(_dot(xt - c[:, None], xt - c[:, None]), axis=1))
    pairs = ball_pairs(c, R * (1 + 1e-12))
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    keep = _dot(c[i] - c[j], c[i] - c[j]) <= (R[i] + R[j]) ** 2 * (1 + 1e-12)
    keep &= _boxes_overlap(xt.min(axis=1), xt.max(axis=1), i, j)
    if body is not None:
        tb = body[tri[:, 0]]
        keep &= (tb[i] == tb[j]) if same_body else (tb[i] != tb[j])
    if body is None or same_body:
        shared = np.any(tri[i][:, :, None] == tri[j][:, None, :], axis=(1, 2))
        keep &= ~shared
    i, j = i[keep], j[keep]                      # i < j (ball_pairs)
    out = np.stack([i, j], axis=1)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def leaflets_intersect(x, triangles, body, tol: float = 1e-12):
    """Pairs (P, 2) int64 (t1 < t2, sorted) of intersecting triangles of different
    leaflets (closed triangles: touching counts).  x (N, 3) mm, triangles (M, 3),
    body (N,) leaflet ids (a triangle's leaflet is that of its first vertex)."""
    x, tri, _ = _check(x, triangles, body)
    cand = candidate_triangle_pairs(x, tri, body)
    hit = triangles_intersect(x[tri[cand[:, 0]]], x[tri[cand[:, 1]]], tol) if len(cand) \
        else np.zeros(0, bool)
    return cand[hit]


def self_intersections(x, triangles, body=None, tol: float = 1e-12):
    """Pairs (P, 2) of intersecting triangles of the same leaflet (all of the mesh if
    body is None) that share no vertex.  Folds between triangles sharing a vertex or an
    edge are not detected."""
    x, tri, body = _check(x, triangles, body)
    cand = candidate_triangle_pairs(x, tri, body, same_body=True)
    hit = triangles_intersect(x[tri[cand[:, 0]]], x[tri[cand[:, 1]]], tol) if len(cand) \
        else np.zeros(0, bool)
    return cand[hit]
