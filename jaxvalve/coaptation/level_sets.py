"""Array-module-generic numerics shared by the sharp (NumPy) and smooth (JAX) metrics.

Every function takes ``xp`` (``numpy`` or ``jax.numpy``) and ``eps``: ``eps=None`` is the
sharp version, a positive ``eps`` (mm) the smooth one.  Level-set values ``phi = g_c - d``
are in mm; the zone is ``phi > 0``.

Smoothing.  The sharp indicator 1[phi > 0] is replaced by H_eps(phi) = S(phi / eps), where
S is the CDF of the biweight kernel rho(t) = 15/16 (1 - t^2)^2 on [-1, 1]: S is C2, equals
0 for phi <= -eps and 1 for phi >= eps (compact support, so nodes farther than g_c + eps
contribute exactly nothing).  Integrals of H_eps(phi) over a triangle or a segment on which
phi is linear are computed *exactly*: with G(t) the sharp fraction where phi > t,

    mean_T H_eps(phi) = int rho_eps(t) G(t) dt,

G is piecewise quadratic (triangle) or linear (segment) in t with breakpoints at the nodal
values, so a 4-point Gauss-Legendre rule on each piece is exact.  As eps -> 0 this tends
to G(0), the exact clipped fraction ("marching triangles"), with error O(eps^2) where G is
C1 (always for triangles).
"""
from __future__ import annotations

import numpy as np

_GL_X, _GL_W = np.polynomial.legendre.leggauss(4)


def sdiv(num, den, xp):
    """num / den, and 0 where den == 0 (finite values and gradients)."""
    ok = den != 0
    return xp.where(ok, num / xp.where(ok, den, 1.0), 0.0)


def step(phi, eps, xp):
    """Zone indicator: 1[phi > 0] (eps None) or the C2 biweight step S(phi / eps)."""
    if eps is None:
        return (phi > 0).astype(np.float64)
    u = xp.clip(phi / eps, -1.0, 1.0)
    return (1.0 + u) ** 3 * ((3.0 * u - 9.0) * u + 8.0) / 16.0   # exactly 0 and 1 at -1, 1


def _kernel(t, eps, xp):
    u = xp.clip(t / eps, -1.0, 1.0)
    return (15.0 / 16.0) / eps * (1.0 - u * u) ** 2


_TINY = 1e-150   # floor of denominators on empty intervals (its square is still normal)


def _gl(lo, hi, f, xp):
    """int_lo^hi f(t) dt (0 where hi <= lo), exact for polynomials of degree <= 7.
    lo, hi (...); f maps t (..., 4) to values (..., 4)."""
    hi = xp.maximum(hi, lo)
    half = 0.5 * (hi - lo)
    t = (0.5 * (hi + lo))[..., None] + half[..., None] * _GL_X
    return half * xp.sum(_GL_W * f(t), axis=-1)


def tri_fraction(phi, eps, xp):
    """Fraction (...,) of each triangle where the linear field with nodal values phi
    (..., 3) is > 0 (sharp), or the exact mean of H_eps(phi) over it (smooth)."""
    p0, p1, p2 = phi[..., 0], phi[..., 1], phi[..., 2]
    a = xp.minimum(xp.minimum(p0, p1), p2)
    c = xp.maximum(xp.maximum(p0, p1), p2)
    b = (p0 + p1 + p2) - a - c                                   # median
    if eps is None:
        f1 = 1.0 - sdiv(a * a, (b - a) * (c - a), xp)
        f2 = sdiv(c * c, (c - a) * (c - b), xp)
        return xp.where(a >= 0, 1.0, xp.where(b >= 0, f1, xp.where(c > 0, f2, 0.0)))
    # G(t) = 1 - (t-a)^2 k1 on [a, b], (c-t)^2 k2 on [b, c]: both pieces at once
    k1 = 1.0 / xp.maximum((b - a) * (c - a), _TINY)
    k2 = 1.0 / xp.maximum((c - a) * (c - b), _TINY)
    lo = xp.stack([xp.maximum(a, -eps), xp.maximum(b, -eps)], axis=-1)
    hi = xp.stack([xp.minimum(b, eps), xp.minimum(c, eps)], axis=-1)
    A, C = a[..., None, None], c[..., None, None]
    K1, K2 = k1[..., None, None], k2[..., None, None]
    first = np.array([[True], [False]])

    def g(t):
        G = xp.where(first, 1.0 - (t - A) ** 2 * K1, (C - t) ** 2 * K2)
        return _kernel(t, eps, xp) * G

    return step(a, eps, xp) + xp.sum(_gl(lo, hi, g, xp), axis=-1)


