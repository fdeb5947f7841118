"""Distance-type-aware squared distances for the barrier contact (IPC, Li et al. 2020).

Lengths in mm; every function takes (..., 3) arrays and broadcasts over leading axes.

The squared distance between a point and a triangle, or between two edges, is the
minimum over the features (vertices, edges, face interior) of the closest pair.  Which
feature is active (the *distance type*) is picked once, without gradient, and the
squared distance is then evaluated with that feature's closed form: point-plane,
point-line or point-point.  Each closed form is a rational function of the positions,
smooth where it is selected, so autodiff gives exact gradients and Hessians (IPC's
approach; no square root, no clamped parameter inside the derivative).

Point-triangle types (`PT_*`): the face, edge k (from vertex k to vertex k+1 mod 3) or
vertex k.  Edge-edge types (`edge_edge_type`): where the closest points lie, for each edge
an endpoint (0 or 1) or the interior; both interiors give the line-line distance, one
interior the point-line distance, none the point-point distance.  The squared distance
to a convex set is C1 in the positions, so the selected closed forms join with a
continuous gradient at every change of type.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .geometry import point_triangle_distance_np

__all__ = ["mollifier_d", "PT_FACE", "PT_EDGE", "PT_VERTEX", "point_triangle_type", "point_triangle_weights",
           "edge_edge_params",
           "point_triangle_distance2", "point_triangle_distance2_np",
           "edge_edge_type", "edge_edge_distance2",
           "line_line_distance2", "edge_edge_cross2", "mollifier",
           "segment_distance2_np", "mollifier_threshold"]

PT_FACE = 0
PT_EDGE = (1, 2, 3)      # edge (t0, t1), (t1, t2), (t2, t0)
PT_VERTEX = (4, 5, 6)    # vertex t0, t1, t2


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _regions(p, t0, t1, t2):
    """Ericson's (2005, sec. 5.1.5) dot products of p against the triangle: d1 ... d6 and
    the barycentric numerators va, vb, vc, without gradient."""
    p, t0, t1, t2 = (jax.lax.stop_gradient(v) for v in (p, t0, t1, t2))
    ab, ac = t1 - t0, t2 - t0
    ap, bp, cp = p - t0, p - t1, p - t2
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    return d1, d2, d3, d4, d5, d6, d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2


def _region_tests(d1, d2, d3, d4, d5, d6, va, vb, vc):
    """[(type code, test)] in order of precedence: the first true test names the feature
    of the triangle nearest the point."""
    return [(PT_VERTEX[0], (d1 <= 0) & (d2 <= 0)),
            (PT_VERTEX[1], (d3 >= 0) & (d4 <= d3)),
            (PT_EDGE[0], (vc <= 0) & (d1 >= 0) & (d3 <= 0)),
            (PT_VERTEX[2], (d6 >= 0) & (d5 <= d6)),
            (PT_EDGE[2], (vb <= 0) & (d2 >= 0) & (d6 <= 0)),
            (PT_EDGE[1], (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))]


def point_triangle_type(p, t0, t1, t2):
    """Active feature (int32, shape ...) of the triangle nearest to p: `PT_FACE`, an
    `PT_EDGE` or a `PT_VERTEX` code (Voronoi regions, Ericson 2005, sec. 5.1.5).  No
    gradient flows through it."""
    r = _regions(p, t0, t1, t2)
    code = jnp.full(jnp.shape(r[0]), PT_FACE, jnp.int32)
    for c, test in reversed(_region_tests(*r)):      # the first true test wins
        code = jnp.where(test, c, code)
    return code


def point_triangle_weights(p, t0, t1, t2):
    """Barycentric weights (..., 3) of the point of triangle (t0, t1, t2) nearest to p,
    without gradient: the squared distance is |p - sum_k w_k t_k|^2, and with w held
    fixed its gradient is the exact one (the closest point is a minimiser: envelope
    theorem), which is how the barrier's forces are evaluated."""
    d1, d2, d3, d4, d5, d6, va, vb, vc = r = _regions(p, t0, t1, t2)
    ratio = lambda a, b: a / jnp.where(b != 0, b, 1.0)
    zero, one = jnp.zeros_like(d1), jnp.ones_like(d1)
    v, w = ratio(vb, va + vb + vc), ratio(vc, va + vb + vc)
    out = jnp.stack([1 - v - w, v, w], -1)
    e01, e12, e20 = ratio(d1, d1 - d3), ratio(d4 - d3, d4 - d3 + d5 - d6), ratio(d2, d2 - d6)
    at = {PT_VERTEX[0]: (one, zero, zero), PT_VERTEX[1]: (zero, one, zero),
          PT_VERTEX[2]: (zero, zero, one), PT_EDGE[0]: (1 - e01, e01, zero),
          PT_EDGE[1]: (zero, 1 - e12, e12), PT_EDGE[2]: (1 - e20, zero, e20)}
    for c, test in reversed(_region_tests(*r)):
        out = jnp.where(test[..., None], jnp.stack(at[c], -1), out)
    return out


