"""Tests for jaxvalve.contact: geometry, broad phase, smooth penalty, paper law (2.2)."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp
from jax.test_util import check_grads
from scipy.optimize import minimize

from jaxvalve.errors import NeighbourListOverflow, ParameterError
from jaxvalve.contact.neighbours import ROW_WIDTH
from jaxvalve.contact import (
    PaperContact, SmoothContact, brute_force_pairs, build_neighbours,
    build_neighbours_checked, check_overflow, default_capacity,
    needs_rebuild, node_areas, point_triangle_distance, point_triangle_distance_np,
    signed_plane_distance, update, vicinity_threshold,
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


# ------------------------------------------------------------------------ broad phase
# The tests reuse a few static shapes (meshes, capacities) so that jit compiles stay few.
CAP, SCAN = 16384, 65536


def _build(x, tri, body, cutoff):
    nbrs = build_neighbours(x, tri, body, cutoff, capacity=CAP, scan_capacity=SCAN)
    assert not bool(nbrs.overflow)
    return nbrs


@pytest.mark.parametrize("nbody", [2, 3])
def test_broad_phase_superset_of_brute_force(nbody):
    rng = np.random.default_rng(nbody)
    x, tri, body = crumpled_bodies(rng, nb=nbody)
    cutoff = 0.35
    nbrs = _build(x, tri, body, cutoff)
    cand = pair_set(nbrs)
    assert len(cand) == int(nbrs.n_pairs) == len(set(cand))          # no duplicates
    assert int(nbrs.count) == ROW_WIDTH * int(nbrs.n_rows) >= len(cand)
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
    # rows are grouped by (node, body of triangle), groups numbered consecutively
    g = np.asarray(nbrs.group)[np.asarray(nbrs.valid)]
    key = [(a, body[tri[b, 0]]) for a, b in pair_set(nbrs)]
    assert np.all(np.diff(g) >= 0) and len(set(key)) == g[-1] + 1
    assert all(len({key[k] for k in np.where(g == gi)[0]}) == 1 for gi in set(g.tolist()))


def test_overflow_flag_and_checked_builder():
    x, tri, body = crumpled_bodies(np.random.default_rng(2))
    cutoff = 0.35
    full = _build(x, tri, body, cutoff)
    # too few pair slots: flagged, the rows kept are full, count says how many are needed
    small = build_neighbours(x, tri, body, cutoff, capacity=64, scan_capacity=SCAN)
    assert bool(small.overflow) and int(small.count) == int(full.count) > 64
    assert int(small.valid.sum()) <= 64 and int(small.valid.sum()) > 32
    assert set(pair_set(small)) < set(pair_set(full))                # dropped, not invented
    with pytest.raises(NeighbourListOverflow, match=rf"capacity=64 .*{int(full.count)}"):
        check_overflow(small)
    # too small a grid scan: flagged with the scan slots needed
    scan = build_neighbours(x, tri, body, cutoff, capacity=CAP, scan_capacity=32)
    assert bool(scan.overflow) and int(scan.n_scan) > scan.scan_capacity
    with pytest.raises(NeighbourListOverflow, match=rf"scan_capacity={scan.scan_capacity} "
                                                    rf".*{int(scan.n_scan)}"):
        check_overflow(scan)
    ok = build_neighbours_checked(x, tri, body, cutoff, capacity=64, scan_capacity=32)
    assert not bool(ok.overflow) and ok.capacity >= int(ok.count)
    assert ok.scan_capacity >= int(ok.n_scan)
    check_overflow(ok)
    assert brute_force_pairs(x, tri, body, cutoff) <= set(pair_set(ok))
    assert set(pair_set(ok)) == set(pair_set(full))
    assert default_capacity(len(x)) >= 8 * len(x)
    with pytest.raises(NeighbourListOverflow, match="capacity"):
        build_neighbours_checked(x, tri, body, cutoff, capacity=64, scan_capacity=32,
                                 max_tries=1)
    with pytest.raises(ParameterError, match="cutoff"):
        build_neighbours_checked(x, tri, body, -1.0)


def test_update_overflow_is_sticky():
    """A rebuild inside `update` that needs more slots than the capacity sets overflow and
    keeps the largest count, even after a later rebuild that fits again."""
    x, tri, body = crumpled_bodies(np.random.default_rng(2))
    far = x + np.where(body == 1, 2.0, 0.0)[:, None] * np.array([0.0, 0.0, 1.0])
    nbrs = build_neighbours(far, tri, body, 0.35, capacity=256, scan_capacity=SCAN)
    assert not bool(nbrs.overflow)
    need = int(_build(x, tri, body, 0.35).count)
    assert need > 256
    up = jax.jit(lambda nb, y: update(nb, y, tri, body, 0.2))
    close = up(nbrs, jnp.asarray(x))
    assert bool(close.overflow) and int(close.count) == need
    back = up(close, jnp.asarray(far))
    assert bool(back.overflow) and int(back.count) == need and int(back.n_rows) * 8 < need
    with pytest.raises(NeighbourListOverflow, match=f"capacity=256 .*{need}"):
        check_overflow(back)


def test_update_inside_while_loop():
    x, tri, body = crumpled_bodies(np.random.default_rng(2))
    skin = 0.2
    nbrs = _build(x, tri, body, 0.15 + skin)
    x = jnp.asarray(x)
    drift = jnp.zeros_like(x).at[body == 1, 2].set(-1.0)   # body 1 sinks 0.012 mm a step

    def body_fn(state):
        k, xk, nb, nrebuild = state
        xk = xk + 0.012 * drift
        new = update(nb, xk, tri, body, skin)
        changed = jnp.any(new.x_build != nb.x_build)
        return k + 1, xk, new, nrebuild + changed

    k, xf, nbf, nreb = jax.jit(lambda s: jax.lax.while_loop(lambda s: s[0] < 20, body_fn, s))(
        (jnp.int32(0), x, nbrs, jnp.int32(0)))
    assert int(nreb) == 2                      # rebuilt at steps 9 and 18 (> skin / 2)
    assert not bool(needs_rebuild(nbf, xf, skin)) and not bool(nbf.overflow)
    assert np.allclose(nbf.x_build, x + 18 * 0.012 * drift)
    ref = brute_force_pairs(np.asarray(xf), tri, body, 0.15)   # 2 steps after the rebuild
    assert len(ref) > 50 and ref <= set(pair_set(nbf))
    assert brute_force_pairs(np.asarray(nbf.x_build), tri, body, 0.15 + skin) <= set(pair_set(nbf))


# ------------------------------------------------------------------------ smooth law
_energy = jax.jit(lambda c, x, tri, nbrs, area: c.energy(x, tri, nbrs, area))
_forces = jax.jit(lambda c, x, tri, nbrs, area: c.forces(x, tri, nbrs, area))

REFINE = ((4, 4), (8, 8), (5, 7), (7, 10))   # (lower, upper) cells across 2 mm


def _setup(x, tri, body, cutoff=0.3):
    nbrs = _build(x, tri, body, cutoff)
    return jnp.asarray(x), jnp.asarray(tri), nbrs, node_areas(jnp.asarray(x), jnp.asarray(tri))


def _tiles(d, z_node=0.5, spacing=10.0):
    """Independent (lower, upper) pairs of 2 x 2 mm sheets side by side (bodies 2k, 2k+1;
    upper at height d), then a 2 x 2 mm sheet with a lone node (last) above it at z_node:
    one compiled evaluation covers several mesh resolutions and the single-node tests."""
    sheets = []
    for k, (n_lo, n_up) in enumerate(REFINE):
        sheets.append(grid_sheet(n_lo, 2.0, origin=(spacing * k, 0.0)))
        sheets.append(grid_sheet(n_up, 2.0, z=d, origin=(spacing * k, 0.0)))
    x0 = spacing * len(REFINE)
    sheets.append(grid_sheet(4, 2.0, origin=(x0, 0.0)))
    sheets.append((np.array([[x0 + 0.7, 0.9, z_node]]), np.zeros((0, 3), np.int32)))
    return _setup(*combine(*sheets))


def test_smooth_zero_beyond_gap():
    c = SmoothContact()
    x, tri, nbrs, area = _tiles(0.2001, 0.2001)
    assert int(nbrs.count) > 0
    assert float(_energy(c, x, tri, nbrs, area)) == 0.0
    assert float(jnp.max(jnp.abs(_forces(c, x, tri, nbrs, area)))) == 0.0


@pytest.mark.parametrize("d", [0.05, 0.12])
def test_smooth_pressure_independent_of_refinement(d):
    """Two overlapping 2 x 2 mm sheets at distance d.  The resultant is k (g0 - d) L^2
    exactly for any (non-matching) meshes; with matching meshes every node feels exactly
    a_i k (g0 - d); with non-matching meshes the interior nodal pressure is that on
    average (the reaction half is lumped onto the triangle vertices)."""
    c = SmoothContact(stiffness=1.3, gap=0.2)
    p_exact = 1.3 * (0.2 - d)
    x, tri, nbrs, area = _tiles(d)
    body = np.asarray(_body_of(x))
    F = np.asarray(_forces(c, x, tri, nbrs, area))
    assert np.max(np.abs(F[:, :2])) < 1e-12
    for k, (n_lo, n_up) in enumerate(REFINE):
        lo, up = body == 2 * k, body == 2 * k + 1
        assert abs(F[up, 2].sum() / 4.0 - p_exact) < 1e-10
        assert abs(F[lo, 2].sum() / 4.0 + p_exact) < 1e-10
        p_node = F[up, 2] / np.asarray(area)[up]
        if n_lo == n_up:
            assert np.allclose(p_node, p_exact, rtol=1e-10)
        else:
            xy = np.asarray(x)[up, :2] - [10.0 * k + 1.0, 1.0]
            inner = np.all(np.abs(xy) < 0.7, axis=1)
            assert abs(np.mean(p_node[inner]) / p_exact - 1) < 0.05


def _body_of(x):
    """Body ids of the `_tiles` mesh, recomputed from the sheet sizes."""
    sizes = [(n + 1) ** 2 for pair in REFINE for n in pair] + [25, 1]
    return np.repeat(np.arange(len(sizes)), sizes)


def test_smooth_continuity_across_gap():
    """Value and slope -> 0 from both sides of d = g0 (one-sided differences); a lone node
    of area 1 over a sheet feels (1/2) k (g0 - d) (the other half of the pair pressure
    comes from the sheet's nodes, absent here)."""
    c = SmoothContact(stiffness=1.0, gap=0.2)
    x, tri, nbrs, area = _tiles(0.05, 0.2)
    area = area.at[-1].set(1.0)
    e0 = float(_energy(c, x.at[-1, 2].set(1.0), tri, nbrs, area))        # sheets only
    E = lambda z: float(_energy(c, x.at[-1, 2].set(z), tri, nbrs, area)) - e0  # noqa: E731
    dE = lambda z: float(_forces(c, x.at[-1, 2].set(z), tri, nbrs, area)[-1, 2])  # noqa: E731
    g0 = 0.2
    assert E(g0) == 0.0 and dE(g0) == 0.0
    for h in (1e-2, 1e-3, 1e-4):
        left = (E(g0) - E(g0 - h)) / h
        right = (E(g0 + h) - E(g0)) / h
        assert right == 0.0 and abs(left) <= 0.5 * 1.0 * h     # |slope| = k h / 4 -> 0
        assert abs(dE(g0 - h) - 0.5 * 1.0 * h) < 1e-12         # force (1/2) a k (g0 - d)


def test_smooth_gradient_finite_when_touching():
    c = SmoothContact()
    x, tri, nbrs, area = _tiles(0.25, 0.0)                   # node lies on the sheet
    area = area.at[-1].set(1.0)
    F = _forces(c, x, tri, nbrs, area)
    assert bool(jnp.all(jnp.isfinite(F)))
    assert float(_energy(c, x, tri, nbrs, area)) == pytest.approx(0.5 * 0.5 * 0.04)


def test_smooth_check_grads_newton_third_law_rigid_invariance():
    x, tri, body = crumpled_bodies(np.random.default_rng(3), nb=3)
    x, tri, nbrs, area = _setup(x, tri, body, cutoff=0.45)
    c = SmoothContact(stiffness=2.0, gap=0.2)
    f = lambda x: _energy(c, x, tri, nbrs, area)  # noqa: E731
    E = f(x)
    F = _forces(c, x, tri, nbrs, area)
    assert float(E) > 0 and float(jnp.max(jnp.abs(F))) > 1e-3
    check_grads(f, (x,), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-6)
    v = jnp.asarray(np.random.default_rng(1).normal(size=x.shape))
    h = 1e-6
    fd = (f(x + h * v) - f(x - h * v)) / (2 * h)                     # energy-force consistency
    assert abs(float(fd + jnp.sum(F * v))) < 1e-6 * max(1.0, float(jnp.abs(fd)))
    scale = float(jnp.sum(jnp.abs(F)))
    assert float(jnp.max(jnp.abs(F.sum(0)))) < 1e-12 * scale           # zero net force
    assert float(jnp.max(jnp.abs(jnp.cross(x, F).sum(0)))) < 1e-11 * scale  # zero torque
    th = 0.7
    R = jnp.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1.0]])
    R = R @ jnp.array([[1.0, 0, 0], [0, np.cos(1.1), -np.sin(1.1)], [0, np.sin(1.1), np.cos(1.1)]])
    y = x @ R.T + jnp.array([3.0, -2.0, 7.5])
    nb_y = _build(y, tri, body, 0.45)
    assert set(pair_set(nb_y)) == set(pair_set(nbrs))
    assert abs(float(_energy(c, y, tri, nb_y, area) - E)) < 1e-12 * float(E)
    assert np.allclose(_forces(c, y, tri, nb_y, area), F @ R.T, atol=1e-12)


