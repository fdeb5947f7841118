"""Candidate points for the three-leaflet (central) zone and the free-edge fallback.

Shared by the sharp (NumPy, eps None) and smooth (JAX, eps > 0) metrics.  For a triple
(i; j, k) the set S_ijk = {p on leaflet i: d_ij(p) < g_c and d_ik(p) < g_c}, with both
distances interpolated linearly on i's triangles, is clipped exactly by the two level
lines; its extreme axial points are vertices of the clipped polygons, i.e. one of

* a node of i inside both zones;
* a crossing of one level line with an edge of i, inside the other zone;
* the intersection of the two level lines inside a triangle of i.

Each candidate gets a weight: 1/0 (sharp) or a smooth membership (smooth): nodes
H(phi_j) H(phi_k); edge crossings |H(phi_X(p)) - H(phi_X(q))| H(phi_Y(c)) with the
crossing point c placed at the exact smoothed fraction from the end with larger phi_X;
interior points cut_j cut_k prod_m H(lambda_m h_m), where cut_X = max - min of H(phi_X)
over the triangle's nodes (1 when the level line X crosses it), lambda_m barycentric and
h_m the altitude, so lambda_m h_m is the distance to edge m in mm.  All weights tend to
the sharp ones and the points to the polygon vertices as eps -> 0.
"""
from __future__ import annotations

import numpy as np

from .level_sets import seg_fraction, sdiv, step


def _norm(v, xp):
    s = xp.sum(v * v, axis=-1)
    pos = s > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, s, 1.0)), 0.0)


def _spread3(v, xp):
    """max - min over the last axis of v (..., 3), as half the sum of the three pairwise
    differences' magnitudes: the same number, with a gradient that is 0 where the three
    are equal.  (Through max and min reductions, the gradient of the smooth h_E and h_c
    at triangles whose three step values tie came out NaN when compiled at XLA's LLVM
    optimisation level 0, while finite at the default level.)"""
    a, b, c = v[..., 0], v[..., 1], v[..., 2]
    return 0.5 * (xp.abs(a - b) + xp.abs(b - c) + xp.abs(c - a))


def central_index(topo):
    """Flat index arrays of all candidates over all triples (i; j, k), as a tuple
    (nodes (Qn,), nodes' j, k; edges (Qe, 2), edges' j, k; tris (Qt, 3), tris' j, k)."""
    cols = [[], [], [], [], [], [], [], [], []]
    for i, j, k in topo.triples:
        for base, arr in ((0, topo.nodes[i]), (3, topo.edges[i]), (6, topo.tris[i])):
            cols[base].append(arr)
            cols[base + 1].append(np.full(arr.shape[0], j))
            cols[base + 2].append(np.full(arr.shape[0], k))
    shapes = ((0,), (0,), (0,), (0, 2), (0,), (0,), (0, 3), (0,), (0,))
    return tuple(np.concatenate(c).astype(np.int64) if c else np.zeros(sh, np.int64)
                 for c, sh in zip(cols, shapes))


def central_candidates(x, phi, index, eps, xp):
    """Candidate points (Q, 3) mm and weights (Q,) of the three-leaflet zone.

    x (N, 3); phi (N, L) level values g_c - d; index from `central_index`.  The step
    function is applied in two batched calls (compact graphs for JAX)."""
    nodes, nj, nk, edges, ej, ek, tris, tj, tk = index
    a, b = edges[:, 0], edges[:, 1]
    n, e, t = nodes.shape[0], a.shape[0], tris.shape[0]
    va = xp.stack([phi[a, ej], phi[a, ek]])               # (2, e): level j, level k
    vb = xp.stack([phi[b, ej], phi[b, ek]])
    fx, fy = phi[tris, tj[:, None]], phi[tris, tk[:, None]]     # (t, 3)
    H = step(xp.concatenate([phi[nodes, nj], phi[nodes, nk], va.ravel(), vb.ravel(),
                             fx.ravel(), fy.ravel()]), eps, xp)
    o = np.cumsum([0, n, n, 2 * e, 2 * e, 3 * t, 3 * t])
    hn_j, hn_k, ha, hb, hx, hy = (H[o[m]:o[m + 1]] for m in range(6))
    ha, hb = ha.reshape(2, e), hb.reshape(2, e)
    hx, hy = hx.reshape(t, 3), hy.reshape(t, 3)
    # edges, both level sets X at once (row 0: X = j, Y = k; row 1: X = k, Y = j)
    first = va >= vb
    tau = seg_fraction(xp.where(first, va, vb), xp.where(first, vb, va), eps, xp)
    xa, xb = x[a], x[b]
    x_hi = xp.where(first[..., None], xa, xb)
    x_lo = xp.where(first[..., None], xb, xa)
    pe = x_hi + tau[..., None] * (x_lo - x_hi)            # (2, e, 3)
    ya, yb = va[::-1], vb[::-1]
    y_hi = xp.where(first, ya, yb)
    y = y_hi + tau * (xp.where(first, yb, ya) - y_hi)
    # interior intersections of the two level lines
    cv = xp.cross(fx, fy)
    sc = xp.sum(cv, axis=-1)
    xt = x[tris]
    area2 = _norm(xp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]), xp)
    # nearly parallel level lines meet far outside the triangle: no candidate.  The test
    # is relative to |fx| |fy|, not to |cv|: for parallel or equal fields, cv is rounding
    # error only (compiled code contracts a*b - c*d into FMAs, so fx x fx need not be 0),
    # and cv / sc would be a ratio of rounding errors with derivatives ~1/sc (~1e18)
    ok = (xp.abs(sc) > 1e-9 * _norm(fx, xp) * _norm(fy, xp)) & (area2 > 0)
    lam = sdiv(cv, xp.where(ok, sc, 0.0)[:, None], xp)
    pt = xp.sum(lam[..., None] * xt, axis=1)
    if eps is None:
        hy_e = step(y.ravel(), eps, xp).reshape(2, e)
        inside = xp.all(lam >= 0, axis=-1).astype(np.float64)
    else:
        opp = _norm(xp.roll(xt, -2, axis=1) - xp.roll(xt, -1, axis=1), xp)
        H2 = step(xp.concatenate([y.ravel(), (lam * sdiv(area2[:, None], opp, xp)).ravel()]),
                  eps, xp)
        hy_e = H2[: 2 * e].reshape(2, e)
        inside = xp.prod(H2[2 * e:].reshape(t, 3), axis=-1)
    cut = _spread3(hx, xp) * _spread3(hy, xp)             # both level lines cross T
    pts = xp.concatenate([x[nodes], pe.reshape(-1, 3), pt])
    wts = xp.concatenate([hn_j * hn_k, (xp.abs(ha - hb) * hy_e).ravel(),
                          xp.where(ok, cut * inside, 0.0)])
    return pts, wts


def free_edge_closest(x, free_segments, axis, origin, xp):
    """For each free-edge segment (F, 2): its point closest to the axis line (F, 3) and
    that point's distance to the axis (F,) in mm (exact, clamped to the segment)."""
    p, q = x[free_segments[:, 0]], x[free_segments[:, 1]]

    def perp(v):
        v = v - origin
        return v - (v @ axis)[:, None] * axis

    pp, dq = perp(p), perp(q) - perp(p)
    tau = xp.clip(sdiv(-xp.sum(pp * dq, axis=-1), xp.sum(dq * dq, axis=-1), xp), 0.0, 1.0)
    c = p + tau[:, None] * (q - p)
    return c, _norm(pp + tau[:, None] * dq, xp)