def _point_line2(p, a, b):
    e = b - a
    c = jnp.cross(p - a, e)
    ee = _dot(e, e)
    return _dot(c, c) / jnp.where(ee > 0, ee, 1.0)


def _along2(n, d):
    """(n . d)^2 / |n|^2: the squared length of d along the normal n (0 where n = 0)."""
    nn = _dot(n, n)
    s = _dot(n, d)
    return s * s / jnp.where(nn > 0, nn, 1.0)


def _point_plane2(p, t0, t1, t2):
    return _along2(jnp.cross(t1 - t0, t2 - t0), p - t0)


def _point_point2(p, q):
    d = p - q
    return _dot(d, d)


def point_triangle_distance2(p, t0, t1, t2, code=None):
    """Squared distance (mm^2, shape ...) from p to the triangle (t0, t1, t2), by the
    closed form of the active feature ``code`` (default `point_triangle_type`)."""
    code = point_triangle_type(p, t0, t1, t2) if code is None else code
    out = _point_plane2(p, t0, t1, t2)
    verts = (t0, t1, t2)
    for k in range(3):
        a, b = verts[k], verts[(k + 1) % 3]
        out = jnp.where(code == PT_EDGE[k], _point_line2(p, a, b), out)
        out = jnp.where(code == PT_VERTEX[k], _point_point2(p, a), out)
    return out


def edge_edge_cross2(ea0, ea1, eb0, eb1):
    """|(ea1 - ea0) x (eb1 - eb0)|^2 (mm^4): zero for parallel edges."""
    c = jnp.cross(ea1 - ea0, eb1 - eb0)
    return _dot(c, c)


def _segment_params(xp, ea0, ea1, eb0, eb1, rel_tol=1e-10):
    """Clamped closest-point parameters (s, t) in [0, 1] of two segments (Ericson 2005,
    sec. 5.1.9), for the array module xp (jax.numpy or numpy).  Nearly parallel edges
    (|u x v|^2 <= rel_tol |u|^2 |v|^2) take s = 0."""
    dot = ((lambda a, b: np.einsum("...i,...i->...", a, b)) if xp is np
           else (lambda a, b: xp.sum(a * b, axis=-1)))
    u, v, r = ea1 - ea0, eb1 - eb0, ea0 - eb0
    a, e, f = dot(u, u), dot(v, v), dot(v, r)
    c, b = dot(u, r), dot(u, v)
    den = a * e - b * b
    a_s = xp.where(a > 0, a, 1.0)
    e_s = xp.where(e > 0, e, 1.0)
    par = den <= rel_tol * a * e
    s = xp.clip(xp.where(par, 0.0, (b * f - c * e) / xp.where(par, 1.0, den)), 0.0, 1.0)
    t = (b * s + f) / e_s
    s = xp.where(t < 0, xp.clip(-c / a_s, 0.0, 1.0),
                 xp.where(t > 1, xp.clip((b - c) / a_s, 0.0, 1.0), s))
    return s, xp.clip(t, 0.0, 1.0)


def edge_edge_params(ea0, ea1, eb0, eb1, rel_tol=1e-10):
    """The closest points' parameters (s, t) in [0, 1] of two segments, without gradient
    (as `point_triangle_weights`: with them fixed, the gradient of the squared distance is
    the exact one)."""
    ea0, ea1, eb0, eb1 = (jax.lax.stop_gradient(v) for v in (ea0, ea1, eb0, eb1))
    return _segment_params(jnp, ea0, ea1, eb0, eb1, rel_tol)


