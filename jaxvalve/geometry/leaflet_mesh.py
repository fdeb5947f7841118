"""Quasi-uniform triangle meshes of a leaflet template (Shewchuk's Triangle, via `triangle`).

The boundary is sampled first, with nodes spaced evenly along each template edge (A-B,
the arc B-C, C-D, D-E, E-A; ceil(length / h) segments each); Triangle then fills the
interior with a constrained conforming Delaunay mesh (minimum angle 30 degrees, maximum
area 1.6 sqrt(3)/4 h^2 so that the mean edge is about h, no Steiner points on the boundary) and a few sweeps of Laplacian
smoothing even out the interior.  The same inputs always give the same mesh.

Node order: the sutured edge A -> B -> C -> D first (indices 0..n_s-1), then the free-edge
interior nodes from D to E to A, then the interior nodes.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import ParameterError
from .mesh import signed_areas_np, triangle_angles, unique_edges
from .template import Template, free_point, sutured_point

__all__ = ["LeafletMesh", "mesh_leaflet", "mesh_quality"]


@dataclasses.dataclass(frozen=True)
class LeafletMesh:
    """A meshed template.

    points (N, 2) mm, template frame; triangles (M, 3) counter-clockwise (normal +z).
    sutured (n_s,) node indices along A-B-C-D; sutured_t (n_s,) their arc-length fraction.
    free (n_f,) node indices along A-E-D (A and D included); free_t their fraction.
    """

    template: Template
    h: float
    points: np.ndarray
    triangles: np.ndarray
    sutured: np.ndarray
    sutured_t: np.ndarray
    free: np.ndarray
    free_t: np.ndarray

    @property
    def n_nodes(self):
        return self.points.shape[0]

    @property
    def sutured_mask(self):
        m = np.zeros(self.n_nodes, bool)
        m[self.sutured] = True
        return m

    @property
    def free_mask(self):
        m = np.zeros(self.n_nodes, bool)
        m[self.free] = True
        return m

    def quality(self):
        return mesh_quality(self.points, self.triangles)


def _edge_counts(tpl: Template, h: float):
    beta = math.radians(tpl.alpha) / 2
    lengths = (tpl.a, 2 * beta * tpl.r, tpl.a, tpl.b, tpl.b)
    return [max(1, math.ceil(L / h - 1e-9)) for L in lengths]


def _boundary(tpl: Template, h: float):
    """Boundary nodes (K, 2), counter-clockwise from A, with sutured/free fractions."""
    na, nc, _, nb, _ = _edge_counts(tpl, h)
    L_s = tpl.sutured_length
    beta = math.radians(tpl.alpha) / 2
    # even spacing on each edge, as fractions of the sutured / free edge length
    u = np.concatenate([np.linspace(0, tpl.a, na + 1)[:-1],
                        tpl.a + np.linspace(0, 2 * beta * tpl.r, nc + 1)[:-1],
                        tpl.a + 2 * beta * tpl.r + np.linspace(0, tpl.a, na + 1)])
    t_s = u / L_s
    t_f = np.concatenate([np.linspace(0, 0.5, nb + 1), np.linspace(0.5, 1, nb + 1)[1:]])
    ps = sutured_point(t_s, tpl.r, tpl.a, tpl.alpha)
    pf = free_point(t_f, tpl.r, tpl.a, tpl.b, tpl.alpha)
    # free edge from D back to A, without the corners
    inner_f = pf[1:-1][::-1]
    pts = np.concatenate([ps, inner_f])
    return pts, t_s, t_f


def mesh_leaflet(template: Template, h: float, *, min_angle: float = 30.0,
                 smooth_sweeps: int = 5) -> LeafletMesh:
    """Mesh ``template`` with target edge length ``h`` (mm)."""
    import triangle as tr

    h = float(h)
    if not math.isfinite(h) or h <= 0:
        raise ParameterError(f"mesh size h must be > 0 mm; got {h}")
    if h > 0.5 * template.chord:
        raise ParameterError(f"mesh size h must be at most |AD| / 2 = {template.chord / 2:.3f} "
                             f"mm for this template; got {h}")
    if not 0 < min_angle <= 33:
        raise ParameterError(f"min_angle must lie in (0, 33] degrees; got {min_angle}")
    bpts, t_s, t_f = _boundary(template, h)
    k = len(bpts)
    seg = np.stack([np.arange(k), (np.arange(k) + 1) % k], axis=1)
    max_area = 1.6 * math.sqrt(3) / 4 * h * h  # Triangle's mean area is ~0.6 of the cap
    out = tr.triangulate(dict(vertices=bpts, segments=seg),
                         f"pq{min_angle:g}a{max_area:.12g}YQ")
    pts = np.asarray(out["vertices"], np.float64)
    tri = np.asarray(out["triangles"], np.int64)
    if not np.allclose(pts[:k], bpts):
        raise RuntimeError("Triangle reordered the boundary nodes")  # pragma: no cover
    tri = _ccw(pts, tri)
    pts = _smooth(pts, tri, k, smooth_sweeps)
    n_s = len(t_s)
    sutured = np.arange(n_s)
    free = np.concatenate([[0], np.arange(k - 1, n_s - 2, -1)])
    return LeafletMesh(template, h, pts, tri.astype(np.int32), sutured, t_s, free, t_f)


def _ccw(p, tri):
    e1, e2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    cw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    tri = tri.copy()
    tri[cw] = tri[cw][:, [0, 2, 1]]
    return tri


def _smooth(p, tri, n_boundary, sweeps):
    """Laplacian smoothing of interior nodes; a sweep that would invert a triangle is undone."""
    n = len(p)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    deg = np.bincount(e.ravel(), minlength=n).astype(float)
    for _ in range(sweeps):
        s = np.zeros_like(p)
        np.add.at(s, e[:, 0], p[e[:, 1]])
        np.add.at(s, e[:, 1], p[e[:, 0]])
        q = p.copy()
        q[n_boundary:] = s[n_boundary:] / deg[n_boundary:, None]
        if np.min(signed_areas_np(q, tri)) <= 0:
            break
        p = q
    return p


def mesh_quality(points, triangles) -> dict:
    """Minimum / mean angle (degrees), edge-length statistics (mm) and their spread
    (max/min and coefficient of variation), triangle and node counts."""
    p = np.asarray(points, float)
    t = np.asarray(triangles)
    ang = triangle_angles(p, t)
    e, _ = unique_edges(t)
    el = np.linalg.norm(p[e[:, 1]] - p[e[:, 0]], axis=1)
    return dict(n_triangles=int(len(t)), n_nodes=int(len(p)), min_angle=float(ang.min()),
                mean_min_angle=float(ang.min(1).mean()), max_angle=float(ang.max()),
                edge_min=float(el.min()), edge_max=float(el.max()), edge_mean=float(el.mean()),
                edge_ratio=float(el.max() / el.min()), edge_cv=float(el.std() / el.mean()))
