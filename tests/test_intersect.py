"""Tests for jaxvalve.valve.intersect: exact triangle-triangle test and leaflet checks."""
import itertools

import numpy as np
import pytest

from jaxvalve.errors import MeshError
from jaxvalve.valve.intersect import (candidate_triangle_pairs, leaflets_intersect,
                                self_intersections, triangles_intersect)

A = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# ------------------------------------------------------------------ slow references
def sat_reference(P, Q):
    """Separating-axis test for closed triangles: disjoint iff some axis among the two
    normals, the 9 edge-edge cross products and the 6 in-plane edge normals separates the
    projections strictly.  Complete for non-degenerate triangles (coplanar included)."""
    out = np.zeros(len(P), bool)
    for k in range(len(P)):
        p, q = P[k], Q[k]
        ep = [p[(i + 1) % 3] - p[i] for i in range(3)]
        eq = [q[(i + 1) % 3] - q[i] for i in range(3)]
        n1, n2 = np.cross(ep[0], ep[1]), np.cross(eq[0], eq[1])
        axes = [n1, n2] + [np.cross(a, b) for a in ep for b in eq]
        axes += [np.cross(n1, e) for e in ep] + [np.cross(n2, e) for e in eq]
        sep = False
        for ax in axes:
            if np.dot(ax, ax) < 1e-24:
                continue
            a, b = p @ ax, q @ ax
            if a.max() < b.min() or b.max() < a.min():
                sep = True
                break
        out[k] = not sep
    return out


def _seg_tri(p, q, a, b, c):
    """Closed segment pq (K,3) meets closed triangle abc, for segments not in its plane."""
    n = np.cross(b - a, c - a)
    dp, dq = np.sum((p - a) * n, -1), np.sum((q - a) * n, -1)
    ok = dp * dq <= 0
    den = np.where(dp != dq, dp - dq, 1.0)
    x = p + (dp / den)[:, None] * (q - p)
    s = [np.sum(np.cross(v1 - v0, x - v0) * n, -1) for v0, v1 in ((a, b), (b, c), (c, a))]
    inside = (s[0] >= 0) & (s[1] >= 0) & (s[2] >= 0)
    return ok & (dp != dq) & inside


def edge_reference(P, Q):
    """Non-coplanar triangles intersect iff an edge of one meets the other triangle."""
    hit = np.zeros(len(P), bool)
    for S, T in ((P, Q), (Q, P)):
        for i in range(3):
            hit |= _seg_tri(S[:, i], S[:, (i + 1) % 3], T[:, 0], T[:, 1], T[:, 2])
    return hit


def sheet(n, L, z=0.0, tilt=0.0, shift=(0.0, 0.0)):
    xs = np.linspace(0, L, n + 1)
    X, Y = np.meshgrid(xs + shift[0], xs + shift[1], indexing="ij")
    p = np.stack([X.ravel(), Y.ravel(), z + tilt * (X.ravel() - shift[0] - L / 2)], 1)
    t = []
    for i, j in itertools.product(range(n), range(n)):
        a = i * (n + 1) + j
        t += [[a, a + n + 1, a + n + 2], [a, a + n + 2, a + 1]]
    return p, np.array(t)


def two(s1, s2):
    (p1, t1), (p2, t2) = s1, s2
    x = np.concatenate([p1, p2])
    return x, np.concatenate([t1, t2 + len(p1)]), np.r_[np.zeros(len(p1), int),
                                                        np.ones(len(p2), int)]


def brute(x, tri, body):
    pairs = np.array([(i, j) for i in range(len(tri)) for j in range(i + 1, len(tri))
                      if body[tri[i, 0]] != body[tri[j, 0]]])
    hit = triangles_intersect(x[tri[pairs[:, 0]]], x[tri[pairs[:, 1]]])
    return {tuple(p) for p in pairs[hit].tolist()}


# ------------------------------------------------------------------ known pairs
@pytest.mark.parametrize("Q, expected, what", [
    (A + [0, 0, 1.0], False, "parallel planes"),
    (np.array([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.5, 0.2, 1.0]]), True, "piercing"),
    (np.array([[2, 0, -1], [2, 0, 1], [2, 1, 0.0]]), False, "plane crossed, apart"),
    (np.array([[0.9, 0.9, -1], [0.9, 0.9, 1], [2, 2, 0.0]]), False, "line misses"),
    (np.array([[1, 0, 0], [2, 0, 1], [2, 1, 0.0]]), True, "touch at a vertex"),
    (np.array([[0.25, 0.25, 0], [0.25, 0.25, 1], [1, 1, 1.0]]), True, "vertex on face"),
    (np.array([[0.5, 0, 0], [0.5, -1, 1], [0.5, -1, -1.0]]), True, "vertex on edge"),
    (np.array([[1.0 + 1e-9, 0, 0], [2, 0, 1], [2, 1, 0.0]]), False, "near miss"),
    (np.array([[0.2, 0.2, 0], [0.4, 0.2, 0], [0.2, 0.4, 0.0]]), True, "coplanar inside"),
    (np.array([[-1, -1, 0], [3, -1, 0], [-1, 3, 0.0]]), True, "coplanar containing"),
    (np.array([[0.5, 0.5, 0], [2, 2, 0], [2, 0.5, 0.0]]), True, "coplanar touching edge"),
    (np.array([[0.6, 0.6, 0], [2, 2, 0], [2, 0.6, 0.0]]), False, "coplanar apart"),
    (np.array([[0.5, -0.5, 0], [0.5, 0.5, 0], [1.5, 0, 0.0]]), True, "coplanar edges cross"),
    (np.array([[1, 0, 0], [2, 0, 0], [2, -1, 0.0]]), True, "coplanar shared vertex"),
    (np.array([[0.5, 0, 0], [2, 0, 0], [2, -1, 0.0]]), True, "coplanar collinear edges"),
    (np.array([[1.5, 0, 0], [2, 0, 0], [2, -1, 0.0]]), False, "collinear, disjoint"),
])
def test_known_pairs(Q, expected, what):
    assert triangles_intersect(A, Q) is expected, what
    assert triangles_intersect(Q, A) is expected, what + " (swapped)"
    assert sat_reference(A[None], Q[None])[0] == expected, what + " (reference)"


