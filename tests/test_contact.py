"""Tests for jaxvalve.contact: geometry, broad phase, smooth penalty, paper law (2.2)."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp
from jax.test_util import check_grads
from scipy.optimize import minimize

from jaxvalve.errors import NeighbourListOverflow, ParameterError
from jaxvalve.contact import (
    PaperContact, SmoothContact, brute_force_pairs, build_neighbours,
    build_neighbours_checked, check_overflow, closest_point_barycentric, default_capacity,
    needs_rebuild, node_areas, point_triangle_distance, point_triangle_distance_np,
    signed_plane_distance, update, vicinity_threshold,
)

RNG = np.random.default_rng(0)
MMHG = 1.33322e-4  # MPa


# ------------------------------------------------------------------------ mesh helpers
def grid_sheet(n, L, z=0.0, origin=(0.0, 0.0), jitter=0.0, rng=None, flip=False):
    """Square sheet [0,L]^2 at height z, n x n cells, 2 triangles each; normal +z
    (or -z when flip)."""
    xs = np.linspace(0.0, L, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([X.ravel() + origin[0], Y.ravel() + origin[1], np.full(X.size, z)], 1)
    if jitter:
        p += jitter * (L / n) * rng.uniform(-1, 1, p.shape)
    t = []
    for i in range(n):
        for j in range(n):
            a = i * (n + 1) + j
            b = a + n + 1
            t += [[a, b, b + 1], [a, b + 1, a + 1]]
    t = np.array(t, dtype=np.int32)
    if flip:
        t = t[:, [0, 2, 1]]
    # (x, y, z) with b along +x then +y: (b-a) x (b+1-a) = +x cross (+x+y) = +z
    return p, t


def combine(*sheets):
    xs, ts, bs, off = [], [], [], 0
    for k, (p, t) in enumerate(sheets):
        xs.append(p)
        ts.append(t + off)
        bs.append(np.full(len(p), k, np.int32))
        off += len(p)
    return np.concatenate(xs), np.concatenate(ts).astype(np.int32), np.concatenate(bs)


def crumpled_bodies(rng, nb=2, n=8, L=4.0):
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


@pytest.mark.parametrize("region", ["face", "A", "B", "C", "AB", "BC", "AC"])
def test_point_triangle_distance_all_regions(region):
    p = _region_points()[region]
    a, b, c = TRI
    d, q, bary = point_triangle_distance(*map(jnp.asarray, (p, a, b, c)))
    assert abs(float(d) - _scipy_distance(p, a, b, c)) < 1e-6
    assert np.allclose(q, bary @ TRI) and abs(float(jnp.sum(bary)) - 1) < 1e-12
    zero = {"face": 0, "A": 2, "B": 2, "C": 2, "AB": 1, "BC": 1, "AC": 1}[region]
    assert int(np.sum(np.asarray(bary) == 0)) == zero
    assert abs(point_triangle_distance_np(p[None], a[None], b[None], c[None])[0] - d) < 1e-12
    # gradient equals central finite differences w.r.t. all 12 coordinates
    args = [jnp.asarray(v) for v in (p, a, b, c)]
    grads = jax.grad(lambda *v: point_triangle_distance(*v)[0], argnums=(0, 1, 2, 3))(*args)
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
        g = jax.grad(lambda p, a, b, c: point_triangle_distance(p, a, b, c)[0],
                     argnums=(0, 1, 2, 3))(p, a, b, c)
        assert float(point_triangle_distance(p, a, b, c)[0]) < 1e-14
        assert all(bool(jnp.all(jnp.isfinite(gi))) for gi in g)
    # degenerate (collinear) triangle: finite value and gradient
    p = jnp.array([0.3, 1.0, 0.2])
    cd = jnp.array([1.0, 0.1, 0.05])
    g = jax.grad(lambda p: point_triangle_distance(p, a, 0.5 * cd, cd)[0])(p)
    assert bool(jnp.all(jnp.isfinite(g)))


def test_signed_plane_distance():
    a, b, c = map(jnp.asarray, TRI)
    n = np.cross(TRI[1] - TRI[0], TRI[2] - TRI[0])
    n /= np.linalg.norm(n)
    p = TRI.mean(0) + 0.7 * n + 3.0 * (TRI[1] - TRI[0])
    assert abs(float(signed_plane_distance(jnp.asarray(p), a, b, c)) - 0.7) < 1e-12
    assert abs(float(signed_plane_distance(jnp.asarray(p), a, c, b)) + 0.7) < 1e-12


# ------------------------------------------------------------------------ broad phase
@pytest.mark.parametrize("nbody", [2, 3])
def test_broad_phase_superset_of_brute_force(nbody):
    rng = np.random.default_rng(nbody)
    x, tri, body = crumpled_bodies(rng, nb=nbody)
    cutoff = 0.35
    nbrs = build_neighbours(x, tri, body, cutoff, capacity=8192)
    assert not bool(nbrs.overflow)
    cand = pair_set(nbrs)
    assert len(cand) == int(nbrs.count) == len(set(cand))            # no duplicates
    cand = set(cand)
    ref = brute_force_pairs(x, tri, body, cutoff)
    assert len(ref) > 100 and ref <= cand
    i, t = np.array(sorted(cand)).T
    assert np.all(body[i] != body[tri[t, 0]])                         # other bodies only
    # conservative but not all pairs: every candidate passes the bounding-sphere test
    cen = x[tri].mean(1)
    R = np.linalg.norm(x[tri] - cen[:, None], axis=-1).max(1)
    assert np.all(np.linalg.norm(x[i] - cen[t], axis=1) < cutoff + R[t] + 1e-12)
    n_other = sum(np.sum(body != body[tri[k, 0]]) for k in range(len(tri)))
    assert len(cand) < 0.5 * n_other


def test_overflow_flag_and_checked_builder():
    x, tri, body = crumpled_bodies(np.random.default_rng(5))
    cutoff = 0.35
    small = build_neighbours(x, tri, body, cutoff, capacity=64)
    assert bool(small.overflow) and int(small.count) > 64
    with pytest.raises(NeighbourListOverflow, match=rf"capacity=64.*{int(small.count)}"):
        check_overflow(small)
    cell = build_neighbours(x, tri, body, cutoff, capacity=8192, cell_capacity=2)
    assert bool(cell.overflow) and int(cell.max_cell_count) > 2
    with pytest.raises(NeighbourListOverflow, match="cell_capacity=2"):
        check_overflow(cell)
    ok = build_neighbours_checked(x, tri, body, cutoff, capacity=64, cell_capacity=2)
    assert not bool(ok.overflow) and ok.capacity >= int(small.count)
    check_overflow(ok)
    assert set(pair_set(ok)) == set(pair_set(build_neighbours(x, tri, body, cutoff, 8192)))
    assert default_capacity(len(x)) >= 8 * len(x)


def test_update_inside_while_loop():
    x, tri, body = crumpled_bodies(np.random.default_rng(7))
    skin = 0.2
    nbrs = build_neighbours(x, tri, body, 0.2 + skin, capacity=8192)
    x = jnp.asarray(x)
    drift = jnp.zeros_like(x).at[body == 1, 2].set(-1.0)   # body 1 sinks 0.03 mm a step

    def body_fn(state):
        k, xk, nb, nrebuild = state
        xk = xk + 0.03 * drift
        new = update(nb, xk, tri, body, skin)
        changed = jnp.any(new.x_build != nb.x_build)
        return k + 1, xk, new, nrebuild + changed

    k, xf, nbf, nreb = jax.jit(lambda s: jax.lax.while_loop(lambda s: s[0] < 22, body_fn, s))(
        (jnp.int32(0), x, nbrs, jnp.int32(0)))
    assert int(nreb) == 5                      # rebuilt at steps 4, 8, 12, 16, 20
    assert not bool(needs_rebuild(nbf, xf, skin))
    fresh = build_neighbours(xf, tri, body, 0.2 + skin, capacity=8192)
    ref = brute_force_pairs(np.asarray(xf), tri, body, 0.2)
    assert ref <= set(pair_set(nbf))
    assert set(pair_set(nbf)) == set(pair_set(build_neighbours(nbf.x_build, tri, body,
                                                               0.2 + skin, 8192)))
    assert ref <= set(pair_set(fresh))


# ------------------------------------------------------------------------ smooth law
_energy = jax.jit(lambda c, x, tri, nbrs, area: c.energy(x, tri, nbrs, area))
_forces = jax.jit(lambda c, x, tri, nbrs, area: c.forces(x, tri, nbrs, area))


def _setup(x, tri, body, cutoff=0.45, cap=8192):
    nbrs = build_neighbours_checked(x, tri, body, cutoff, capacity=cap)
    assert not bool(nbrs.overflow)
    return jnp.asarray(x), jnp.asarray(tri), nbrs, node_areas(jnp.asarray(x), jnp.asarray(tri))


def test_smooth_zero_beyond_gap():
    c = SmoothContact()
    x, tri, body = combine(grid_sheet(4, 2.0), grid_sheet(3, 2.0, z=0.2001))
    x, tri, nbrs, area = _setup(x, tri, body)
    assert int(nbrs.count) > 0
    assert float(_energy(c, x, tri, nbrs, area)) == 0.0
    assert float(jnp.max(jnp.abs(_forces(c, x, tri, nbrs, area)))) == 0.0


def test_smooth_continuity_across_gap():
    """Value and slope -> 0 from both sides of d = g0 (one-sided differences)."""
    c = SmoothContact(stiffness=1.0, gap=0.2)
    p0, t0 = grid_sheet(2, 2.0)
    x, tri, body = combine((p0, t0), (np.array([[0.7, 0.9, 0.2]]), np.zeros((0, 3), np.int32)))
    x, tri, nbrs, area = _setup(x, tri, body)
    area = area.at[-1].set(1.0)
    E = jax.jit(lambda z: c.energy(x.at[-1, 2].set(z), tri, nbrs, area))
    dE = jax.jit(jax.grad(lambda z: c.energy(x.at[-1, 2].set(z), tri, nbrs, area)))
    g0 = 0.2
    assert float(E(g0)) == 0.0 and float(dE(g0)) == 0.0
    for h in (1e-2, 1e-3, 1e-4):
        left = (float(E(g0)) - float(E(g0 - h))) / h
        right = (float(E(g0 + h)) - float(E(g0))) / h
        assert right == 0.0 and abs(left) <= 0.5 * 1.0 * h     # |slope| = a k h / 4 -> 0
        assert abs(float(dE(g0 - h)) - (-0.5 * 1.0 * h)) < 1e-12   # -(1/2) a k (g0 - d)


def test_smooth_check_grads_and_force_consistency():
    x, tri, body = crumpled_bodies(np.random.default_rng(11))
    x, tri, nbrs, area = _setup(x, tri, body)
    c = SmoothContact(stiffness=2.0, gap=0.2)
    f = lambda x: c.energy(x, tri, nbrs, area)  # noqa: E731
    assert float(f(x)) > 0
    check_grads(f, (x,), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)
    # gradients w.r.t. the traced parameters as well
    g = lambda k, g0: SmoothContact(k, g0).energy(x, tri, nbrs, area)  # noqa: E731
    check_grads(g, (2.0, 0.2), order=1, modes=("rev",), eps=1e-6)
    F = _forces(c, x, tri, nbrs, area)
    v = jnp.asarray(np.random.default_rng(1).normal(size=x.shape))
    h = 1e-6
    fd = (f(x + h * v) - f(x - h * v)) / (2 * h)
    assert abs(float(fd + jnp.sum(F * v))) < 1e-6 * max(1.0, float(jnp.abs(fd)))


def test_smooth_newton_third_law_and_rigid_invariance():
    x, tri, body = crumpled_bodies(np.random.default_rng(13), nb=3)
    x, tri, nbrs, area = _setup(x, tri, body)
    c = SmoothContact()
    E = _energy(c, x, tri, nbrs, area)
    F = _forces(c, x, tri, nbrs, area)
    assert float(E) > 0 and float(jnp.max(jnp.abs(F))) > 1e-3
    scale = float(jnp.sum(jnp.abs(F)))
    assert float(jnp.max(jnp.abs(F.sum(0)))) < 1e-12 * scale           # zero net force
    assert float(jnp.max(jnp.abs(jnp.cross(x, F).sum(0)))) < 1e-11 * scale  # zero torque
    th = 0.7
    R = jnp.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1.0]])
    R = R @ jnp.array([[1.0, 0, 0], [0, np.cos(1.1), -np.sin(1.1)], [0, np.sin(1.1), np.cos(1.1)]])
    y = x @ R.T + jnp.array([3.0, -2.0, 7.5])
    nb_y = build_neighbours(y, tri, body, 0.45, capacity=8192)
    assert set(pair_set(nb_y)) == set(pair_set(nbrs))
    assert abs(float(_energy(c, y, tri, nb_y, area) - E)) < 1e-12 * float(E)
    assert np.allclose(_forces(c, y, tri, nb_y, area), F @ R.T, atol=1e-12)


@pytest.mark.parametrize("d", [0.05, 0.12])
def test_smooth_pressure_independent_of_refinement(d):
    """Two overlapping L x L sheets at distance d.  The resultant is k (g0 - d) L^2
    exactly for any (non-matching) meshes; with matching meshes every node feels exactly
    a_i k (g0 - d); with non-matching meshes the interior nodal pressure is that on
    average (the reaction half is lumped onto the triangle vertices)."""
    c = SmoothContact(stiffness=1.3, gap=0.2)
    L = 2.0
    p_exact = 1.3 * (0.2 - d)
    for n_lo, n_up in ((3, 3), (6, 6), (12, 12), (3, 4), (7, 5), (12, 17)):
        up, t_up = grid_sheet(n_up, L, z=d)
        x, tri, body = combine(grid_sheet(n_lo, L), (up, t_up))
        x, tri, nbrs, area = _setup(x, tri, body)
        F = _forces(c, x, tri, nbrs, area)
        upper = body == 1
        assert abs(float(F[upper, 2].sum()) / L**2 - p_exact) < 1e-10
        assert abs(float(F[~upper, 2].sum()) / L**2 + p_exact) < 1e-10
        assert float(jnp.max(jnp.abs(F[:, :2]))) < 1e-12
        p_node = np.asarray(F[upper, 2] / area[upper])
        if n_lo == n_up:
            assert np.allclose(p_node, p_exact, rtol=1e-10)
        else:
            inner = np.all(np.abs(np.asarray(x)[upper, :2] - L / 2) < L / 2 - 0.3, axis=1)
            assert abs(np.mean(p_node[inner]) / p_exact - 1) < 0.05


@pytest.mark.parametrize("mmhg", [80.0, 800.0])
def test_smooth_sheets_do_not_pass_through_under_pressure(mmhg):
    """Upper sheet pushed onto a fixed lower sheet by a pressure load, relaxed to
    equilibrium: it settles at d = g0 - P/k > 0, never crossing the lower sheet."""
    c = SmoothContact()
    P = mmhg * MMHG
    lo, t_lo = grid_sheet(8, 2.0, origin=(-0.5, -0.5), flip=True)
    up, t_up = grid_sheet(5, 1.0, z=0.25)
    x0, tri, body = combine((lo, t_lo), (up, t_up))
    x0, tri, nbrs, area = _setup(x0, tri, body, cutoff=0.5)
    upper = jnp.asarray(body == 1)
    f_ext = jnp.zeros_like(x0).at[:, 2].set(jnp.where(upper, -P * area, 0.0))
    step = 0.5 / (c.stiffness * float(jnp.max(area)))

    def it(_, x):
        F = c.forces(x, tri, nbrs, area) + f_ext
        return x.at[:, 2].add(step * jnp.where(upper, F[:, 2], 0.0))   # nodes slide in z

    x = jax.jit(lambda x: jax.lax.fori_loop(0, 600, it, x))(x0)
    z = np.asarray(x[upper, 2])
    d_eq = 0.2 - P / c.stiffness
    inner = np.all(np.abs(np.asarray(x0)[upper, :2] - 0.5) < 0.3, axis=1)
    assert np.all(z > 0.5 * d_eq)                       # no node crosses or nears d = 0
    assert 0.2 - z.min() < 1.3 * P / c.stiffness        # penetration ~ P/k (5 % of g0)
    assert abs(np.mean(z[inner]) - d_eq) < 0.1 * P / c.stiffness
    if mmhg == 80.0:
        assert (0.2 - z.min()) / 0.2 < 0.06            # penetration into layer ~5 % of g0
    assert not bool(needs_rebuild(nbrs, x, 0.3))


def test_smooth_gradient_finite_when_touching():
    p, t = grid_sheet(2, 2.0)
    x, tri, body = combine((p, t), (np.array([[0.7, 0.9, 0.0]]), np.zeros((0, 3), np.int32)))
    x, tri, nbrs, area = _setup(x, tri, body)
    F = SmoothContact().forces(x, tri, nbrs, area)
    assert bool(jnp.all(jnp.isfinite(F)))


@pytest.mark.parametrize("kw,name", [({"stiffness": 0.0}, "stiffness"),
                                     ({"stiffness": float("nan")}, "stiffness"),
                                     ({"gap": -0.1}, "gap"), ({"gap": 0.6}, "gap")])
def test_smooth_validate(kw, name):
    with pytest.raises(ParameterError, match=name):
        SmoothContact(**kw).validate()
    SmoothContact().validate()


# ------------------------------------------------------------------------ paper law
def paper_reference_np(x, F_nc, delta, tri, body, k1=8e-4, k2=0.02, d_pi=0.7):
    """Direct transcription of eq. (2.2) with loops (all node / triangle pairs)."""
    x = np.asarray(x)
    rT = x[tri].mean(1)
    d = 1.1 * np.mean([max(np.linalg.norm(rT[t] - x[k]) for k in tri[t]) for t in range(len(tri))])
    out = np.zeros_like(x)
    for i in range(len(x)):
        Fi = F_nc[i]
        Fn = np.linalg.norm(Fi)
        for t in range(len(tri)):
            if body[tri[t, 0]] == body[i] or np.linalg.norm(x[i] - rT[t]) >= d:
                continue
            a, b, c = x[tri[t]]
            n = np.cross(b - a, c - a)
            n /= np.linalg.norm(n)
            dpi = (x[i] + delta * Fi - rT[t]) @ n
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
    nbrs = build_neighbours(x, tri, body, 1.25 * d, capacity=4096)
    assert not bool(nbrs.overflow)
    F = law.force(jnp.asarray(x), jnp.asarray(F_nc), delta, jnp.asarray(tri), nbrs)
    ref = paper_reference_np(x, F_nc, delta, tri, body)
    assert np.count_nonzero(np.linalg.norm(ref, axis=1)) > 10
    # both branches (d_pi > 0 and <= 0) and the threshold are exercised
    pf = law.pair_forces(jnp.asarray(x), jnp.asarray(F_nc), delta, jnp.asarray(tri), nbrs)
    assert int(jnp.sum(jnp.any(pf != 0, axis=1))) < int(nbrs.count)
    assert np.allclose(F, ref, rtol=1e-12, atol=1e-15)


def test_paper_threshold_direction_and_zero_force_guard():
    law = PaperContact()
    a = np.array([[0.0, 0, 0], [3.0, 0, 0], [0.0, 3.0, 0]])
    tri = np.array([[0, 1, 2]], np.int32)
    rT = a.mean(0)
    body = np.array([0, 0, 0, 1], np.int32)

    def f(h, Fnc, delta=0.0):
        x = np.vstack([a, rT + [0.1, 0.1, h]])
        nb = build_neighbours(x, tri, body, 3.0, capacity=8)
        F_nc = np.zeros((4, 3))
        F_nc[3] = Fnc
        return np.asarray(law.force(jnp.asarray(x), jnp.asarray(F_nc), delta, jnp.asarray(tri), nb))

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
    # |F_i| = 0: no NaN; zero above the plane, -k2 d_pi below it
    assert np.all(f(0.3, [0, 0, 0]) == 0)
    F = f(-0.2, [0, 0, 0])
    assert np.all(np.isfinite(F)) and abs(F[3, 2] - 0.02 * 0.2) < 1e-15


def test_paper_validate():
    with pytest.raises(ParameterError, match="k2"):
        PaperContact(k2=-1.0).validate()
    with pytest.raises(ParameterError, match="d_pi"):
        PaperContact(d_pi=float("nan")).validate()
