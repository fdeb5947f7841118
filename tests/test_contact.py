"""Tests for jaxvalve.contact: point-triangle geometry and the paper's law (2.2)."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp
from scipy.optimize import minimize

from jaxvalve.errors import ParameterError
from jaxvalve.contact import (
    PaperContact, point_triangle_distance, point_triangle_distance_np,
    signed_plane_distance, vicinity_threshold,
)
from sheets import combine, grid_sheet

RNG = np.random.default_rng(0)
MMHG = 1.33322e-4  # MPa


# ------------------------------------------------------------------------ mesh helpers
def crumpled_bodies(rng, nb=2, n=7, L=3.5):
    sheets = []
    for k in range(nb):
        p, t = grid_sheet(n, L, z=0.15 * k, jitter=0.2, rng=rng)
        p[:, 2] += 0.3 * np.sin(1.3 * p[:, 0] + k) * np.cos(0.9 * p[:, 1])
        p[:, 2] += 0.05 * rng.standard_normal(len(p))
        sheets.append((p, t))
    return combine(*sheets)


def pair_set(nbrs):
    pr = np.asarray(nbrs.pairs)[np.asarray(nbrs.valid)]
    return [tuple(r) for r in pr.tolist()]


# ------------------------------------------------------------------------ geometry
TRI = np.array([[0.0, 0.0, 0.0], [2.0, 0.2, 0.1], [0.5, 1.7, -0.2]])


def _region_points():
    a, b, c = TRI
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    pts = {}
    cen = (a + b + c) / 3
    pts["face"] = cen + 0.3 * n
    for name, v in (("A", a), ("B", b), ("C", c)):
        pts[name] = v + 0.5 * (v - cen) / np.linalg.norm(v - cen) - 0.2 * n
    for name, (u, v, w) in (("AB", (a, b, c)), ("BC", (b, c, a)), ("AC", (a, c, b))):
        mid = 0.5 * (u + v)
        e = (v - u) / np.linalg.norm(v - u)
        out = np.cross(e, n)
        if out @ (w - mid) > 0:
            out = -out
        pts[name] = mid + 0.4 * out + 0.25 * n
    return pts


def _scipy_distance(p, a, b, c):
    """Reference: dense barycentric sampling, then SLSQP refinement."""
    s = np.linspace(0, 1, 81)
    S, T = np.meshgrid(s, s)
    keep = S + T <= 1
    S, T = S[keep], T[keep]
    q = a + S[:, None] * (b - a) + T[:, None] * (c - a)
    k = np.argmin(np.linalg.norm(q - p, axis=1))
    f = lambda st: np.sum((a + st[0] * (b - a) + st[1] * (c - a) - p) ** 2)  # noqa: E731
    res = minimize(f, [S[k], T[k]], method="SLSQP", bounds=[(0, 1), (0, 1)],
                   constraints=[{"type": "ineq", "fun": lambda st: 1 - st[0] - st[1]}],
                   options={"ftol": 1e-15, "maxiter": 200})
    return np.sqrt(res.fun)


_dist_grad = jax.jit(jax.grad(lambda *v: point_triangle_distance(*v)[0], argnums=(0, 1, 2, 3)))


@pytest.mark.parametrize("region", ["face", "A", "B", "C", "AB", "BC", "AC"])
def test_point_triangle_distance_all_regions(region):
    p = _region_points()[region]
    a, b, c = TRI
    d, q, bary = jax.jit(point_triangle_distance)(*map(jnp.asarray, (p, a, b, c)))
    assert abs(float(d) - _scipy_distance(p, a, b, c)) < 1e-6
    assert np.allclose(q, bary @ TRI) and abs(float(jnp.sum(bary)) - 1) < 1e-12
    zero = {"face": 0, "A": 2, "B": 2, "C": 2, "AB": 1, "BC": 1, "AC": 1}[region]
    assert int(np.sum(np.asarray(bary) == 0)) == zero
    assert abs(point_triangle_distance_np(p[None], a[None], b[None], c[None])[0] - d) < 1e-12
    # gradient equals central finite differences w.r.t. all 12 coordinates
    grads = _dist_grad(*[jnp.asarray(v) for v in (p, a, b, c)])
    h = 1e-6
    for k in range(4):
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            up = [np.array(v) for v in (p, a, b, c)]
            dn = [np.array(v) for v in (p, a, b, c)]
            up[k] += e
            dn[k] -= e
            fd = (point_triangle_distance_np(*[u[None] for u in up])[0]
                  - point_triangle_distance_np(*[u[None] for u in dn])[0]) / (2 * h)
            assert abs(float(grads[k][j]) - fd) < 1e-6


def test_point_triangle_distance_random_vs_numpy_and_vmap():
    p = RNG.normal(size=(500, 3)) * 2
    a, b, c = (np.broadcast_to(v, (500, 3)) for v in TRI)
    d, _, _ = jax.vmap(point_triangle_distance)(*map(jnp.asarray, (p, a, b, c)))
    ref = np.array([_scipy_distance(pi, *TRI) for pi in p[:25]])
    assert np.allclose(d[:25], ref, atol=1e-6)
    assert np.allclose(d, point_triangle_distance_np(p, a, b, c), atol=1e-12)


def test_gradient_finite_at_zero_distance_and_degenerate():
    a, b, c = map(jnp.asarray, TRI)
    on = (a + b + c) / 3
    for p in (on, a, 0.5 * (a + b)):
        g = _dist_grad(p, a, b, c)
        assert float(point_triangle_distance(p, a, b, c)[0]) < 1e-14
        assert all(bool(jnp.all(jnp.isfinite(gi))) for gi in g)
    # degenerate (collinear) triangle: finite value and gradient
    p = jnp.array([0.3, 1.0, 0.2])
    cd = jnp.array([1.0, 0.1, 0.05])
    g = _dist_grad(p, a, 0.5 * cd, cd)[0]
    assert bool(jnp.all(jnp.isfinite(g)))


def test_signed_plane_distance():
    a, b, c = map(jnp.asarray, TRI)
    n = np.cross(TRI[1] - TRI[0], TRI[2] - TRI[0])
    n /= np.linalg.norm(n)
    p = TRI.mean(0) + 0.7 * n + 3.0 * (TRI[1] - TRI[0])
    assert abs(float(signed_plane_distance(jnp.asarray(p), a, b, c)) - 0.7) < 1e-12
    assert abs(float(signed_plane_distance(jnp.asarray(p), a, c, b)) + 0.7) < 1e-12


# ------------------------------------------------------------------------ the paper's law
_paper = jax.jit(lambda law, x, F, delta, tri, nbrs, body: law.force(x, F, delta, nbrs,
                                                                     body, tri))


def _build(x, tri, body, cutoff):
    """Every point-triangle (and edge-edge) pair within ``cutoff`` mm of x: the in-jit
    lists' candidates (`jaxvalve.contact.pairs`), no node sutured."""
    from jaxvalve.contact import pairs as pair_lists
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x)
    lists, _ = pair_lists.allocate(topo, jnp.asarray(x), jnp.asarray(x), cutoff, 0.0, 0.0)
    return lists.cand