@jax.jit
def _relax_under_pressure(c, P, x0, tri, nbrs, area, upper):
    """Upper-sheet nodes slide in z under the load -P a_i e_z + contact (Jacobi-damped
    fixed point, step 0.5 / (k a_i))."""
    f_ext = jnp.where(upper, -P * area, 0.0)
    step = jnp.where(upper, 0.5 / (c.stiffness * jnp.where(upper, area, 1.0)), 0.0)

    def it(_, x):
        F = c.forces(x, tri, nbrs, area)[:, 2] + f_ext
        return x.at[:, 2].add(step * F)

    return jax.lax.fori_loop(0, 300, it, x0)


@pytest.mark.parametrize("mmhg", [80.0, 800.0])
def test_smooth_sheets_do_not_pass_through_under_pressure(mmhg):
    """Upper sheets pushed onto fixed lower sheets by a pressure load, relaxed to
    equilibrium: they settle near d = g0 - P/k > 0 and never cross the lower sheet."""
    c = SmoothContact()
    P = mmhg * MMHG
    x0, tri, nbrs, area = _tiles(0.25)
    body = _body_of(x0)
    upper = jnp.asarray((body % 2 == 1) & (body < 2 * len(REFINE)))
    x = _relax_under_pressure(c, P, x0, tri, nbrs, area, upper)
    d_eq = 0.2 - P / c.stiffness
    F = _forces(c, x, tri, nbrs, area)
    for k, (n_lo, n_up) in enumerate(REFINE):
        up = body == 2 * k + 1
        z = np.asarray(x[up, 2])
        assert np.all(z > 0.5 * d_eq)                       # no node crosses or nears d = 0
        # nodes here have no membrane stiffness, so the lumped reaction on non-matching
        # meshes spreads them around d_eq; still none gets near the other sheet
        assert 0.2 - z.min() < 2.0 * P / c.stiffness        # penetration ~ P/k (5 % of g0)
        if n_lo == n_up:
            assert np.allclose(z, d_eq, atol=1e-6 * P / c.stiffness)
        assert float(jnp.sum(F[up, 2])) == pytest.approx(P * 4.0, rel=1e-4)   # equilibrium
    if mmhg == 80.0:
        assert (0.2 - float(jnp.min(jnp.where(upper, x[:, 2], 1.0)))) / 0.2 < 0.1


