"""Point-triangle geometry for contact (pure JAX, single point / single triangle; vmap it).

Lengths are mm.  `p, a, b, c` are (3,) float64 positions; `a, b, c` are the vertices of an
oriented triangle whose unit normal is n = (b - a) x (c - a) / |(b - a) x (c - a)|.

The closest point follows Ericson, *Real-Time Collision Detection* (2005), sec. 5.1.5: the
Voronoi region of `p` (vertex a/b/c, edge ab/ac/bc, or face) is selected with `jnp.where`,
so every branch is evaluated; divisions are guarded (`_safe_div`) and the square root
uses the jax-md ``safe_mask`` pattern, so values and gradients are finite everywhere,
including at d = 0 (where the gradient of the unsigned distance is taken as 0) and for
degenerate triangles.
"""
from __future__ import annotations

import numpy as np
import jax.numpy as jnp

__all__ = [
    "safe_norm",
    "triangle_normal",
    "closest_point_barycentric",
    "point_triangle_distance",
    "signed_plane_distance",
    "point_triangle_distance_np",
]


def _safe_div(num, den):
    """num / den, and 0 (with zero gradient) where den == 0."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def safe_norm(v, axis=-1):
    """Euclidean norm along `axis`, with a finite (zero) gradient at v = 0 (safe_mask)."""
    s = jnp.sum(v * v, axis=axis)
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


def triangle_normal(a, b, c):
    """Unit normal (3,) of the oriented triangle (a, b, c); zero vector if degenerate."""
    n = jnp.cross(b - a, c - a)
    return n / jnp.where(safe_norm(n) > 0, safe_norm(n), 1.0)[..., None]


def closest_point_barycentric(p, a, b, c):
    """Barycentric coordinates (3,) of the point of triangle (a, b, c) closest to `p`.

    Robust in all seven Voronoi regions; the weights are >= 0 and sum to 1.
    """
    ab = b - a
    ac = c - a
    ap = p - a
    bp = p - b
    cp = p - c
    d1 = ab @ ap
    d2 = ac @ ap
    d3 = ab @ bp
    d4 = ac @ bp
    d5 = ab @ cp
    d6 = ac @ cp
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    in_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)

    den = va + vb + vc
    v = _safe_div(vb, den)
    w = _safe_div(vc, den)
    t_ab = _safe_div(d1, d1 - d3)
    t_ac = _safe_div(d2, d2 - d6)
    t_bc = _safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    one = jnp.ones_like(d1)
    zero = jnp.zeros_like(d1)

    bary = jnp.stack([1.0 - v - w, v, w])  # face region (lowest priority)
    # Ericson's test order is A, B, AB, C, AC, BC, face: apply in reverse so A wins ties.
    bary = jnp.where(in_bc, jnp.stack([zero, 1.0 - t_bc, t_bc]), bary)
    bary = jnp.where(in_ac, jnp.stack([1.0 - t_ac, zero, t_ac]), bary)
    bary = jnp.where(in_c, jnp.stack([zero, zero, one]), bary)
    bary = jnp.where(in_ab, jnp.stack([1.0 - t_ab, t_ab, zero]), bary)
    bary = jnp.where(in_b, jnp.stack([zero, one, zero]), bary)
    bary = jnp.where(in_a, jnp.stack([one, zero, zero]), bary)
    return bary


def point_triangle_distance(p, a, b, c):
    """Unsigned distance (mm) from `p` to the closed triangle (a, b, c).

    Returns ``(d, q, bary)``: distance (), closest point q (3,), barycentric coords (3,)
    of q.  Gradient w.r.t. p (and a, b, c) is finite everywhere; it is 0 at d = 0.
    """
    bary = closest_point_barycentric(p, a, b, c)
    q = bary[0] * a + bary[1] * b + bary[2] * c
    return safe_norm(p - q), q, bary


def signed_plane_distance(p, a, b, c):
    """Signed distance (mm) of `p` to the plane of triangle (a, b, c): (p - a) . n_T."""
    return (p - a) @ triangle_normal(a, b, c)


# ----------------------------------------------------------------- NumPy reference (tests)
def point_triangle_distance_np(p, a, b, c):
    """NumPy reference: distances (K,) from points p (K,3) to triangles a, b, c (K,3)."""
    p, a, b, c = (np.asarray(v, dtype=np.float64) for v in (p, a, b, c))
    ab, ac = b - a, c - a
    dot = lambda u, v: np.sum(u * v, axis=-1)  # noqa: E731
    d1, d2 = dot(ab, p - a), dot(ac, p - a)
    d3, d4 = dot(ab, p - b), dot(ac, p - b)
    d5, d6 = dot(ab, p - c), dot(ac, p - c)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        den = va + vb + vc
        v, w = vb / den, vc / den
    face = a + v[:, None] * ab + w[:, None] * ac
    conds = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    choices = [a, b, a + t_ab[:, None] * ab, c, a + t_ac[:, None] * ac,
               b + t_bc[:, None] * (c - b)]
    q = face
    for cond, ch in zip(reversed(conds), reversed(choices)):
        q = np.where(cond[:, None], ch, q)
    return np.linalg.norm(p - q, axis=-1)
