"""Independent checks of a deformed membrane state (NumPy only; no code shared with the
solvers, the materials or the contact law).

`triangle_checks(ref, triangles, x)` measures, for every triangle of a mesh whose flat
template ``ref`` (N, 2) is the stress-free state, the deformed-to-reference area ratio
J = a / A = sqrt(det C) and the principal stretches, and for every interior edge the
cosine between the unit normals of its two triangles:

* a **collapsed** triangle has J below ``j_min`` (default 0.05: a triangle squashed to a
  twentieth of its area, far outside anything a membrane under pressure reaches);
* an **inverted** (folded-over) triangle has turned over its neighbour: the normals of
  two triangles that share an edge point more than ``fold_deg`` (default 150 degrees)
  apart.  A membrane triangle in 3D has no sign of its own (its area is always >= 0),
  so orientation is judged against the neighbours: a consistently oriented mesh that
  folds over an edge shows as nearly opposite normals on that edge.  The closed valve's
  sharpest fold at h = 2 mm (the free edge bent over at the centre) stays below 100
  degrees in the symmetric benchmark root.  States of the barrier law with self-contact
  are checked with fold_deg = 180 (no fold bound): there a sharp crease is held open by
  contact, not turned over (`jaxvalve.valve.model.state_failure`).

`inverted_triangles` returns the offending triangles; `CheckReport.ok` says whether all
passed.  Lengths in mm.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..geometry.mesh import cauchy_green_np

__all__ = ["CheckReport", "triangle_checks", "inverted_triangles", "interior_edges",
           "fold_angles",
           "gent_invariant", "crossing_depth"]

J_MIN = 0.05
FOLD_DEG = 150.0


@dataclasses.dataclass(frozen=True)
class CheckReport:
    """Result of `triangle_checks`.

    min_J, max_J: extreme area ratios; min_stretch, max_stretch: extreme principal
    stretches; collapsed: indices of triangles with J < j_min; folded: (K, 2) triangle
    pairs sharing an edge whose normals are more than fold_deg apart; max_fold_deg: the
    largest angle between the normals of two neighbours (degrees); finite: every
    coordinate finite."""

    min_J: float
    max_J: float
    min_stretch: float
    max_stretch: float
    collapsed: np.ndarray
    folded: np.ndarray
    max_fold_deg: float
    finite: bool

    @property
    def ok(self) -> bool:
        return bool(self.finite and len(self.collapsed) == 0 and len(self.folded) == 0)

    def describe(self) -> str:
        if not self.finite:
            return "non-finite coordinates"
        bits = []
        if len(self.collapsed):
            bits.append(f"{len(self.collapsed)} collapsed triangles (min J {self.min_J:.3g})")
        if len(self.folded):
            bits.append(f"{len(self.folded)} folded edges (max {self.max_fold_deg:.0f} deg)")
        return "; ".join(bits) if bits else "ok"


def interior_edges(triangles):
    """(E, 2) pairs of triangles sharing an edge (each interior edge once)."""
    tri = np.asarray(triangles)
    m = len(tri)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    owner = np.tile(np.arange(m), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    return np.stack([owner[:-1][same], owner[1:][same]], axis=1)


def gent_invariant(ref, triangles, x):
    """I1 + 1/I2 - 3 per triangle (M,): the Gent model stays admissible while it is < Jm."""
    C = cauchy_green_np(x, triangles, ref)
    tr = C[:, 0, 0] + C[:, 1, 1]
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(det > 0, tr + 1.0 / np.where(det > 0, det, 1.0) - 3.0, np.inf)


def fold_angles(triangles, x):
    """(pairs (E, 2) of triangles sharing an edge (`interior_edges`), the angle between
    their normals (E,) degrees at positions x (N, 3), True (E,) where both triangles have
    a normal (non-zero area))."""
    tri = np.asarray(triangles)
    y = np.asarray(x, np.float64)[tri]
    n = np.cross(y[:, 1] - y[:, 0], y[:, 2] - y[:, 0])
    nn = np.linalg.norm(n, axis=1)
    n = n / np.where(nn > 0, nn, 1.0)[:, None]
    pairs = interior_edges(tri)
    cos = np.sum(n[pairs[:, 0]] * n[pairs[:, 1]], axis=1)
    good = (nn[pairs[:, 0]] > 0) & (nn[pairs[:, 1]] > 0)
    return pairs, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), good


def triangle_checks(ref, triangles, x, *, j_min: float = J_MIN,
                    fold_deg: float = FOLD_DEG) -> CheckReport:
    """Collapsed and folded-over triangles of the state x (N, 3) of the mesh (ref (N, 2),
    triangles (M, 3), consistently oriented).  See the module docstring."""
    x = np.asarray(x, np.float64)
    tri = np.asarray(triangles)
    empty = np.zeros((0,), int)
    if not np.all(np.isfinite(x)):
        return CheckReport(math.nan, math.nan, math.nan, math.nan, empty,
                           np.zeros((0, 2), int), math.nan, False)
    C = cauchy_green_np(x, tri, ref)
    tr = C[:, 0, 0] + C[:, 1, 1]
    det = np.maximum(C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0], 0.0)
    J = np.sqrt(det)
    disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    lam_hi = np.sqrt(0.5 * tr + disc)
    lam_lo = np.sqrt(np.maximum(0.5 * tr - disc, 0.0))
    pairs, angle, good = fold_angles(tri, x)
    folded = pairs[good & (angle > fold_deg)]
    return CheckReport(min_J=float(J.min()), max_J=float(J.max()),
                       min_stretch=float(lam_lo.min()), max_stretch=float(lam_hi.max()),
                       collapsed=np.flatnonzero(J < j_min), folded=folded,
                       max_fold_deg=float(angle[good].max()) if good.any() else 0.0,
                       finite=True)


def inverted_triangles(ref, triangles, x, **kw) -> np.ndarray:
    """Indices of the triangles that are collapsed or take part in a fold-over."""
    rep = triangle_checks(ref, triangles, x, **kw)
    return np.unique(np.concatenate([rep.collapsed, rep.folded.ravel()])).astype(int)


def crossing_depth(x, triangles, pairs) -> float:
    """How deep the crossing triangle pairs (P, 2) of the state x (N, 3) cut into each
    other (mm; 0 for no pairs): per pair, for each triangle the largest distance of its
    vertices on the minority side of the other's plane, the smaller of the two; the
    largest over pairs.  Two sheets in contact whose faces graze through each other
    between nodes give about the contact layer (0.1-0.2 mm); a leaflet pushed through
    another gives its depth."""
    pairs = np.asarray(pairs).reshape(-1, 2)
    if len(pairs) == 0:
        return 0.0
    x = np.asarray(x, np.float64)
    T = x[np.asarray(triangles)]

    def poke(A, B):
        n = np.cross(B[:, 1] - B[:, 0], B[:, 2] - B[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        s = np.einsum("kij,kj->ki", A - B[:, :1], n)
        pos, neg = (s > 0).sum(1), (s < 0).sum(1)
        minority = np.where((pos <= neg)[:, None], np.where(s > 0, s, 0.0),
                            np.where(s < 0, -s, 0.0))
        return minority.max(axis=1)

    A, B = T[pairs[:, 0]], T[pairs[:, 1]]
    return float(np.max(np.minimum(poke(A, B), poke(B, A))))