@pytest.mark.parametrize("kw,name", [({"stiffness": 0.0}, "stiffness"),
                                     ({"stiffness": float("nan")}, "stiffness"),
                                     ({"gap": -0.1}, "gap"), ({"gap": 0.6}, "gap")])
def test_smooth_validate(kw, name):
    with pytest.raises(ParameterError, match=name):
        SmoothContact(**kw).validate()
    SmoothContact().validate()


# ------------------------------------------------------------------------ dense layout
def _reference_energy(c, x, tri, body, pairs, area):
    """The previous implementation, as a reference: a flat pair list sorted by (node,
    body of T), vmap'ed point-triangle distances, segment_min per group (autodiff all
    through).  Given the same candidate pairs it must give the same energy.  (The
    one-sided law depends on the candidates beyond the cutoff: a node farther than the
    cutoff on the -n side of its nearest candidate is penalised.)"""
    pairs = np.array(sorted(pairs, key=lambda r: (r[0], body[tri[r[1], 0]], r[1])))
    i, t = pairs[:, 0], pairs[:, 1]
    _, group = np.unique(i * 100 + body[tri[t, 0]], return_inverse=True)
    ng = int(group.max()) + 1
    node = jnp.asarray(i[np.unique(group, return_index=True)[1]])
    seg = dict(segment_ids=jnp.asarray(group), num_segments=ng, indices_are_sorted=True)
    tt = jnp.asarray(tri)[t]

    def energy(x):
        p, a, b, cc = x[i], x[tt[:, 0]], x[tt[:, 1]], x[tt[:, 2]]
        d, q, bary = jax.vmap(point_triangle_distance)(p, a, b, cc)
        dmin = jax.ops.segment_min(d, **seg)
        if c.one_sided:   # -1: over the face (all weights > 0), on the -n side
            back = jnp.sum((p - q) * jnp.cross(b - a, cc - a), -1) < 0
            side = jnp.where(jnp.all(bary > 0, axis=-1) & back, -1.0, 1.0)
            near = d <= dmin[jnp.asarray(group)]
            dmin = jax.ops.segment_max(jnp.where(near, side, -1.0), **seg) * dmin
        return 0.5 * jnp.sum(area[node] * c.potential(jnp.minimum(dmin, c.gap)))

    return energy


