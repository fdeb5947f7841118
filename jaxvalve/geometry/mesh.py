"""Triangle-mesh checks and flat reference geometry.

A mesh is reference coordinates ``ref`` of shape (N, 2) (a flat template, mm) or (N, 3)
(3D points, each triangle is flat in its own plane), and oriented ``triangles`` of shape
(M, 3), int32.  Validation is NumPy, outside jit; the reference geometry functions are
pure JAX so that they can be differentiated with respect to ``ref``.
"""
from __future__ import annotations

import numpy as np
import jax.numpy as jnp

from ..errors import MeshError


def validate_mesh(ref, triangles, *, min_area_ratio: float = 1e-10):
    """Check a mesh and return ``(ref float64 (N,d), triangles int32 (M,3))``.

    Raises `MeshError` for: wrong shapes, non-finite coordinates, indices outside [0, N),
    repeated vertices in a triangle, degenerate (zero-area) triangles, inconsistent
    orientation (an interior edge used twice in the same direction, or in 2D a triangle
    with negative signed area), and edges shared by more than two triangles.
    """
    ref = np.asarray(ref, dtype=np.float64)
    tri = np.asarray(triangles)
    if ref.ndim != 2 or ref.shape[1] not in (2, 3):
        raise MeshError(f"ref must have shape (N, 2) or (N, 3); got {ref.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise MeshError(f"triangles must have shape (M, 3); got {tri.shape}")
    if tri.shape[0] == 0:
        raise MeshError("triangles is empty; a mesh needs at least one triangle")
    if not np.issubdtype(tri.dtype, np.integer):
        if not np.all(np.isfinite(tri)) or np.any(tri != np.round(tri)):
            raise MeshError("triangles must hold integer node indices")
    tri = tri.astype(np.int64)
    if not np.all(np.isfinite(ref)):
        bad = np.argwhere(~np.isfinite(ref))[0]
        raise MeshError(f"ref holds a non-finite coordinate (NaN or inf) at node {bad[0]}; "
                        "every coordinate must be finite")
    n = ref.shape[0]
    if tri.min() < 0 or tri.max() >= n:
        raise MeshError(f"triangle indices must lie in [0, {n - 1}] (N = {n} nodes); "
                        f"found range [{tri.min()}, {tri.max()}]")
    if np.any((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])):
        raise MeshError("a triangle repeats a vertex index; each triangle needs 3 distinct nodes")
    area = signed_areas_np(ref, tri)
    scale = np.max(np.ptp(ref, axis=0)) ** 2
    tiny = min_area_ratio * max(scale, 1e-300)
    if ref.shape[1] == 2:
        if np.any(np.abs(area) <= tiny):
            k = int(np.argmin(np.abs(area)))
            raise MeshError(f"triangle {k} is degenerate (area {area[k]:.3e}); every triangle "
                            f"needs area > {tiny:.1e} mm^2")
        if np.any(area < 0):
            k = int(np.argmax(area < 0))
            raise MeshError(f"triangle {k} is clockwise; 2D templates need every triangle "
                            "counter-clockwise (consistent orientation)")
    else:
        if np.any(area <= tiny):
            k = int(np.argmin(area))
            raise MeshError(f"triangle {k} is degenerate (area {area[k]:.3e}); every triangle "
                            f"needs area > {tiny:.1e} mm^2")
    _check_edge_orientation(tri)
    return ref, tri.astype(np.int32)


def _check_edge_orientation(tri):
    directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    uniq, counts = np.unique(directed, axis=0, return_counts=True)
    if np.any(counts > 1):
        e = uniq[np.argmax(counts > 1)]
        raise MeshError(f"edge ({e[0]}, {e[1]}) is used twice in the same direction: the "
                        "triangles are not consistently oriented (or duplicated)")
    und = np.sort(directed, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    if np.any(counts > 2):
        raise MeshError("an edge is shared by more than two triangles; the mesh must be a manifold")


def signed_areas_np(ref, tri):
    """Areas (M,) in mm^2; signed (counter-clockwise positive) for 2D refs."""
    a = ref[tri[:, 1]] - ref[tri[:, 0]]
    b = ref[tri[:, 2]] - ref[tri[:, 0]]
    if ref.shape[1] == 2:
        return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return 0.5 * np.linalg.norm(np.cross(a, b), axis=1)


def cauchy_green_np(x, triangles, ref):
    """Right Cauchy-Green tensors C = F^T F (M, 2, 2) of the affine maps from the template
    triangles ``ref`` (N, 2) mm to ``x`` (N, 2|3) mm (NumPy, float64)."""
    x = np.asarray(x, np.float64)
    ref = np.asarray(ref, np.float64)
    t = np.asarray(triangles)
    Dm = np.stack([ref[t[:, 1]] - ref[t[:, 0]], ref[t[:, 2]] - ref[t[:, 0]]], axis=-1)
    Ds = np.stack([x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]], axis=-1)
    F = Ds @ np.linalg.inv(Dm)
    return np.swapaxes(F, -1, -2) @ F