def edge_edge_type(ea0, ea1, eb0, eb1, rel_tol=1e-10):
    """Where the closest points of two segments lie: (ka, kb) int32 arrays, each 0 or 1
    (that endpoint) or 2 (the interior), from `edge_edge_params`.  No gradient."""
    s, t = edge_edge_params(ea0, ea1, eb0, eb1, rel_tol)
    code = lambda q: jnp.where(q <= 0, 0, jnp.where(q >= 1, 1, 2)).astype(jnp.int32)
    return code(s), code(t)


def edge_edge_distance2(ea0, ea1, eb0, eb1, types=None):
    """Squared distance (mm^2) between two segments by the closed form of their distance
    type ``types`` = (ka, kb) (default `edge_edge_type`)."""
    ka, kb = edge_edge_type(ea0, ea1, eb0, eb1) if types is None else types
    pa = jnp.where((ka == 0)[..., None], ea0, ea1)
    pb = jnp.where((kb == 0)[..., None], eb0, eb1)
    out = _point_point2(pa, pb)
    out = jnp.where((ka < 2) & (kb == 2), _point_line2(pa, eb0, eb1), out)
    out = jnp.where((ka == 2) & (kb < 2), _point_line2(pb, ea0, ea1), out)
    return jnp.where((ka == 2) & (kb == 2), line_line_distance2(ea0, ea1, eb0, eb1), out)


def line_line_distance2(ea0, ea1, eb0, eb1):
    """Squared distance (mm^2) between the lines through the two edges."""
    return _along2(jnp.cross(ea1 - ea0, eb1 - eb0), ea0 - eb0)


#: The parallel-edge threshold's coefficient: eps_x = MOLLIFIER_C |ea|^2 |eb|^2, i.e. edges
#: closer to parallel than sin^2(angle) = MOLLIFIER_C are mollified: ten times IPC's, so
#: that the nearly parallel free edges of coapted leaflets do not cross the whole mollified
#: range in one small step (docs/barrier-contact.md, "Mollifier").
MOLLIFIER_C = 1e-2


def mollifier_threshold(la, lb):
    """The parallel-edge threshold eps_x = MOLLIFIER_C |ea|^2 |eb|^2 (mm^4) from the edges'
    rest lengths la, lb (mm)."""
    return MOLLIFIER_C * la * la * lb * lb


def mollifier(x, eps_x):
    """The edge-edge mollifier m(x) = 1 - (1 - x / eps_x)^3 for x < eps_x, else 1, with
    x = `edge_edge_cross2`: zero for parallel edges, where the line-line distance is
    undefined, and C2 at the threshold (m' = m'' = 0 there).  IPC's (2 - x / eps_x) x /
    eps_x is only C1 there, and its jump in m'' is a jump in the Hessian of every pair
    that crosses the threshold."""
    return mollifier_d(x, eps_x)[0]


def mollifier_d(x, eps_x):
    """(m(x), m'(x)) of `mollifier` (the barrier's hand-written forces)."""
    q = jnp.clip(1.0 - x / eps_x, 0.0, 1.0)
    return 1.0 - q ** 3, 3.0 * q * q / eps_x


# ------------------------------------------------------------------- NumPy (host side)
def point_triangle_distance2_np(p, t0, t1, t2):
    """Squared distance (mm^2) from points to triangles (NumPy, (K, 3) arrays): the
    square of the project's one point-triangle distance (`geometry.point_triangle_distance_np`)."""
    return point_triangle_distance_np(p, t0, t1, t2) ** 2


def segment_distance2_np(ea0, ea1, eb0, eb1):
    """Squared distance (mm^2) between segments (NumPy, (..., 3) arrays), by the clamped
    closest points (`_segment_params`)."""
    ea0, ea1, eb0, eb1 = (np.asarray(v, float) for v in (ea0, ea1, eb0, eb1))
    s, t = _segment_params(np, ea0, ea1, eb0, eb1, 1e-14)
    d = ea0 - eb0 + s[..., None] * (ea1 - ea0) - t[..., None] * (eb1 - eb0)
    return np.einsum("...i,...i->...", d, d)