def seg_fraction(p, q, eps, xp):
    """Fraction of a segment where the linear field from p to q is > 0 (sharp), or the
    exact mean of H_eps over it (smooth).  Symmetric in (p, q)."""
    lo, hi = xp.minimum(p, q), xp.maximum(p, q)
    if eps is None:
        return xp.where(lo >= 0, 1.0, xp.where(hi > 0, sdiv(hi, hi - lo, xp), 0.0))
    k = (1.0 / xp.maximum(hi - lo, _TINY))[..., None]
    H = hi[..., None]

    def g(t):
        return _kernel(t, eps, xp) * (H - t) * k

    return step(lo, eps, xp) + _gl(xp.maximum(lo, -eps), xp.minimum(hi, eps), g, xp)


def tri_moments(q, xp):
    """Exact mean (..., 2) and second moment (..., 2, 2) of q over each triangle (divided
    by its area), for vertex coordinates q (..., 3, 2): mean = sum q_k / 3,
    M2 = (sum q_k q_k^T + (sum q_k)(sum q_k)^T) / 12."""
    s = q.sum(axis=-2)
    m2 = xp.einsum("...ki,...kj->...ij", q, q)
    return s / 3.0, (m2 + s[..., :, None] * s[..., None, :]) / 12.0


def shift(v, k, xp):
    """v[..., (i + k) % 3] along the last axis of length 3."""
    if xp is np:
        return v[..., [(i + k) % 3 for i in range(3)]]
    return xp.roll(v, -k, axis=-1)


def chords(wv, uv, pv, w0, xp):
    """Intersection of the line {w = w0} with triangles projected to the (w, u) plane.

    wv, uv, pv: (..., 3) vertex coordinates w, u (mm) and level values phi; w0 (...).
    A vertex is on the right when w >= w0.  Returns (hit (...) bool, u1, u2, p1, p2):
    the chord's end points (u, phi) on the two edges leaving the lone vertex.
    """
    s = wv >= w0[..., None]
    s1, s2 = shift(s, 1, xp), shift(s, 2, xp)
    lone = (s != s1) & (s != s2)                       # at most one lone vertex
    if xp is np:
        return _chords_np(wv, uv, pv, w0, lone)
    w1, w2 = shift(wv, 1, xp), shift(wv, 2, xp)
    u1, u2 = shift(uv, 1, xp), shift(uv, 2, xp)
    p1, p2 = shift(pv, 1, xp), shift(pv, 2, xp)
    dw = w0[..., None] - wv
    t1 = sdiv(dw, w1 - wv, xp)
    t2 = sdiv(dw, w2 - wv, xp)
    t1 = xp.where(lone, t1, 0.0)
    t2 = xp.where(lone, t2, 0.0)

    def pick(v):
        return xp.sum(xp.where(lone, v, 0.0), axis=-1)

    return (xp.any(lone, axis=-1),
            pick(uv + t1 * (u1 - uv)), pick(uv + t2 * (u2 - uv)),
            pick(pv + t1 * (p1 - pv)), pick(pv + t2 * (p2 - pv)))


def _chords_np(wv, uv, pv, w0, lone):
    """NumPy fast path of `chords` (gathers the lone vertex instead of masking)."""
    hit = lone.any(axis=-1)
    k = lone.argmax(axis=-1)[..., None]

    def take(v, m):
        return np.take_along_axis(v, (k + m) % 3, axis=-1)[..., 0]

    w_, u_, p_ = take(wv, 0), take(uv, 0), take(pv, 0)
    out = [hit]
    t = []
    for m in (1, 2):
        den = take(wv, m) - w_
        t.append(np.where(hit, (w0 - w_) / np.where(hit, den, 1.0), 0.0))
    for v, v_ in ((uv, u_), (pv, p_)):
        out += [v_ + t[0] * (take(v, 1) - v_), v_ + t[1] * (take(v, 2) - v_)]
    return out[0], out[1], out[2], out[3], out[4]