def test_random_pairs_match_references():
    rng = np.random.default_rng(3)
    K = 3000
    P = rng.uniform(0, 1, (K, 3, 3))
    Q = rng.uniform(0, 1, (K, 3, 3))
    Q[K // 2:] = P[K // 2:] + 0.3 * rng.standard_normal((K - K // 2, 3, 3))  # near pairs
    got = triangles_intersect(P, Q)
    assert 0.2 < got.mean() < 0.8
    np.testing.assert_array_equal(got, edge_reference(P, Q))
    np.testing.assert_array_equal(got[:400], sat_reference(P[:400], Q[:400]))


def test_random_coplanar_pairs_match_sat():
    rng = np.random.default_rng(4)
    K = 600
    P = rng.uniform(0, 1, (K, 3, 3))
    Q = rng.uniform(0, 1, (K, 3, 3))
    P[..., 2] = Q[..., 2] = 0.5
    # a random rotation keeps them coplanar up to rounding (snapping tolerance)
    R, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    got = triangles_intersect(P @ R.T, Q @ R.T)
    ref = sat_reference(P, Q)
    assert 0.2 < ref.mean() < 0.9
    np.testing.assert_array_equal(got, ref)


# ------------------------------------------------------------------ meshes
def test_sheets_crossing_and_not():
    x, tri, body = two(sheet(6, 3.0), sheet(6, 3.0, z=0.05, tilt=0.3, shift=(0.1, 0.2)))
    got = leaflets_intersect(x, tri, body)
    assert len(got) > 0
    assert {tuple(p) for p in got.tolist()} == brute(x, tri, body)
    # all hits straddle the crossing line x = 1.5 + 0.1 - 0.05 / 0.3 of the tilted sheet
    xc = 1.6 - 0.05 / 0.3
    for t1, t2 in got:
        for t in (t1, t2):
            assert x[tri[t], 0].min() - 1e-9 <= xc + 0.5 and x[tri[t], 0].max() >= xc - 0.5
    x2, tri2, body2 = two(sheet(6, 3.0), sheet(6, 3.0, z=1.0, tilt=0.3))
    assert len(leaflets_intersect(x2, tri2, body2)) == 0
    assert brute(x2, tri2, body2) == set()


def test_parallel_sheets_close_do_not_intersect():
    x, tri, body = two(sheet(8, 3.0), sheet(8, 3.0, z=0.19))
    x[:, 2] += 0.4 * np.sin(2.0 * x[:, 0]) * np.cos(1.5 * x[:, 1])   # wavy, 0.19 apart
    assert len(candidate_triangle_pairs(x, tri, body)) > 0   # the broad phase sees them
    assert len(leaflets_intersect(x, tri, body)) == 0


def test_self_intersections():
    x, tri, body = two(sheet(4, 2.0), sheet(4, 2.0, z=0.05, tilt=0.4))
    same = np.zeros_like(body)
    cross = self_intersections(x, tri, same)
    assert {tuple(p) for p in cross.tolist()} == brute(x, tri, body)
    assert len(self_intersections(*sheet(6, 2.0))) == 0       # neighbours are excluded
    assert len(self_intersections(x, tri, body)) == 0


def test_bad_inputs():
    with pytest.raises(MeshError, match="shape"):
        triangles_intersect(A, A[:2])
    x, tri = sheet(2, 1.0)
    with pytest.raises(MeshError, match="non-finite"):
        leaflets_intersect(np.where(np.arange(len(x))[:, None] == 0, np.nan, x), tri,
                           np.zeros(len(x), int))
    with pytest.raises(MeshError, match="indices"):
        leaflets_intersect(x, tri + 100, np.zeros(len(x), int))


def test_state_check_finds_a_leaflet_through_itself_on_any_law():
    """Two triangles of one leaflet, sharing no node, the second piercing the first, no
    edge folded (they share no edge) and both undeformed: `state_failure` reports
    leaflets_cross with and without self-contact (a FIRE closure on the penalty law had
    converged to such a state, found only by ipctk)."""
    import types
    from jaxvalve.valve.model import state_failure
    x = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0],
                  [0.5, 0.5, -1.0], [0.5, 0.5, 1.0], [0.5, 1.5, 0.0]])
    tri = np.array([[0, 1, 2], [3, 4, 5]])
    # the flat template: the same triangles laid apart in the plane (no strain)
    ref = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [5.0, -1.0], [5.0, 1.0], [6.0, 0.0]])
    valve = types.SimpleNamespace(triangles=tri, body=np.zeros(6, int), ref=ref,
                                  problem=types.SimpleNamespace(fixed=np.zeros(6, bool)))
    for sc in (False, True):
        assert state_failure(valve, x, self_contact=sc) == "leaflets_cross"
    apart = x + np.array([0.0, 0.0, 0.0])
    apart[3:, 0] += 3.0                     # moved clear of the first triangle
    for sc in (False, True):
        assert state_failure(valve, apart, self_contact=sc) is None