# two cases, not the four of the product: each compiles the reference anew (~20 s in CI),
# and these two cover both sides, two and three bodies, and two random scenes
@pytest.mark.parametrize("seed,nbody,one_sided", [(5, 2, False), (6, 3, True)])
def test_dense_layout_matches_reference(seed, nbody, one_sided):
    """Energy, forces and Hessian-vector products of the dense (chunked) layout equal the
    previous flat implementation on random crumpled sheets that cross each other; the
    pair list holds exactly the bounding-sphere candidates."""
    rng = np.random.default_rng(seed)
    x, tri, body = crumpled_bodies(rng, nb=nbody)
    cutoff = 0.45
    nbrs = _build(x, tri, body, cutoff)
    cen = x[tri].mean(1)
    R = np.linalg.norm(x[tri] - cen[:, None], axis=-1).max(1)
    ii, tt = np.nonzero((np.linalg.norm(x[:, None] - cen[None], axis=-1) < cutoff + R[None])
                        & (body[:, None] != body[tri[:, 0]][None]))
    assert set(pair_set(nbrs)) == set(zip(ii.tolist(), tt.tolist()))
    c = SmoothContact(stiffness=2.0, gap=0.2, one_sided=one_sided)
    xj, tj = jnp.asarray(x), jnp.asarray(tri)
    area = node_areas(xj, tj)
    ref = _reference_energy(c, x, tri, body, list(zip(ii, tt)), area)
    E, E_ref = _energy(c, xj, tj, nbrs, area), jax.jit(ref)(xj)
    assert float(E_ref) > 0.05 and abs(float(E - E_ref)) <= 1e-12 * float(E_ref)
    F, F_ref = _forces(c, xj, tj, nbrs, area), -jax.jit(jax.grad(ref))(xj)
    scale = float(jnp.max(jnp.abs(F_ref)))
    assert scale > 1e-2 and float(jnp.max(jnp.abs(F - F_ref))) <= 1e-12 * scale
    v = jnp.asarray(rng.normal(size=x.shape))
    hvp = jax.jit(lambda f: jax.jvp(jax.grad(f), (xj,), (v,))[1], static_argnums=0)
    H = hvp(lambda y: c.energy(y, tj, nbrs, area))
    H_ref = hvp(ref)
    assert float(jnp.max(jnp.abs(H - H_ref))) <= 1e-10 * float(jnp.max(jnp.abs(H_ref)))


