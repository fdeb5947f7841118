"""Node-to-leaflet distances ("gap field") behind a broad phase (NumPy, host side): below a
cutoff the one of `jaxvalve.geometry.broad_phase`, without one a k-d tree per leaflet.

gap[n, j] = unsigned distance (mm) from node n to the surface of leaflet j (the minimum
point-triangle distance over j's triangles), exact where it is below `cutoff` and +inf
beyond (and +inf for the node's own leaflet).  Candidates are triangles T with
|x_n - c_T| < cutoff + R_T (c_T barycentre, R_T = max vertex distance to it), which is
conservative since d(x_n, T) >= |x_n - c_T| - R_T.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..contact.geometry import point_triangle_distance_np
from ..geometry.broad_phase import ball_pairs

__all__ = ["gap_field", "candidate_pairs"]


def _centres(x, tri):
    xt = x[tri]
    c = xt.mean(axis=1)
    return c, np.sqrt(np.max(np.sum((xt - c[:, None]) ** 2, axis=-1), axis=1))


def _flatten(lists):
    counts = np.fromiter((len(v) for v in lists), dtype=np.int64, count=len(lists))
    rows = np.repeat(np.arange(len(lists)), counts)
    cols = (np.concatenate([np.asarray(v, dtype=np.int64) for v in lists])
            if counts.sum() else np.zeros(0, np.int64))
    return rows, cols


def candidate_pairs(x, tri, body, radius):
    """(node, triangle) pairs of different leaflets with |x_n - c_T| < radius + R_T.

    x (N, 3) mm, tri (M, 3), body (N,); radius (mm) may be a scalar or (N,) per node.
    Returns (nodes (P,), triangles (P,)) int64, sorted by node, then triangle.  The
    candidates come from the broad phase by size class
    (`jaxvalve.geometry.broad_phase.ball_pairs`)."""
    c, R = _centres(x, tri)
    p = ball_pairs(x, radius, c, R)
    rows, cols = p[:, 0], p[:, 1]
    keep = body[tri[cols, 0]] != body[rows]
    rows, cols = rows[keep], cols[keep]
    r = radius[rows] if np.ndim(radius) else radius
    keep = np.sum((x[rows] - c[cols]) ** 2, axis=1) < (r + R[cols]) ** 2
    rows, cols = rows[keep], cols[keep]
    order = np.argsort(rows * len(tri) + cols, kind="stable")
    return rows[order], cols[order]


def gap_field(x, tri, body, cutoff=np.inf):
    """Distances (N, L) from every node to every other leaflet's surface (mm).

    cutoff: exact below it, +inf at or beyond (default inf: exact everywhere, using the
    distance to the nearest barycentre of each leaflet as the search radius)."""
    x = np.asarray(x, dtype=np.float64)
    tri = np.asarray(tri)
    body = np.asarray(body)
    n = x.shape[0]
    L = int(body.max()) + 1
    gap = np.full((n, L), np.inf)
    tbody = body[tri[:, 0]]
    if np.isfinite(cutoff):
        rows, cols = candidate_pairs(x, tri, body, float(cutoff))
    else:  # exact everywhere: radius = distance to the nearest barycentre of leaflet j
        c, R = _centres(x, tri)
        rs, cs = [], []
        for j in range(L):
            sel = np.flatnonzero(tbody == j)
            tree = cKDTree(c[sel])
            dc, _ = tree.query(x, k=1)
            r, k = _flatten(tree.query_ball_point(x, dc + R[sel].max() + 1e-9,
                                                  return_sorted=False))
            keep = body[r] != j
            rs.append(r[keep])
            cs.append(sel[k[keep]])
        rows, cols = np.concatenate(rs), np.concatenate(cs)
    t = tri[cols]
    d = point_triangle_distance_np(x[rows], x[t[:, 0]], x[t[:, 1]], x[t[:, 2]])
    np.minimum.at(gap, (rows, tbody[cols]), d)
    gap[gap >= cutoff] = np.inf
    return gap