def paper_reference_np(x, F_nc, delta, tri, body, k1=8e-4, k2=0.02, d_pi=0.7):
    """Direct transcription of eq. (2.2) with loops (all node / triangle pairs)."""
    x = np.asarray(x)
    rT = x[tri].mean(1)
    d = 1.1 * np.mean([max(np.linalg.norm(rT[t] - x[k]) for k in tri[t]) for t in range(len(tri))])
    out = np.zeros_like(x)
    br = paper_reference_np.branches = {"far": 0, "above_threshold": 0, "pos": 0, "neg": 0}
    for i in range(len(x)):
        Fi = F_nc[i]
        Fn = np.linalg.norm(Fi)
        for t in range(len(tri)):
            if body[tri[t, 0]] == body[i]:
                continue
            if np.linalg.norm(x[i] - rT[t]) >= d:
                br["far"] += 1
                continue
            a, b, c = x[tri[t]]
            n = np.cross(b - a, c - a)
            n /= np.linalg.norm(n)
            dpi = (x[i] + delta * Fi - rT[t]) @ n
            br["above_threshold" if dpi >= d_pi else "pos" if dpi > 0 else "neg"] += 1
            if dpi < d_pi:
                out[i] += (Fn * np.exp(-k1 * dpi / Fn) if dpi > 0 else Fn - k2 * dpi) * n
    return out