def triangle_angles(points, triangles):
    """Interior angles (M, 3) in degrees, angle k at vertex k."""
    p = np.asarray(points, float)
    t = np.asarray(triangles)
    out = []
    for k in range(3):
        u = p[t[:, (k + 1) % 3]] - p[t[:, k]]
        w = p[t[:, (k + 2) % 3]] - p[t[:, k]]
        c = np.sum(u * w, 1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1))
        out.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.stack(out, 1)


def edge_lengths_np(points, triangles):
    """(M, 3) length (mm) of each triangle's three edges (vertex k to k+1), NumPy; the
    edges inside the mesh appear once per triangle that has them."""
    X = np.asarray(points, float)
    tri = np.asarray(triangles)
    return np.linalg.norm(X[np.roll(tri, -1, axis=1)] - X[tri], axis=-1)


def unique_edges(triangles):
    """Undirected edges (E, 2) int32, sorted, and the map (M, 3) from triangle edge k
    (opposite vertex k, i.e. vertices k+1, k+2) to its row in the edge list."""
    tri = np.asarray(triangles)
    local = np.stack([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]], axis=1)  # (M,3,2)
    flat = np.sort(local.reshape(-1, 2), axis=1)
    edges, inv = np.unique(flat, axis=0, return_inverse=True)
    return edges.astype(np.int32), inv.reshape(-1, 3).astype(np.int32)


def boundary_nodes(triangles):
    """Boolean mask (N,) of nodes on the mesh boundary (edges used by one triangle)."""
    tri = np.asarray(triangles)
    und = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    e, c = np.unique(und, axis=0, return_counts=True)
    mask = np.zeros(int(tri.max()) + 1, dtype=bool)
    mask[e[c == 1].ravel()] = True
    return mask


# ---------------------------------------------------------------- differentiable geometry
def local_reference(ref, triangles):
    """Flat reference shape of each triangle in its own 2D frame.

    Returns ``Dm`` (M, 2, 2): columns are edges X1-X0 and X2-X0 in local 2D coordinates.
    For a 2D template the local frame is the template frame itself, so directions given
    in template coordinates (fibre angles) keep their meaning.
    """
    X = ref[triangles]  # (M,3,d)
    e1 = X[:, 1] - X[:, 0]
    e2 = X[:, 2] - X[:, 0]
    if ref.shape[1] == 2:
        return jnp.stack([e1, e2], axis=-1)
    l1 = jnp.linalg.norm(e1, axis=-1)
    t1 = e1 / l1[:, None]
    n = jnp.cross(e1, e2)
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    t2 = jnp.cross(n, t1)
    col1 = jnp.stack([l1, jnp.zeros_like(l1)], axis=-1)
    col2 = jnp.stack([jnp.sum(e2 * t1, -1), jnp.sum(e2 * t2, -1)], axis=-1)
    return jnp.stack([col1, col2], axis=-1)


def reference_areas(Dm):
    """Reference triangle areas (M,) from `local_reference` output."""
    return 0.5 * (Dm[:, 0, 0] * Dm[:, 1, 1] - Dm[:, 0, 1] * Dm[:, 1, 0])


def right_cauchy_green(x, triangles, Dm_inv):
    """C = F^T F (M, 2, 2) with F = Ds Dm^-1 (M, 3, 2) the map from the flat reference."""
    xt = x[triangles]
    Ds = jnp.stack([xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]], axis=-1)  # (M,3,2)
    F = Ds @ Dm_inv
    return jnp.swapaxes(F, -1, -2) @ F
