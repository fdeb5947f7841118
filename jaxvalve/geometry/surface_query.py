"""Queries against a triangle surface (the aortic wall), on the host: the exact closest
point and distance of each query point (`closest_points`, `distance_to_surface`), and
the projection of points and polylines onto the surface (`project_to_surface`).

Exact, not approximate: the candidates of a point are the ``k`` triangles whose centroids
lie nearest; where a triangle not among them could still be closer (its centroid lies
within the best distance found plus the largest centroid-to-vertex distance of the
mesh), every triangle whose centroid lies in that ball is measured too.  The
point-triangle distance is `jaxvalve.contact.geometry.point_triangle_distance_np`.
Lengths in mm."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..contact.geometry import point_triangle_distance_np
from ..errors import MeshError

__all__ = ["SurfaceIndex", "closest_points", "distance_to_surface", "project_to_surface"]


class SurfaceIndex:
    """A triangle surface (points (P, 3) mm, triangles (T, 3)) with a k-d tree of its
    triangle centroids, built once for many queries."""

    def __init__(self, surface_points, triangles):
        V = np.asarray(surface_points, dtype=np.float64)
        T = np.asarray(triangles, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or not len(V):
            raise MeshError(f"surface points must have shape (P, 3), P >= 1; got {V.shape}")
        if T.ndim != 2 or T.shape[1] != 3 or not len(T):
            raise MeshError(f"surface triangles must have shape (T, 3), T >= 1; got {T.shape}")
        if T.min() < 0 or T.max() >= len(V):
            raise MeshError(f"surface triangle indices must lie in [0, {len(V) - 1}]; found "
                            f"[{T.min()}, {T.max()}]")
        self.points, self.triangles = V, T
        corners = V[T]                                      # (T, 3, 3)
        self.centroids = corners.mean(axis=1)
        self.reach = float(np.sqrt(np.max(np.sum(
            (corners - self.centroids[:, None]) ** 2, axis=-1))))
        self.tree = cKDTree(self.centroids)

    def _measure(self, p, tri):
        V, T = self.points, self.triangles
        return point_triangle_distance_np(p, V[T[tri, 0]], V[T[tri, 1]], V[T[tri, 2]],
                                          return_point=True)

    def closest(self, points, k: int = 8):
        """(distance (N,), closest point (N, 3), triangle index (N,)) of each point."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            raise MeshError("query points hold NaN or inf")
        k = min(k, len(self.triangles))
        dc, idx = self.tree.query(p, k=k)
        dc, idx = dc.reshape(len(p), k), idx.reshape(len(p), k)
        d, q = self._measure(np.repeat(p, k, axis=0), idx.ravel())
        d, q = d.reshape(len(p), k), q.reshape(len(p), k, 3)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(p))
        best_d, best_q, best_t = d[rows, j], q[rows, j], idx[rows, j]
        # a triangle outside the k candidates is closer only if its centroid lies within
        # best_d + reach; where the k-th centroid is nearer than that, look at all of them
        for n in np.flatnonzero(dc[:, -1] < best_d + self.reach):
            cand = np.asarray(self.tree.query_ball_point(p[n], best_d[n] + self.reach + 1e-9))
            if not len(cand):
                continue
            dd, qq = self._measure(np.repeat(p[n:n + 1], len(cand), axis=0), cand)
            m = int(np.argmin(dd))
            if dd[m] < best_d[n]:
                best_d[n], best_q[n], best_t[n] = dd[m], qq[m], cand[m]
        return best_d, best_q, best_t


def closest_points(points, surface_points, triangles):
    """Exact closest points of ``points`` (N, 3) on a triangle mesh: (distance (N,) mm,
    closest point (N, 3), triangle index (N,))."""
    return SurfaceIndex(surface_points, triangles).closest(points)


def distance_to_surface(points, surface_points, triangles):
    """Exact Euclidean distance (N,) mm from each point (N, 3) to a triangle mesh."""
    return closest_points(points, surface_points, triangles)[0]


def project_to_surface(points, surface_points, triangles):
    """The closest points (N, 3) on the surface of ``points`` (N, 3), and how far each
    moved (N,) mm."""
    d, q, _ = closest_points(points, surface_points, triangles)
    return q, d