def test_paper_matches_numpy_transcription():
    rng = np.random.default_rng(3)
    lo, t_lo = grid_sheet(4, 3.0, jitter=0.1, rng=rng)
    up, t_up = grid_sheet(3, 3.0, z=0.3, jitter=0.1, rng=rng, flip=True)
    up[:, 2] += 0.4 * rng.uniform(-1, 1, len(up))
    x, tri, body = combine((lo, t_lo), (up, t_up))
    F_nc = 0.01 * rng.standard_normal(x.shape)
    delta = 20.0
    law = PaperContact().validate()
    d = float(vicinity_threshold(jnp.asarray(x), jnp.asarray(tri)))
    nbrs = _build(x, tri, body, 1.25 * d)
    F = _paper(law, jnp.asarray(x), jnp.asarray(F_nc), delta, jnp.asarray(tri), nbrs,
               jnp.asarray(body))
    ref = paper_reference_np(x, F_nc, delta, tri, body)
    assert np.count_nonzero(np.linalg.norm(ref, axis=1)) > 10
    # both branches (d_pi > 0 and <= 0), the threshold and the vicinity are exercised
    assert all(v > 0 for v in paper_reference_np.branches.values())
    assert np.allclose(F, ref, rtol=1e-12, atol=1e-15)


def test_paper_threshold_direction_and_zero_force_guard():
    law = PaperContact()
    a = np.array([[0.0, 0, 0], [3.0, 0, 0], [0.0, 3.0, 0]])
    tri = np.array([[0, 1, 2]], np.int32)
    rT = a.mean(0)
    body = np.array([0, 0, 0, 1], np.int32)

    def f(h, Fnc, delta=0.0):
        x = np.vstack([a, rT + [0.1, 0.1, h]])
        nb = _build(x, tri, body, 3.0)
        F_nc = np.zeros((4, 3))
        F_nc[3] = Fnc
        return np.asarray(_paper(law, jnp.asarray(x), jnp.asarray(F_nc), delta,
                                 jnp.asarray(tri), nb, jnp.asarray(body)))

    Fv = np.array([0.003, -0.004, 0.0])                    # |F| = 0.005 N
    assert np.all(f(0.71, Fv) == 0)                         # beyond d_pi = 0.7 mm
    for h in (0.69, 0.3, 0.0, -0.2):
        F = f(h, Fv)
        assert np.allclose(F[:3], 0) and np.allclose(F[3, :2], 0)   # along n_T = +z only
        dpi = h
        mag = 0.005 * np.exp(-8e-4 * dpi / 0.005) if dpi > 0 else 0.005 - 0.02 * dpi
        assert abs(F[3, 2] - mag) < 1e-15
    # the tentative position r~ = x + delta F moves the node across the threshold
    assert np.all(f(0.69, [0, 0, 0.005], delta=10.0) == 0)
    # outside the d-vicinity of the barycentre: no force even below d_pi
    x = np.vstack([a, rT + [0.0, 0.0, 2.6]])
    nb = _build(x, tri, body, 3.0)
    assert int(nb.n_pt) == 1
    F_nc = np.zeros((4, 3))
    F_nc[3] = [0, 0, -0.01]
    assert np.all(np.asarray(_paper(law, jnp.asarray(x), jnp.asarray(F_nc), 250.0,
                                    jnp.asarray(tri), nb, jnp.asarray(body))) == 0)
    # |F_i| = 0: no NaN; zero above the plane, -k2 d_pi below it
    assert np.all(f(0.3, [0, 0, 0]) == 0)
    F = f(-0.2, [0, 0, 0])
    assert np.all(np.isfinite(F)) and abs(F[3, 2] - 0.02 * 0.2) < 1e-15


def test_paper_validate():
    with pytest.raises(ParameterError, match="k2"):
        PaperContact(k2=-1.0).validate()
    with pytest.raises(ParameterError, match="d_pi"):
        PaperContact(d_pi=float("nan")).validate()


def test_numpy_distance_to_a_collapsed_triangle_is_the_distance_to_its_segment():
    """A triangle collapsed onto a segment (or a point) is measured without a warning
    (warnings are errors here): the distance to the segment, or to the point."""
    from jaxvalve.contact.geometry import point_triangle_distance_np
    p = np.array([[0.5, 1.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    a = np.zeros((3, 3))
    b = np.tile([1.0, 0.0, 0.0], (3, 1))
    c = np.tile([2.0, 0.0, 0.0], (3, 1))       # a, b, c on one line: the segment [0, 2]
    np.testing.assert_allclose(point_triangle_distance_np(p, a, b, c), [1.0, 1.0, 2.0])
    np.testing.assert_allclose(point_triangle_distance_np(p, a, a, a),
                               np.linalg.norm(p, axis=1))