def test_chunked_loops_and_buckets_agree(monkeypatch):
    """Tiny loop chunks (many iterations, a clamped last chunk) give the same list and
    energy as the defaults."""
    from jaxvalve.contact import neighbours as NB, smooth as SM
    x, tri, body = crumpled_bodies(np.random.default_rng(7), nb=3)
    c = SmoothContact(one_sided=True)
    xj, tj = jnp.asarray(x), jnp.asarray(tri)
    area = node_areas(xj, tj)
    nbrs = _build(x, tri, body, 0.45)
    E = float(_energy(c, xj, tj, nbrs, area))
    F = _forces(c, xj, tj, nbrs, area)
    monkeypatch.setattr(NB, "SCAN_CHUNK", 3)
    monkeypatch.setattr(SM, "CHUNK_ROWS", 5)
    build = jax.jit(NB._build.__wrapped__,
                    static_argnames=("capacity", "scan_capacity", "n_bodies", "grid_size"))
    small = build(xj, tj, jnp.asarray(body), 0.45, nbrs.capacity, nbrs.scan_capacity,
                  nbrs.n_bodies, nbrs.grid_size)
    assert int(nbrs.n_scan) > 10 * 3 * 32 and int(nbrs.n_rows) > 10 * 5
    for name in ("cand", "row_group", "group_node", "group_row", "count", "n_pairs"):
        assert np.array_equal(getattr(small, name), getattr(nbrs, name)), name
    E2 = float(jax.jit(lambda y: c.energy(y, tj, small, area))(xj))
    F2 = -jax.jit(jax.grad(lambda y: c.energy(y, tj, small, area)))(xj)
    assert E2 == E and bool(jnp.all(F2 == F))


