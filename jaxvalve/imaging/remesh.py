"""Isotropic remeshing of a triangle surface to a target edge length L (Botsch and
Kobbelt 2004, "A remeshing approach to multiresolution modeling").

Each of ``iterations`` rounds: split every edge longer than 4/3 L at its midpoint;
collapse every edge shorter than 4/5 L (unless that would make an edge longer than
4/3 L, break the link condition, or turn a triangle over); flip edges where that brings
the vertices' valences nearer 6 (4 on the boundary); move each vertex in the tangent
plane towards its neighbours' mean; and project every vertex back onto the input
surface (exact closest points, `jaxvalve.geometry.surface_query.SurfaceIndex`).  The
result has nearly equilateral triangles of edge about L lying on the input surface;
marching cubes' slivers are gone.

Open boundaries (the cut ends of a tube) are kept: boundary edges are split and
collapsed only along the boundary, no boundary edge is flipped, and boundary vertices
are relaxed along the boundary and projected back onto the input's boundary edges, so
the number of boundary loops and the Euler characteristic stay.
Host-side numpy and Python; lengths in mm."""
from __future__ import annotations

import numpy as np

from ..errors import MeshError, ParameterError
from .surface import _edges, _umbrella

__all__ = ["remesh"]


def remesh(points, triangles, edge_mm: float, *, iterations: int = 5,
           relax: float = 0.5):
    """The surface (points (P, 3), triangles (T, 3), consistently oriented, manifold)
    remeshed to edge length ``edge_mm`` (module docstring): (points (P', 3), triangles
    (T', 3)) on the input surface, with the input's orientation and boundary loops.
    relax: the tangential relaxation's step, in (0, 1]."""
    from ..geometry.surface_query import SurfaceIndex
    P0 = np.asarray(points, np.float64)
    T0 = np.asarray(triangles, np.int64)
    if P0.ndim != 2 or P0.shape[1] != 3 or T0.ndim != 2 or T0.shape[1] != 3 or not len(T0):
        raise MeshError(f"remesh needs points (P, 3) and triangles (T, 3); got "
                        f"{P0.shape} and {T0.shape}")
    if not np.all(np.isfinite(P0)):
        raise MeshError("remesh: the points hold NaN or inf")
    if T0.min() < 0 or T0.max() >= len(P0):
        raise MeshError(f"remesh: triangle indices must lie in [0, {len(P0) - 1}]")
    if not (np.isfinite(edge_mm) and edge_mm > 0):
        raise ParameterError(f"remesh edge_mm must be a positive length (mm); got {edge_mm!r}")
    if not (isinstance(iterations, int) and 1 <= iterations <= 50):
        raise ParameterError(f"remesh iterations must be an integer in [1, 50]; got "
                             f"{iterations!r}")
    if not (0 < relax <= 1):
        raise ParameterError(f"remesh relax must lie in (0, 1]; got {relax!r}")
    if _edges(T0)[1].max() > 2:
        raise MeshError("remesh needs a manifold surface: an edge is shared by three or "
                        "more triangles")
    index = SurfaceIndex(P0, T0)
    mesh = _Mesh(P0, T0)
    rim = _boundary_segments(P0, T0)
    hi, lo = 4.0 / 3.0 * edge_mm, 4.0 / 5.0 * edge_mm
    for _ in range(iterations):
        mesh.split_long(hi)
        mesh.collapse_short(lo, hi)
        mesh.flip_to_valence()
        mesh.relax(relax)
        alive = mesh.alive_vertices()
        inner, outer = alive & ~mesh.boundary, alive & mesh.boundary
        mesh.P[inner] = index.closest(mesh.P[inner], k=16)[1]
        if outer.any():
            mesh.P[outer] = _onto_segments(mesh.P[outer], rim)
    P, T = mesh.arrays()
    used = np.unique(T)
    new = np.full(len(P), -1)
    new[used] = np.arange(len(used))
    return P[used], new[T]


def _boundary_segments(P, T):
    """The boundary edges of the mesh as segments (K, 2, 3)."""
    e, count = _edges(T)
    return P[e[count == 1]]


