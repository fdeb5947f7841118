"""Simple deterministic meshes for verification problems (NumPy, outside jit).

disk: a clamped circular membrane; rectangle: homogeneous-stretch tests; icosphere: a
closed spherical membrane.  Valve leaflet templates have their own mesher.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay


def disk(radius: float, n_rings: int):
    """Disk of radius (mm) with ``n_rings`` concentric rings of 6k nodes (k = 1..n_rings).

    Returns (points (N, 2), triangles (M, 3) counter-clockwise, boundary mask (N,)).
    Mesh size h = radius / n_rings.
    """
    if n_rings < 1:
        raise ValueError("n_rings must be >= 1")
    pts = [np.zeros((1, 2))]
    for k in range(1, n_rings + 1):
        t = 2 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
        pts.append(radius * k / n_rings * np.stack([np.cos(t), np.sin(t)], axis=1))
    p = np.concatenate(pts)
    tri = Delaunay(p).simplices.astype(np.int32)
    tri = _ccw(p, tri)
    r = np.linalg.norm(p, axis=1)
    return p, tri, np.isclose(r, radius)


def rectangle(lx: float, ly: float, nx: int, ny: int):
    """Structured rectangle [0, lx] x [0, ly], nx x ny cells, each split in 2 triangles
    along alternating diagonals.  Returns (points (N, 2), triangles (M, 3) CCW)."""
    xs, ys = np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    p = np.stack([X.ravel(), Y.ravel()], axis=1)
    idx = lambda i, j: i * (ny + 1) + j
    tri = []
    for i in range(nx):
        for j in range(ny):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            if (i + j) % 2 == 0:
                tri += [[a, b, c], [a, c, d]]
            else:
                tri += [[a, b, d], [b, c, d]]
    return p, np.asarray(tri, np.int32)


def icosphere(radius: float, subdivisions: int):
    """Triangulated sphere (points (N, 3), triangles (M, 3) with outward normals)."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        cache, verts, faces = {}, list(v), []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            faces += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        v, f = np.asarray(verts), np.asarray(faces)
    p = radius * v
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = np.sum(n * p[f].mean(axis=1), axis=1) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return p, f.astype(np.int32)


def _ccw(p, tri):
    a, b = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    neg = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) < 0
    tri = tri.copy()
    tri[neg] = tri[neg][:, [0, 2, 1]]
    return tri


def lift(points2d):
    """(N, 2) -> (N, 3) with z = 0."""
    return np.concatenate([points2d, np.zeros((len(points2d), 1))], axis=1)
