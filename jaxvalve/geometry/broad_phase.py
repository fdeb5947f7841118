"""Broad phase: which pairs of bounding balls come within a gap of each other (the
barrier contact's pair lists, `jaxvalve.contact.ipc_pairs`, the crossing check,
`jaxvalve.valve.intersect`, and the coaptation metrics' node-triangle candidates,
`jaxvalve.coaptation.gaps`).

One k-d tree query with the largest radius lists every pair within ``gap + 2 max r``,
which is right while the elements are of one size.  A ballooned element (a leaflet
running away past its inflation limit stretches some edges to 10-15 mm on a 2 mm mesh)
then makes every pair a candidate: 1.19 million edge pairs instead of 35 000-150 000 on
the soft neo-Hookean valve of the stress tests, and the lists grow as the square of the
mesh.  `ball_pairs` sorts the balls into size classes by octave of radius above the
median (class 0 up to twice the median) and queries each pair of classes with the sum of
their own largest radii, so that a large ball widens only the queries of its own class.

The result is a superset for the caller's exact test: every pair of balls within the
gap, and some farther ones (up to the largest radii of their two classes), in no
particular order.  It suits element balls, of one size but for a few outliers; radii
spread evenly over several octaves (per-point search radii) are each queried with up to
twice their own, and a per-point query serves them better (`jaxvalve.coaptation.gaps`,
its exact-everywhere branch: 4.7x slower through this function).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ParameterError

__all__ = ["ball_pairs"]

#: relative widening of each k-d tree query, so that rounding in the tree's distances
#: cannot drop a pair at the edge of its ball
_SLACK = 1e-9


def _groups(r):
    """[(indices (k,) or None for all, largest radius)] per non-empty size class of the
    radii r (K,): class 0 up to twice the median radius, then one class per octave."""
    big = float(np.max(r)) if r.size else 0.0
    r0 = float(np.median(r)) if r.size else 0.0
    if not r0 > 0:
        r0 = big
    if big <= 2.0 * r0:              # one size: one class, one query
        return [(None, big)]
    lev = np.ceil(np.log2(np.maximum(r, 1e-300) / (2.0 * r0)))
    lev = np.maximum(lev, 0).astype(np.int64)
    return [(np.flatnonzero(lev == k), float(np.max(r[lev == k]))) for k in np.unique(lev)]


def _cross(ca, ia, cb, ib, radius):
    """(K, 2) [i, j] of a[ia] and b[ib] (None: all) with centres within radius."""
    m = cKDTree(ca if ia is None else ca[ia]).sparse_distance_matrix(
        cKDTree(cb if ib is None else cb[ib]), radius, output_type="ndarray")
    i, j = m["i"].astype(np.int64, copy=False), m["j"].astype(np.int64, copy=False)
    return np.column_stack([i if ia is None else ia[i], j if ib is None else ib[j]])


def ball_pairs(ca, ra, cb=None, rb=None, gap: float = 0.0) -> np.ndarray:
    """(K, 2) int64 [i, j]: every pair of balls, centres c (K, 3) mm and radii r (K,) mm
    (scalars broadcast), with |c_i - c_j| <= gap + r_i + r_j, and possibly pairs a
    little farther (module docstring).  Pairs of a with b, or, with cb None, of a with
    itself (i < j).  In no particular order: a caller that needs one sorts what it keeps."""
    ca = np.asarray(ca, float).reshape(-1, 3)
    ra = np.broadcast_to(np.asarray(ra, float), ca.shape[:1])
    self_pairs = cb is None
    cb = ca if self_pairs else np.asarray(cb, float).reshape(-1, 3)
    rb = ra if self_pairs else np.broadcast_to(np.asarray(rb, float), cb.shape[:1])
    gap = float(gap)
    if not (np.isfinite(gap) and gap >= 0):
        raise ParameterError(f"gap must be a finite length >= 0 (mm); got {gap!r}")
    for name, c, r in (("a", ca, ra), ("b", cb, rb)):
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise ParameterError(f"ball_pairs needs finite centres and finite radii >= 0 "
                                 f"(set {name})")
    if len(ca) == 0 or len(cb) == 0:
        return np.zeros((0, 2), np.int64)
    ga = _groups(ra)
    gb = ga if self_pairs else _groups(rb)
    found = []
    for k, (ia, Ra) in enumerate(ga):
        for m, (ib, Rb) in enumerate(gb):
            radius = (gap + Ra + Rb) * (1.0 + _SLACK)
            if not self_pairs:
                found.append(_cross(ca, ia, cb, ib, radius))
            elif m == k:         # ia ascending: local i < j is global i < j
                p = cKDTree(ca if ia is None else ca[ia]).query_pairs(
                    radius, output_type="ndarray").reshape(-1, 2)
                found.append(p if ia is None else ia[p])
            elif m > k:
                p = _cross(ca, ia, ca, ib, radius)
                found.append(np.column_stack([p.min(axis=1), p.max(axis=1)]))
    out = found[0] if len(found) == 1 else np.concatenate(found)
    return out.astype(np.int64, copy=False)