def test_one_sided_pushes_crossed_node_back():
    """A node slightly through a sheet (on its -n side) is pushed back to the +n side by
    the one-sided law (and further through by the unsigned one); the energy is continuous
    across the sheet (s = 0) and so is the force (away from exactly s = 0, where the
    distance gradient is taken as 0)."""
    p, t = grid_sheet(4, 2.0)                          # normal +z
    x, tri, body = combine((p, t), (np.array([[0.7, 0.9, 0.05]]), np.zeros((0, 3), np.int32)))
    nbrs = build_neighbours(x, tri, body, 0.45, capacity=64)
    xj, tj = jnp.asarray(x), jnp.asarray(tri)
    area = node_areas(xj, tj).at[-1].set(1.0)
    one, two = SmoothContact(one_sided=True), SmoothContact()

    def at(c, z):
        y = xj.at[-1, 2].set(z)
        return float(_energy(c, y, tj, nbrs, area)), np.asarray(_forces(c, y, tj, nbrs, area))

    e0 = at(one, 1.0)[0]                               # the sheet's own nodes: no energy
    for z in (-0.01, -0.1):
        E, F = at(one, z)
        assert F[-1, 2] > 0 and abs(F[-1, 2] - 0.5 * 1.0 * (0.2 - z)) < 1e-12  # pushed up
        assert abs(E - e0 - 0.25 * (0.2 - z) ** 2) < 1e-12
        assert at(two, z)[1][-1, 2] < 0                # unsigned: pushed further through
    for h in (1e-4, 1e-7):
        (Ep, Fp), (Em, Fm) = at(one, h), at(one, -h)
        assert abs(Ep - Em) < 0.25 * 4 * 0.2 * h + 1e-15          # continuous energy
        assert abs(Fp[-1, 2] - Fm[-1, 2]) < 2 * h + 1e-14          # and force
    assert abs(at(one, 0.0)[0] - e0 - 0.25 * 0.2 ** 2) < 1e-15


