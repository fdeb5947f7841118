"""Input checks and per-leaflet topology for the coaptation metrics (NumPy, host side)."""
from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from ..errors import MeshError, ParameterError
from ..geometry.mesh import edge_lengths_np


@dataclasses.dataclass(frozen=True)
class Topology:
    """Per-leaflet index sets of a closed valve (all indices are global).

    body: (N,) int64 leaflet of each node; tri: (M, 3) int64 triangles; tbody: (M,)
    leaflet of each triangle;
    tris[i]: (M_i, 3) triangles of leaflet i; tri_ids[i]: (M_i,) their rows in `tri`;
    nodes[i]: (N_i,) nodes of leaflet i; edges[i]: (E_i, 2) undirected edges;
    free[i]: (F_i, 2) free-edge segments (boundary edges with both ends on the free edge);
    pairs: all leaflet pairs (i, j), i < j; triples: (i, j, k), j < k, all different.
    """

    n_nodes: int
    n_leaflets: int
    body: np.ndarray
    tri: np.ndarray
    tbody: np.ndarray
    tris: tuple
    tri_ids: tuple
    nodes: tuple
    edges: tuple
    free: tuple
    pairs: tuple
    triples: tuple


def check_x(x, n=None, name="x"):
    """(N, 3) float64 finite positions (mm)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or (n is not None and x.shape[0] != n):
        want = "(N, 3)" if n is None else f"({n}, 3)"
        raise MeshError(f"{name} must have shape {want}; got {x.shape}")
    if not np.all(np.isfinite(x)):
        k = int(np.argwhere(~np.isfinite(x))[0, 0])
        raise MeshError(f"{name} holds a non-finite coordinate (NaN or inf) at node {k}; "
                        "every coordinate must be finite")
    return x


def check_frame(axis, origin, annulus_level=None):
    """Unit axis (3,), origin (3,) and annulus level (float, mm, or None)."""
    a = np.asarray(axis, dtype=np.float64)
    o = np.asarray(origin, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise ParameterError(f"axis must be a finite nonzero 3-vector; got {axis!r}")
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ParameterError(f"origin must be a finite 3-vector (mm); got {origin!r}")
    a = a / np.linalg.norm(a)
    if annulus_level is not None:
        try:
            s0 = float(annulus_level)
        except (TypeError, ValueError):
            s0 = math.nan
        if not math.isfinite(s0):
            raise ParameterError(f"annulus_level must be a finite axial coordinate (mm); "
                                 f"got {annulus_level!r}")
        annulus_level = s0
    return a, o, annulus_level


def perp_basis(axis):
    """Orthonormal (2, 3) basis of the plane normal to the unit `axis`."""
    k = int(np.argmin(np.abs(axis)))
    e = np.zeros(3)
    e[k] = 1.0
    b1 = np.cross(axis, e)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(axis, b1)])


def _undirected(tri):
    und = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    return np.unique(und, axis=0, return_counts=True)


def topology(triangles, body, free_edge, n_nodes):
    """Validate the mesh arrays and build the `Topology`."""
    tri = np.asarray(triangles)
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
        raise MeshError(f"triangles must have shape (M, 3), M >= 1; got {tri.shape}")
    if not np.issubdtype(tri.dtype, np.integer):
        raise MeshError("triangles must hold integer node indices")
    tri = tri.astype(np.int64)
    if tri.min() < 0 or tri.max() >= n_nodes:
        raise MeshError(f"triangle indices must lie in [0, {n_nodes - 1}]; found "
                        f"[{tri.min()}, {tri.max()}]")
    body = np.asarray(body)
    if body.shape != (n_nodes,) or not np.issubdtype(body.dtype, np.integer):
        raise MeshError(f"body must be an integer array of shape ({n_nodes},); "
                        f"got {body.dtype} {body.shape}")
    body = body.astype(np.int64)
    L = int(body.max()) + 1 if body.size else 0
    if body.min() < 0 or L < 2 or set(np.unique(body).tolist()) != set(range(L)):
        raise MeshError("body must number the leaflets 0..L-1 with L >= 2, each used; got "
                        f"ids {np.unique(body).tolist()}")
    tb = body[tri]
    if np.any(tb != tb[:, :1]):
        k = int(np.argmax(np.any(tb != tb[:, :1], axis=1)))
        raise MeshError(f"triangle {k} joins nodes of different leaflets (body {tb[k]})")
    tbody = tb[:, 0]
    free_edge = np.asarray(free_edge)
    if free_edge.shape != (n_nodes,):
        raise MeshError(f"free_edge must be a boolean mask of shape ({n_nodes},); "
                        f"got {free_edge.shape}")
    free_edge = free_edge.astype(bool)
    tris, ids, nodes, edges, free = [], [], [], [], []
    for i in range(L):
        sel = np.flatnonzero(tbody == i)
        if sel.size == 0:
            raise MeshError(f"leaflet {i} has no triangles")
        t = tri[sel]
        e, cnt = _undirected(t)
        fe = e[(cnt == 1) & free_edge[e[:, 0]] & free_edge[e[:, 1]]]
        if fe.shape[0] == 0:
            raise MeshError(f"leaflet {i} has no free-edge segment (boundary edge with both "
                            "ends flagged in free_edge); h_avr needs a free edge")
        tris.append(t)
        ids.append(sel)
        nodes.append(np.unique(t))
        edges.append(e)
        free.append(fe)
    pairs = tuple(itertools.combinations(range(L), 2))
    triples = tuple((i, j, k) for i in range(L)
                    for j, k in itertools.combinations([m for m in range(L) if m != i], 2))
    return Topology(n_nodes, L, body, tri, tbody, tuple(tris), tuple(ids), tuple(nodes),
                    tuple(edges), tuple(free), pairs, triples)


def max_edge_length(x, tri):
    """Longest triangle edge (mm)."""
    return float(np.max(edge_lengths_np(x, tri)))


def annulus_level(x, sutured, body, axis, origin):
    """Axial coordinate s0 (mm) of the annulus plane: the mean over leaflets of the
    largest axial coordinate (most ventricular point) of each leaflet's sutured nodes.

    x (N, 3) mm; sutured (N,) bool; body (N,) int.  For a symmetric root the three lowest
    points share one axial coordinate and this is exactly the plane through them."""
    x = check_x(x)
    a, o, _ = check_frame(axis, origin)
    sutured = np.asarray(sutured, dtype=bool)
    body = np.asarray(body)
    if sutured.shape != (x.shape[0],) or body.shape != (x.shape[0],):
        raise MeshError("sutured and body must have shape (N,)")
    s = (x - o) @ a
    lows = [s[sutured & (body == b)].max() for b in np.unique(body) if
            np.any(sutured & (body == b))]
    if not lows:
        raise MeshError("no sutured nodes: the annulus plane needs the suture paths")
    return float(np.mean(lows))