def _onto_segments(x, seg, chunk=512):
    """The closest points (N, 3) of x (N, 3) on the segments seg (K, 2, 3)."""
    a, d = seg[:, 0], seg[:, 1] - seg[:, 0]
    dd = np.maximum(np.sum(d * d, axis=1), 1e-300)
    out = np.empty_like(x)
    for i in range(0, len(x), chunk):
        p = x[i:i + chunk, None, :]
        t = np.clip(np.sum((p - a) * d, axis=2) / dd, 0.0, 1.0)
        q = a + t[..., None] * d
        j = np.argmin(np.sum((p - q) ** 2, axis=2), axis=1)
        out[i:i + chunk] = q[np.arange(len(j)), j]
    return out


class _Mesh:
    """A triangle mesh under local edits: faces as lists with a live flag, each vertex's
    set of faces, boundary flags of the vertices."""

    def __init__(self, P, T):
        self.P = P.copy()
        self.F = [list(map(int, t)) for t in T]
        self.live = [True] * len(self.F)
        self.vf = [set() for _ in range(len(P))]
        for f, t in enumerate(self.F):
            for v in t:
                self.vf[v].add(f)
        self.boundary = np.zeros(len(P), bool)
        for a, b in self.edges():
            if len(self.edge_faces(a, b)) == 1:
                self.boundary[[a, b]] = True

    # -------------------------------------------------------------- queries
    def edges(self):
        return [tuple(map(int, x)) for x in _edges(self.arrays()[1])[0]]

    def edge_faces(self, a, b):
        return self.vf[a] & self.vf[b]

    def neighbours(self, v):
        return {u for f in self.vf[v] for u in self.F[f]} - {v}

    def alive_vertices(self):
        return np.asarray([len(s) > 0 for s in self.vf])

    def arrays(self):
        return self.P.copy(), np.asarray([t for t, ok in zip(self.F, self.live) if ok],
                                         np.int64)

    def _length(self, a, b):
        return float(np.linalg.norm(self.P[a] - self.P[b]))

    def _normal(self, t):
        P = self.P
        return np.cross(P[t[1]] - P[t[0]], P[t[2]] - P[t[0]])

    def _add_face(self, t):
        self.F.append(list(t))
        self.live.append(True)
        f = len(self.F) - 1
        for v in t:
            self.vf[v].add(f)
        return f

    # -------------------------------------------------------------- split
    def split_long(self, hi):
        long = [(self._length(a, b), a, b) for a, b in self.edges()]
        grow = [x for x in long if x[0] > hi]
        if not grow:
            return
        # room for the new vertices at once: np.vstack per vertex is quadratic
        start = len(self.P)
        self.P = np.vstack([self.P, np.zeros((len(grow), 3))])
        self.vf.extend(set() for _ in grow)
        self.boundary = np.append(self.boundary, np.zeros(len(grow), bool))
        m = start
        for _, a, b in sorted(grow, reverse=True):
            faces = self.edge_faces(a, b)
            if not faces or self._length(a, b) <= hi:
                continue
            self.P[m] = 0.5 * (self.P[a] + self.P[b])
            self.boundary[m] = len(faces) == 1
            for f in list(faces):
                t = self.F[f]
                t2 = [m if v == a else v for v in t]          # (m, b, c)
                self.F[f] = [m if v == b else v for v in t]   # (a, m, c)
                self.vf[b].discard(f)
                self.vf[m].add(f)
                self._add_face(t2)
            m += 1
        keep = m
        self.P, self.vf = self.P[:keep], self.vf[:keep]
        self.boundary = self.boundary[:keep]

    # -------------------------------------------------------------- collapse
    def collapse_short(self, lo, hi):
        short = sorted((self._length(a, b), a, b) for a, b in self.edges())
        for L, a, b in short:
            if L >= lo:
                break
            faces = self.edge_faces(a, b)
            if not faces or self._length(a, b) >= lo:
                continue
            self._try_collapse(a, b, faces, hi)

    def _try_collapse(self, a, b, faces, hi):
        tiny = 1e-12 * hi * hi               # twice a degenerate triangle's area
        ba, bb = self.boundary[a], self.boundary[b]
        on_boundary = len(faces) == 1
        if ba and bb and not on_boundary:
            return False                      # would pinch the surface across
        if ba and not bb:
            x = self.P[a]
        elif bb and not ba:
            x = self.P[b]
        else:
            x = 0.5 * (self.P[a] + self.P[b])
        opposite = {v for f in faces for v in self.F[f]} - {a, b}
        na, nb = self.neighbours(a), self.neighbours(b)
        if na & nb != opposite:               # the link condition
            return False
        for c in opposite:                    # keep every vertex at valence >= 3
            if len(self.neighbours(c)) - 1 < (2 if self.boundary[c] else 3):
                return False
        if len(na | nb) - 2 < (2 if (ba or bb) else 3):
            return False
        if any(np.linalg.norm(x - self.P[n]) > hi for n in (na | nb) - {a, b}):
            return False
        for f in (self.vf[a] | self.vf[b]) - faces:    # no triangle turned over
            t = self.F[f]
            q = [x if v in (a, b) else self.P[v] for v in t]
            n0, n1 = self._normal(t), np.cross(q[1] - q[0], q[2] - q[0])
            a0, a1 = np.linalg.norm(n0), np.linalg.norm(n1)
            if a1 <= tiny or (a0 > tiny and np.dot(n0, n1) <= 0.5 * a0 * a1):
                return False                  # degenerate, or turned by over 60 degrees
        for f in faces:
            self.live[f] = False
            for v in self.F[f]:
                self.vf[v].discard(f)
        for f in self.vf[b]:
            self.F[f] = [a if v == b else v for v in self.F[f]]
        self.vf[a] |= self.vf[b]
        self.vf[b] = set()
        self.P[a] = x
        self.boundary[a] = ba or bb
        return True

    # -------------------------------------------------------------- flip
    def flip_to_valence(self):
        val = {}

        def valence(v):
            if v not in val:
                val[v] = len(self.neighbours(v))
            return val[v]

        for a, b in self.edges():
            faces = self.edge_faces(a, b)
            if len(faces) != 2:
                continue
            f1, f2 = faces
            t1, t2 = self.F[f1], self.F[f2]
            # orient: in f1 the edge runs a -> b
            i = t1.index(a)
            if t1[(i + 1) % 3] != b:
                f1, f2, t1, t2 = f2, f1, t2, t1
            c = next(v for v in t1 if v not in (a, b))
            d = next(v for v in t2 if v not in (a, b))
            if d in self.neighbours(c):
                continue
            target = {v: 4 if self.boundary[v] else 6 for v in (a, b, c, d)}
            before = sum(abs(valence(v) - target[v]) for v in (a, b, c, d))
            after = (abs(valence(a) - 1 - target[a]) + abs(valence(b) - 1 - target[b])
                     + abs(valence(c) + 1 - target[c]) + abs(valence(d) + 1 - target[d]))
            if after >= before:
                continue
            n1, n2 = [a, d, c], [d, b, c]
            o = self._normal(t1) + self._normal(t2)
            m1, m2 = self._normal(n1), self._normal(n2)
            if np.dot(m1, o) <= 0 or np.dot(m2, o) <= 0 or np.dot(m1, m2) <= 0:
                continue
            self.F[f1], self.F[f2] = n1, n2
            self.vf[b].discard(f1)
            self.vf[a].discard(f2)
            self.vf[d].add(f1)
            self.vf[c].add(f2)
            for v in (a, b):
                val[v] = val[v] - 1
            for v in (c, d):
                val[v] = val[v] + 1

    # -------------------------------------------------------------- relax
    def relax(self, step):
        from scipy.sparse import coo_matrix
        _, T = self.arrays()
        n = len(self.P)
        mean = _umbrella(T, n) @ self.P
        N = np.zeros((n, 3))
        fn = np.cross(self.P[T[:, 1]] - self.P[T[:, 0]], self.P[T[:, 2]] - self.P[T[:, 0]])
        for k in range(3):
            np.add.at(N, T[:, k], fn)
        N /= np.maximum(np.linalg.norm(N, axis=1), 1e-300)[:, None]
        d = mean - self.P
        d -= np.sum(d * N, axis=1)[:, None] * N
        move = self.alive_vertices() & ~self.boundary
        self.P[move] += step * d[move]
        # boundary vertices: along the boundary, towards their two boundary neighbours
        e, count = _edges(T)
        b = e[count == 1]
        if len(b):
            r = np.concatenate([b[:, 0], b[:, 1]])
            c = np.concatenate([b[:, 1], b[:, 0]])
            B = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n)).tocsr()
            bdeg = np.asarray(B.sum(axis=1)).ravel()
            on = bdeg == 2
            bmean = (B @ self.P) / np.maximum(bdeg, 1)[:, None]
            self.P[on] += step * (bmean[on] - self.P[on])