# ------------------------------------------------------------------------ paper law
_paper = jax.jit(lambda law, x, F, delta, tri, nbrs: law.force(x, F, delta, tri, nbrs))


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
    F = _paper(law, jnp.asarray(x), jnp.asarray(F_nc), delta, jnp.asarray(tri), nbrs)
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
        nb = build_neighbours(x, tri, body, 3.0, capacity=8)
        F_nc = np.zeros((4, 3))
        F_nc[3] = Fnc
        return np.asarray(_paper(law, jnp.asarray(x), jnp.asarray(F_nc), delta,
                                 jnp.asarray(tri), nb))

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
    nb = build_neighbours(x, tri, body, 3.0, capacity=8)
    assert int(nb.n_pairs) == 1
    F_nc = np.zeros((4, 3))
    F_nc[3] = [0, 0, -0.01]
    assert np.all(np.asarray(_paper(law, jnp.asarray(x), jnp.asarray(F_nc), 250.0,
                                    jnp.asarray(tri), nb)) == 0)
    # |F_i| = 0: no NaN; zero above the plane, -k2 d_pi below it
    assert np.all(f(0.3, [0, 0, 0]) == 0)
    F = f(-0.2, [0, 0, 0])
    assert np.all(np.isfinite(F)) and abs(F[3, 2] - 0.02 * 0.2) < 1e-15


def test_paper_validate():
    with pytest.raises(ParameterError, match="k2"):
        PaperContact(k2=-1.0).validate()
    with pytest.raises(ParameterError, match="d_pi"):
        PaperContact(d_pi=float("nan")).validate()


def test_mesh_skin_keeps_the_candidates_per_node_fixed_under_refinement():
    """With the skin equal to the mesh size (`equilibrium.mesh_skin`), the candidate pairs
    per node of two sheets 0.1 mm apart grow only through the fixed gap g0 = 0.2 mm as the
    mesh is refined (a broad phase near linear in the triangles); with the fixed 1 mm skin
    they grow like 1 / h^2."""
    from jaxvalve.solvers.equilibrium import DEFAULT_SKIN, mesh_skin

    gap = 0.2
    per_node, per_node_fixed, skins = [], [], []
    for n in (8, 16, 32):                          # h = 2, 1, 0.5 mm on 16 mm sheets
        x, tri, body = combine(grid_sheet(n, 16.0), grid_sheet(n, 16.0, z=0.1, flip=True))
        skin = mesh_skin(tri, x)
        skins.append(skin)
        counts = []
        for cutoff in (gap + skin, gap + DEFAULT_SKIN):
            nb = build_neighbours_checked(jnp.asarray(x), jnp.asarray(tri),
                                          jnp.asarray(body), cutoff)
            counts.append(int(nb.n_pairs) / len(x))
        per_node.append(counts[0])
        per_node_fixed.append(counts[1])
    # the median edge (the legs of the right triangles: L / n), capped at 1 mm
    assert skins == [DEFAULT_SKIN, 1.0, 0.5]
    grow_fixed = per_node_fixed[2] / per_node_fixed[1]
    grow = per_node[2] / per_node[1]
    assert grow_fixed > 2.2     # -> 4 = (1 mm / 0.5 mm)^2 at a fixed cutoff (2.44: edges)
    # ((g0 + h + R) / h)^2 with R ~ 0.75 h the bounding radius: (1.07 / 1.95 * 2)^2 = 1.2
    assert grow < 1.35 and grow < 0.6 * grow_fixed                          # 1.25


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
