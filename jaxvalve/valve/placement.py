"""Initial position of the leaflets in the root (paper, Section 1).

For leaflet i between commissures c_i and c_{i+1}:
1. the flat mesh is mapped rigidly to the plane through c_i and c_{i+1} parallel to the
   valve axis, with the template's y axis toward the aorta and the midpoint of A-D on the
   midpoint of the commissures; the side is chosen so that the triangle normals point
   toward the valve axis (from the aortic to the ventricular side, where pressure pushes);
2. the sutured-edge nodes are put on the suturing path, uniformly by arc length (node at
   fraction t of A-B-C-D goes to fraction t of the path, measured from A's commissure);
3. the other nodes follow the sutured edge by a harmonic extension of its displacement
   (cotangent Laplacian on the flat template), a smooth fold-free surface that spans the
   path;
4. the closure at P = 0 (`jaxvalve.valve.settle`) then relaxes that surface.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import MeshError

__all__ = ["along_path", "along_polyline", "leaflet_frame", "place_leaflet"]


def along_path(path, t):
    """Points (K, 3) at arc-length fractions t (K,) in [0, 1] of the polyline path (P, 3);
    jax.numpy, differentiable in both path and t.  Zero-length segments are skipped;
    t = 0 and t = 1 give the end points exactly."""
    path = jnp.asarray(path)
    seg = jnp.linalg.norm(jnp.diff(path, axis=0), axis=1)
    s = jnp.concatenate([jnp.zeros(1, path.dtype), jnp.cumsum(seg)])
    u = jnp.clip(jnp.asarray(t, path.dtype), 0.0, 1.0) * s[-1]
    k = jnp.clip(jnp.searchsorted(jax.lax.stop_gradient(s), jax.lax.stop_gradient(u),
                                  side="right") - 1, 0, path.shape[0] - 2)
    ok = seg[k] > 0
    w = jnp.where(ok, (u - s[k]) / jnp.where(ok, seg[k], 1.0), 0.0)
    out = path[k] + w[:, None] * (path[k + 1] - path[k])
    # the ends exactly (neighbouring leaflets share their commissure node bit for bit)
    out = jnp.where((u >= s[-1])[:, None], path[-1], out)
    return jnp.where((u <= 0.0)[:, None], path[0], out)


_along_path_jit = jax.jit(along_path)


def along_polyline(path, t):
    """`along_path` on the host: NumPy in, NumPy (K, 3) out (one compiled program per
    shape, not one per jax.numpy operation)."""
    return np.asarray(_along_path_jit(np.asarray(path, float), np.asarray(t, float)))


def leaflet_frame(c0, c1, axis, centre):
    """Orthonormal (e_x, e_y, e_n) and the mirror flag for the plane through c0, c1
    parallel to ``axis`` (aorta -> ventricle).  e_y points to the aorta, e_x runs from
    A's commissure to D's, e_n = e_x x e_y points toward ``centre`` (a point on the axis)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    up = -axis
    chord = np.asarray(c1, float) - np.asarray(c0, float)
    ex = chord - np.dot(chord, axis) * axis
    nrm = np.linalg.norm(ex)
    if nrm < 1e-9:
        raise MeshError("two commissures lie on one line parallel to the valve axis; the "
                        "leaflet plane is undefined")
    ex /= nrm
    en = np.cross(ex, up)
    mid = 0.5 * (np.asarray(c0, float) + np.asarray(c1, float))
    mirror = np.dot(en, np.asarray(centre, float) - mid) < 0
    if mirror:  # A goes on c1: run e_x the other way
        ex, en = -ex, -en
    return ex, up, en, bool(mirror)


def place_leaflet(lmesh, c0, c1, path, axis, centre):
    """Start positions (N, 3) of one leaflet and the fraction of the path where each
    sutured node sits.  ``path`` runs from c0 to c1."""
    ex, ey, _, mirror = leaflet_frame(c0, c1, axis, centre)
    p = lmesh.points
    A = p[lmesh.sutured[0]]
    D = p[lmesh.sutured[-1]]
    mid2 = 0.5 * (A + D)
    mid3 = 0.5 * (np.asarray(c0, float) + np.asarray(c1, float))
    x = mid3 + (p[:, :1] - mid2[0]) * ex + (p[:, 1:2] - mid2[1]) * ey
    t = lmesh.sutured_t
    frac = 1.0 - t if mirror else t
    u = np.zeros_like(x)
    u[lmesh.sutured] = along_polyline(path, frac) - x[lmesh.sutured]
    return x + harmonic_extension(p, lmesh.triangles, lmesh.sutured_mask, u)


def cot_laplacian(p, tri):
    """Cotangent Laplacian (N, N) of a flat mesh p (N, 2) (scipy.sparse, positive
    semi-definite)."""
    n = len(p)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = tri[:, (k + 1) % 3], tri[:, (k + 2) % 3], tri[:, k]
        u, v = p[i] - p[o], p[j] - p[o]
        cot = np.sum(u * v, 1) / np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
        w = 0.5 * cot
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-w, -w, w, w]
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def harmonic_extension(p, tri, fixed, u):
    """Displacements (N, 3): u on the ``fixed`` nodes, harmonic (cot Laplacian) inside."""
    L = cot_laplacian(p, tri)
    free = ~fixed
    A = L[free][:, free].tocsc()
    b = -L[free][:, fixed] @ u[fixed]
    out = u.copy()
    out[free] = spla.splu(A).solve(b)
    return out
