"""The wall surface of a segmented lumen: marching cubes on the image itself, at the
segmentation's half-maximum level and within the mask (so the surface passes between
voxels where the blurred intensity crosses that level, not along voxel faces), in
patient coordinates; the largest connected piece; Taubin smoothing, which removes noise
without shrinking the surface (a Laplacian step followed by a negative one); and, for a
target edge length, isotropic remeshing onto that surface (`jaxvalve.imaging.remesh`:
even, nearly equilateral triangles in place of marching cubes' slivers).  `mesh_quality`
measures the result;
`jaxvalve.geometry.surface_query.distance_to_surface` compares it with another surface."""
from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from .segment import Segmentation
from .volume import Volume

__all__ = ["wall_surface", "taubin", "mesh_quality"]


def wall_surface(volume: Volume, seg: Segmentation, *, edge_mm: float | None = None,
                 smooth_iterations: int = 10):
    """The lumen's wall: (points (P, 3) LPS mm, triangles (T, 3) int), the level set of
    the segmentation's smoothed image (``seg.image``) at its threshold.  edge_mm: the
    target edge length; the marching-cubes surface (edges of about a voxel) is remeshed
    to it (default None: not remeshed).  smooth_iterations: Taubin passes (0: none)."""
    from scipy import ndimage
    from skimage import measure
    sp = volume.spacing
    if edge_mm is not None and not (np.isfinite(edge_mm)
                                    and sp.min() <= edge_mm <= 20 * sp.max()):
        raise ParameterError(f"edge_mm must lie in [{sp.min():g}, {20 * sp.max():g}] mm (the "
                             f"smallest voxel to 20 voxels); got {edge_mm!r}")
    if not (isinstance(smooth_iterations, int) and 0 <= smooth_iterations <= 200):
        raise ParameterError(f"smooth_iterations must be an integer in [0, 200]; got "
                             f"{smooth_iterations!r}")
    data = np.asarray(seg.image, np.float32)
    if data.shape != volume.shape:
        raise ParameterError(f"the segmentation's image {data.shape} is not on the volume's "
                             f"grid {volume.shape}")
    # only the mask's own boundary: outside it (one voxel on) the image is set below the
    # level, so touching structures left out by the segmentation give no surface
    region = ndimage.binary_dilation(seg.mask, iterations=1)
    low = min(float(data.min()), seg.threshold - 1.0)
    data = np.where(region, data, low)
    ijk, tris, _, _ = measure.marching_cubes(data, seg.threshold, allow_degenerate=False)
    pts = volume.to_world(ijk)
    pts, tris = _largest_piece(pts, tris.astype(np.int64))
    if smooth_iterations:
        pts = taubin(pts, tris, iterations=smooth_iterations)
    if edge_mm is not None:
        from .remesh import remesh
        pts, tris = remesh(pts, tris, float(edge_mm))
    return pts, tris


def _largest_piece(pts, tris):
    """The connected piece of the mesh with the most triangles, reindexed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    n = len(pts)
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    tl = lab[tris[:, 0]]
    keep = tris[tl == np.bincount(tl).argmax()]
    used = np.unique(keep)
    new = np.full(n, -1)
    new[used] = np.arange(len(used))
    return pts[used], new[keep]


def _umbrella(tris, n):
    """The mean-of-edge-neighbours operator (sparse (n, n)): (A @ pts) is each vertex's
    neighbours' mean (the umbrella operator)."""
    from scipy.sparse import coo_matrix, diags
    e = _edges(tris)[0]
    r = np.concatenate([e[:, 0], e[:, 1]])
    c = np.concatenate([e[:, 1], e[:, 0]])
    A = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)).tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    return diags(1.0 / np.maximum(deg, 1)) @ A


def taubin(pts, tris, *, iterations=10, lam=0.5, mu=-0.53):
    """Taubin's lambda|mu smoothing: each pass moves every vertex by lam, then by mu (< 0),
    times the offset to its neighbours' mean; the pair is a low-pass filter that keeps
    the enclosed volume (a plain Laplacian shrinks it).  Boundary vertices stay put."""
    if not (0 < lam < -mu):
        raise ParameterError(f"taubin needs 0 < lam < -mu; got lam = {lam!r}, mu = {mu!r}")
    pts = np.asarray(pts, float).copy()
    fixed = _boundary_vertices(tris, len(pts))
    M = _umbrella(tris, len(pts))
    for _ in range(iterations):
        for f in (lam, mu):
            d = M @ pts - pts
            d[fixed] = 0.0
            pts = pts + f * d
    return pts


def _edges(tris):
    """Every edge once (E, 2), and how many triangles share it (E,)."""
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def _boundary_vertices(tris, n):
    e, count = _edges(tris)
    out = np.zeros(n, bool)
    out[e[count == 1].ravel()] = True
    return out


def mesh_quality(pts, tris) -> dict:
    """Vertices, triangles, edge lengths (mm: min, mean, max), smallest angles (degrees:
    min, 5th percentile, share of triangles under 20 degrees), boundary edges (an open
    tube has two loops of them) and non-manifold edges (shared by three or more)."""
    pts, tris = np.asarray(pts, float), np.asarray(tris)
    e, count = _edges(tris)
    length = np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1)
    a, b, c = (pts[tris[:, i]] for i in range(3))
    angles = []
    for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
        u, v = q - p, r - p
        cos = np.sum(u * v, 1) / np.maximum(np.linalg.norm(u, axis=1)
                                            * np.linalg.norm(v, axis=1), 1e-300)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    smallest = np.min(angles, axis=0)
    return dict(vertices=int(len(pts)), triangles=int(len(tris)),
                edge_mm=dict(min=float(length.min()), mean=float(length.mean()),
                             max=float(length.max())),
                min_angle_deg=dict(min=float(smallest.min()),
                                   p5=float(np.percentile(smallest, 5)),
                                   share_below_20=float(np.mean(smallest < 20.0))),
                boundary_edges=int(np.sum(count == 1)),
                non_manifold_edges=int(np.sum(count > 2)))
