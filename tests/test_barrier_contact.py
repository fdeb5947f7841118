"""The IPC barrier contact: distances, barrier, broad phase and CCD, checked against the IPC
toolkit (``ipctk``, an independent C++ implementation) and against brute force."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp

ipctk = pytest.importorskip("ipctk")

from jaxvalve.contact import ccd  # noqa: E402
from jaxvalve.contact import ipc_distance as D  # noqa: E402
from jaxvalve.contact.barrier import (BarrierContact, barrier, collision_weights,  # noqa: E402
                                      ee_energies, pt_energies)
from jaxvalve.contact.ipc_pairs import barrier_topology, build_pairs, pair_distances2  # noqa: E402
from jaxvalve.errors import ParameterError  # noqa: E402

RNG = np.random.default_rng(7)
PT_TYPES = {ipctk.PointTriangleDistanceType.P_T: 0, ipctk.PointTriangleDistanceType.P_E0: 1,
            ipctk.PointTriangleDistanceType.P_E1: 2, ipctk.PointTriangleDistanceType.P_E2: 3,
            ipctk.PointTriangleDistanceType.P_T0: 4, ipctk.PointTriangleDistanceType.P_T1: 5,
            ipctk.PointTriangleDistanceType.P_T2: 6}


def _pt_d2(v12):
    v = v12.reshape(4, 3)
    return D.point_triangle_distance2(v[0], v[1], v[2], v[3])


def _ee_d2(v12):
    v = v12.reshape(4, 3)
    return D.edge_edge_distance2(v[0], v[1], v[2], v[3])


_pt_all = jax.jit(jax.vmap(lambda v: (_pt_d2(v), jax.grad(_pt_d2)(v), jax.hessian(_pt_d2)(v))))
_ee_all = jax.jit(jax.vmap(lambda v: (_ee_d2(v), jax.grad(_ee_d2)(v), jax.hessian(_ee_d2)(v))))


def test_point_triangle_distance_gradient_hessian_match_ipctk():
    """Every distance type occurs; types, squared distances, gradients and Hessians agree
    with ipctk's to rounding."""
    V = RNG.normal(size=(400, 4, 3))
    d2, g, H = (np.asarray(a) for a in _pt_all(jnp.asarray(V.reshape(-1, 12))))
    codes = np.asarray(D.point_triangle_type(*(jnp.asarray(V[:, k]) for k in range(4))))
    assert set(codes.tolist()) == set(range(7))
    for k, v in enumerate(V):
        assert codes[k] == PT_TYPES[ipctk.point_triangle_distance_type(*v)]
        ref = ipctk.point_triangle_distance(*v)
        np.testing.assert_allclose(d2[k], ref, rtol=1e-11)
        np.testing.assert_allclose(g[k], ipctk.point_triangle_distance_gradient(*v),
                                   rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(H[k], ipctk.point_triangle_distance_hessian(*v),
                                   rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(D.point_triangle_distance2_np(*(a[None] for a in v))[0], ref,
                                   rtol=1e-11)


def test_edge_edge_distance_gradient_hessian_match_ipctk():
    V = RNG.normal(size=(400, 4, 3))
    d2, g, H = (np.asarray(a) for a in _ee_all(jnp.asarray(V.reshape(-1, 12))))
    ka, kb = (np.asarray(a) for a in D.edge_edge_type(*(jnp.asarray(V[:, k]) for k in range(4))))
    assert np.any((ka == 2) & (kb == 2)) and np.any((ka < 2) & (kb < 2))
    assert np.any((ka == 2) != (kb == 2))
    for k, v in enumerate(V):
        ref = ipctk.edge_edge_distance(*v)
        np.testing.assert_allclose(d2[k], ref, rtol=1e-10)
        np.testing.assert_allclose(D.segment_distance2_np(*v), ref, rtol=1e-10)
        np.testing.assert_allclose(g[k], ipctk.edge_edge_distance_gradient(*v),
                                   rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(H[k], ipctk.edge_edge_distance_hessian(*v),
                                   rtol=1e-7, atol=1e-9)


def test_barrier_and_mollifier_match_ipctk():
    """B(z) d_hat^4 is the toolkit's barrier of the squared distance; the law's pair
    energy is its 'physical' barrier (divided by d_hat^3).  The mollifier is the toolkit's
    where both are 1 (edges farther from parallel than the threshold), and like it zero
    for parallel edges and increasing in between; unlike it, C2 at the threshold."""
    dhat = 0.2
    for d in (0.01, 0.05, 0.13, 0.199, 0.25):
        z = d * d / dhat ** 2
        ref = ipctk.barrier(d * d, dhat * dhat)
        np.testing.assert_allclose(float(barrier(z)) * dhat ** 4, ref, rtol=1e-12, atol=1e-300)
    V = RNG.normal(size=(200, 4, 3))
    V[:50, 3] = V[:50, 2] + (V[:50, 1] - V[:50, 0]) * 0.7 + 1e-3 * RNG.normal(size=(50, 3))
    inside = 0
    for v in V:
        eps = D.mollifier_threshold(np.linalg.norm(v[1] - v[0]), np.linalg.norm(v[3] - v[2]))
        x = float(D.edge_edge_cross2(*map(jnp.asarray, v)))
        ours, theirs = float(D.mollifier(x, eps)), ipctk.edge_edge_mollifier(*v, eps)
        if x >= eps:
            assert ours == theirs == 1.0
        else:
            inside += 1
            assert 0.0 <= theirs < 1.0 and 0.0 <= ours < 1.0
    assert inside >= 40
    m = lambda r: D.mollifier(r, 1.0)
    d1, d2 = jax.grad(m), jax.grad(jax.grad(m))
    assert float(m(0.0)) == 0.0 and float(d1(0.0)) > 0
    r = np.linspace(0.0, 0.999, 50)
    assert np.all(np.diff(np.asarray(jax.vmap(m)(r))) > 0)
    for side in (1.0 - 1e-6, 1.0 + 1e-6):      # C2 at the threshold: m' and m'' tend to 0
        assert abs(float(m(side)) - 1.0) < 1e-12
        assert abs(float(d1(side))) < 1e-10 and abs(float(d2(side))) < 1e-5


def test_barrier_is_c2_at_the_activation_distance():
    """B, B' and B'' tend to 0 as z -> 1 from below (B ~ (1 - z)^3, B'' ~ 6 (1 - z)), and
    vanish above."""
    f = lambda z: barrier(z)
    d1, d2 = jax.grad(f), jax.grad(jax.grad(f))
    for z in (1 - 1e-4, 1 - 1e-6):
        assert abs(float(f(z))) < 1e-11 and abs(float(d1(z))) < 1e-7
        np.testing.assert_allclose(float(d2(z)), 6.0 * (1.0 - z), rtol=1e-3)
    for z in (1.0, 1.5):
        assert float(f(z)) == 0.0 and float(d1(z)) == 0.0 and float(d2(z)) == 0.0


def _barrier_derivatives(z):
    """B, B', B'' of B(z) = -(z - 1)^2 ln z, written out by hand."""
    u, lz = z - 1.0, np.log(z)
    return -u * u * lz, -2.0 * u * lz - u * u / z, -2.0 * lz - 4.0 * u / z + u * u / (z * z)


def _pair_energy_np(law, v, kind, w):
    """One pair's energy, gradient and Hessian composed from ipctk's distance derivatives
    and the barrier's hand-written derivatives in z (chain rule)."""
    dh2 = law.dhat ** 2
    if kind == "pt":
        d2, g, H = (ipctk.point_triangle_distance(*v), ipctk.point_triangle_distance_gradient(*v),
                    ipctk.point_triangle_distance_hessian(*v))
    else:
        d2, g, H = (ipctk.edge_edge_distance(*v), ipctk.edge_edge_distance_gradient(*v),
                    ipctk.edge_edge_distance_hessian(*v))
    b0, b1, b2 = _barrier_derivatives(d2 / dh2)
    c = law.stiffness * law.dhat * w
    return c * b0, c * b1 * g / dh2, c * (b2 * np.outer(g, g) / dh2 ** 2 + b1 * H / dh2)


def test_pair_energies_gradients_hessians_match_ipctk_composition():
    law = BarrierContact(dhat=0.3, stiffness=2e-3)
    loc = jnp.arange(4)[None]
    energy = {"pt": lambda x12: pt_energies(law, x12.reshape(4, 3), loc, jnp.ones(1))[0],
              "ee": lambda x12: ee_energies(law, x12.reshape(4, 3), loc, jnp.ones(1),
                                            jnp.full(1, 1e-12))[0]}
    for kind in ("pt", "ee"):
        e = energy[kind]
        V = RNG.normal(size=(300, 4, 3)) * 0.15
        V[:, 0] += 0.05
        dist = ipctk.point_triangle_distance if kind == "pt" else ipctk.edge_edge_distance
        d2 = np.array([dist(*v) for v in V])
        V = V[(d2 > 1e-4) & (d2 < 0.8 * law.dhat ** 2)]
        assert len(V) > 20
        E, G, H = (np.asarray(a) for a in jax.jit(jax.vmap(
            lambda x: (e(x), jax.grad(e)(x), jax.hessian(e)(x))))(jnp.asarray(V.reshape(-1, 12))))
        for k, v in enumerate(V):
            E0, G0, H0 = _pair_energy_np(law, v, kind, 1.0)
            np.testing.assert_allclose(E[k], E0, rtol=1e-9)
            np.testing.assert_allclose(G[k], G0, rtol=1e-7, atol=1e-9 * np.abs(G0).max())
            np.testing.assert_allclose(H[k], H0, rtol=1e-6, atol=1e-8 * np.abs(H0).max())


def _two_sheets(n=6, gap=0.3, shift=(0.13, 0.07)):
    """Two parallel square sheets (bodies 0, 1) of n x n nodes, 1 mm wide, gap apart."""
    g = np.linspace(0.0, 1.0, n)
    X, Y = np.meshgrid(g, g, indexing="ij")
    p = np.column_stack([X.ravel(), Y.ravel(), np.zeros(n * n)])
    tri = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            tri += [[a, b, c], [a, c, d]]
    tri = np.asarray(tri)
    q = p + np.array([shift[0], shift[1], gap])
    x = np.concatenate([p, q])
    triangles = np.concatenate([tri, tri + n * n])
    body = np.repeat([0, 1], n * n)
    return x, triangles, body


def test_broad_phase_equals_brute_force():
    # the sheets' own nodes lie 0.2 mm apart, inside the cutoff: the pairs between the
    # sheets only here (self-contact: the next test)
    x, tri, body = _two_sheets(gap=0.15)
    x = x + 0.05 * RNG.normal(size=x.shape)
    fixed = np.zeros(len(x), bool)
    topo = barrier_topology(tri, body, x[:, :2], fixed, x, self_contact=False)
    cut = 0.3
    pairs = build_pairs(topo, x, cut)
    brute_pt = set()
    for p in range(len(x)):
        for t in range(len(tri)):
            if body[p] != body[tri[t, 0]]:
                if D.point_triangle_distance2_np(x[p][None], *(a[None] for a in x[tri[t]]))[0] < cut ** 2:
                    brute_pt.add((p,) + tuple(tri[t]))
    assert set(map(tuple, pairs.pt.tolist())) == brute_pt
    E = topo.edges
    brute_ee = set()
    for a in range(len(E)):
        for b in range(len(E)):
            if body[E[a, 0]] < body[E[b, 0]]:
                if D.segment_distance2_np(*x[E[a]], *x[E[b]]) < cut ** 2:
                    brute_ee.add(tuple(E[a]) + tuple(E[b]))
    assert set(map(tuple, pairs.ee.tolist())) == brute_ee
    assert len(brute_pt) > 20 and len(brute_ee) > 20


def _folded_sheet(n=9, angle_deg=170.0):
    """One sheet (body 0) of n x n nodes, 2 mm wide (its flat template ref (N, 2)),
    folded about the line x = 1 mm by angle_deg (0: flat), the far half above the near
    one: (x, triangles, body, ref)."""
    x, tri, body = _two_sheets(n=n)
    m = n * n
    x, tri, body = 2.0 * x[:m], tri[: len(tri) // 2], body[:m]
    ref = x[:, :2].copy()
    t = np.radians(180.0 - angle_deg)
    far = x[:, 0] > 1.0 + 1e-9
    u = x[far, 0] - 1.0
    x[far, 0], x[far, 2] = 1.0 - u * np.cos(t), u * np.sin(t)
    return x, tri, body, ref


def test_self_contact_lists_the_pairs_of_one_sheet_that_share_no_node():
    """A sheet folded to 170 degrees: its two halves face each other.  The pairs listed
    are exactly those of a brute-force search over node-triangle and edge-edge pairs
    that share no node and lie at least self_gap apart in the flat template; without
    self-contact there are none; in the flat sheet (a right-angled grid of 0.25 mm,
    whose nodes lie 0.18 mm from triangles they do not touch) none either."""
    x, tri, body, ref = _folded_sheet()
    r3 = np.pad(ref, ((0, 0), (0, 1)))
    fixed = np.zeros(len(x), bool)
    cut, gap = 0.2, 0.5
    topo = barrier_topology(tri, body, ref, fixed, x, self_gap=gap)
    pairs = build_pairs(topo, x, cut)

    def pt2(y, p, t):
        return D.point_triangle_distance2_np(y[p][None], *(y[k][None] for k in t))[0]
    brute_pt = {(p,) + tuple(t) for p in range(len(x)) for t in tri.tolist()
                if p not in t and pt2(x, p, t) < cut ** 2 and pt2(r3, p, t) >= gap ** 2}
    assert set(map(tuple, pairs.pt.tolist())) == brute_pt and len(brute_pt) > 5
    E = topo.edges

    def ee2(y, a, b):
        return D.segment_distance2_np(*y[E[a]], *y[E[b]])
    brute_ee = {tuple(E[a]) + tuple(E[b]) for a in range(len(E)) for b in range(a + 1, len(E))
                if not set(E[a]) & set(E[b]) and ee2(x, a, b) < cut ** 2
                and ee2(r3, a, b) >= gap ** 2}
    assert set(map(tuple, pairs.ee.tolist())) == brute_ee and len(brute_ee) > 5
    off = build_pairs(barrier_topology(tri, body, ref, fixed, x, self_contact=False), x, cut)
    assert len(off.pt) == len(off.ee) == 0
    flat = r3
    assert pt2(flat, 1, tri[tri[:, 0] == 0][0]) < cut ** 2     # the grid's near neighbours
    p = build_pairs(topo, flat, cut)
    assert len(p.pt) == len(p.ee) == 0
    with pytest.raises(ParameterError, match="self_gap"):
        barrier_topology(tri, body, ref, fixed, x, self_gap=0.0)


def test_self_contact_ccd_keeps_a_folding_sheet_from_passing_through_itself():
    """The outer part of a sheet's far half (folded to 170 degrees) is pushed down through
    the near half:
    with self-contact the CCD step stops short, and ipctk (an independent
    implementation, which checks a mesh against itself) finds no intersection at the
    step, where the whole move intersects."""
    x, tri, body, ref = _folded_sheet()
    dx = np.zeros_like(x)
    dx[ref[:, 0] > 1.4, 2] = -0.6       # the outer part of the far half, down through
    topo = barrier_topology(tri, body, ref, np.zeros(len(x), bool), x)
    pairs = build_pairs(topo, x, 2.0 * 0.6 * 1.001 + 0.2)
    t = ccd.max_step(x, dx, pairs)
    assert 0.0 < t < 1.0
    mesh = ipctk.CollisionMesh(x, ipctk.edges(tri.astype(np.int32)), tri.astype(np.int32))
    assert ipctk.has_intersections(mesh, x + dx)
    assert not ipctk.has_intersections(mesh, x + t * dx)
    toi = ipctk.compute_collision_free_stepsize(mesh, x, x + dx)
    assert t <= toi
    off = build_pairs(barrier_topology(tri, body, ref, np.zeros(len(x), bool), x,
                                       self_contact=False), x, 1.5)
    assert ccd.max_step(x, dx, off) == 1.0       # nothing between the halves to stop it


def test_the_broad_phase_of_a_move_keeps_every_pair_that_can_come_within_dhat():
    """The CCD broad phase with the move dx: a sheet folded to 160 degrees turns as a whole
    (0.35 rad) while its far half closes on the near one.  Pairs of one sheet are listed
    only where their nodes' relative move can bring them within d_hat, so the list is a
    fraction of the bound 2 max |dx| alone; but every pair whose distance comes below
    d_hat anywhere along the move (sampled densely) is in it."""
    x, tri, body, ref = _folded_sheet(angle_deg=160.0)
    c, s = np.cos(0.35), np.sin(0.35)
    turn = (x - x.mean(axis=0)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T
    dx = turn + x.mean(axis=0) - x
    dx[ref[:, 0] > 1.0, 2] -= 0.25 * (ref[ref[:, 0] > 1.0, 0] - 1.0)
    dx += 0.005 * RNG.normal(size=x.shape)
    topo = barrier_topology(tri, body, ref, np.zeros(len(x), bool), x)
    dhat = 0.2
    cut = dhat + 2.0 * 1.001 * np.linalg.norm(dx, axis=1).max() + 1e-9
    full, pruned = build_pairs(topo, x, cut), build_pairs(topo, x, cut, dx=dx)
    def rows(p):
        return set(map(tuple, p.pt.tolist())), set(map(tuple, p.ee.tolist()))
    (fp, fe), (pp, pe) = rows(full), rows(pruned)
    assert pp <= fp and pe <= fe and len(pp) + len(pe) < (len(fp) + len(fe)) / 2
    hit_pt, hit_ee = np.zeros(len(full.pt), bool), np.zeros(len(full.ee), bool)
    for t in np.linspace(0.0, 1.0, 101):
        d_pt, d_ee = pair_distances2(x + t * dx, full.pt, full.ee)
        hit_pt |= d_pt < dhat ** 2
        hit_ee |= d_ee < dhat ** 2
    assert hit_pt.sum() > 0 and hit_ee.sum() > 0
    assert set(map(tuple, full.pt[hit_pt].tolist())) <= pp
    assert set(map(tuple, full.ee[hit_ee].tolist())) <= pe


def test_pins_exclude_sewn_points_and_fixed_pairs():
    """Two sheets sewn at one shared corner: the coincident sutured nodes are pinned, and
    no pair across the pin (distance 0 by construction) enters the lists."""
    x, tri, body = _two_sheets(n=4, gap=0.0, shift=(1.0, 1.0))   # corner to corner
    fixed = np.zeros(len(x), bool)
    shared = np.flatnonzero(np.isclose(x[:, 0], 1.0) & np.isclose(x[:, 1], 1.0))
    fixed[shared] = True
    topo = barrier_topology(tri, body, x[:, :2], fixed, x)
    assert (topo.pin >= 0).sum() == 2 and len(set(topo.pin[shared])) == 1
    pairs = build_pairs(topo, x, 0.5)
    assert pairs.min_distance > 0


def _sheets_driven_through(seed):
    """Two sheets 0.2 mm apart, jittered, and a random move (N, 3) that drives the second
    through the first: (x, triangles, dx, the pair list that CCD needs for the move)."""
    rng = np.random.default_rng(seed)
    x, tri, body = _two_sheets(n=5, gap=0.2)
    x = x + 0.02 * rng.normal(size=x.shape)
    dx = np.zeros_like(x)
    dx[body == 1] = [0.1, -0.05, -0.6]
    dx += 0.05 * rng.normal(size=x.shape)
    topo = barrier_topology(tri, body, x[:, :2], np.zeros(len(x), bool), x,
                            self_contact=False)
    return x, tri, dx, build_pairs(topo, x, 2.0 * np.abs(dx).max() * 2 + 0.3)


@pytest.mark.parametrize("seed", range(4))
def test_additive_ccd_never_lets_triangles_cross(seed):
    """Random moves that drive two sheets through each other: the CCD step keeps every
    distance positive along the whole move (checked densely with ipctk's distances), it is
    at most the toolkit's time of impact, and a move away from contact is taken whole."""
    x, tri, dx, pairs = _sheets_driven_through(seed)
    t = ccd.max_step(x, dx, pairs)
    assert 0.0 < t < 1.0
    mesh = ipctk.CollisionMesh(x, ipctk.edges(tri.astype(np.int32)), tri.astype(np.int32))
    toi = ipctk.compute_collision_free_stepsize(mesh, x, x + dx)
    assert toi < 1.0 and t <= toi
    for s in np.linspace(0.0, t, 201):
        xs = x + s * dx
        d_pt = D.point_triangle_distance2_np(*(xs[pairs.pt[:, k]] for k in range(4)))
        d_ee = D.segment_distance2_np(*(xs[pairs.ee[:, k]] for k in range(4)))
        assert min(d_pt.min(), d_ee.min()) > 0
    assert not ipctk.has_intersections(mesh, x + t * dx)
    assert ccd.max_step(x, -dx, pairs) == 1.0


@pytest.mark.parametrize("seed", range(3))
def test_the_smallest_step_search_gives_the_minimum_of_every_pair(seed):
    """`ccd.max_step` follows pairs only while they can still lower the smallest step
    (``smallest=True``); the minimum is that of every pair followed to its own bound, and
    no entry falls below it.  A cap outside [0, 1] is refused."""
    x, _, dx, pairs = _sheets_driven_through(seed)
    for kind, rows in (("pt", pairs.pt), ("ee", pairs.ee)):
        every = ccd.additive_ccd(x[rows], dx[rows], kind)
        fast = ccd.additive_ccd(x[rows], dx[rows], kind, smallest=True)
        assert every.min() < 1.0 and fast.min() == every.min()
        assert np.all(fast >= every.min()) and np.all(fast <= every)
    assert ccd.max_step(x, dx, pairs) == ccd.max_step(x, dx, pairs, smallest=False) < 1.0
    for cap in (-0.1, 1.5, float("nan")):
        with pytest.raises(ParameterError, match="cap must be a step fraction in"):
            ccd.additive_ccd(x[pairs.pt], dx[pairs.pt], "pt", cap=cap)


def test_barrier_contact_rejects_bad_parameters():
    with pytest.raises(ParameterError, match="dhat"):
        BarrierContact(dhat=0.0).validate()
    with pytest.raises(ParameterError, match="stiffness"):
        BarrierContact(stiffness=float("nan")).validate()


def test_collision_weights_on_the_host_equal_the_traced_ones_and_sum_to_the_area():
    """The barrier topology's weights come from NumPy (`collision_weights(..., xp=np)`),
    the adjoint's from JAX: the same function, the same values.  A node's weights are
    half a third of its triangles' area and an edge's a quarter of a third of the area at
    it, so they sum to A / 2 and A / 4, A the sheet's area; the squared rest lengths are
    the edges'."""
    from jaxvalve.geometry.mesh import unique_edges
    g = np.linspace(0.0, 2.0, 4)
    ref = np.stack(np.meshgrid(g, 0.5 * g), -1).reshape(-1, 2)          # 2 x 1 mm sheet
    k = np.arange(16).reshape(4, 4)[:-1, :-1].ravel()
    tri = np.concatenate([np.stack([k, k + 1, k + 5], 1), np.stack([k, k + 5, k + 4], 1)])
    edges, tri_edge = unique_edges(tri)
    host = collision_weights(ref, tri, tri_edge, len(edges), xp=np)
    traced = collision_weights(jnp.asarray(ref), jnp.asarray(tri), jnp.asarray(tri_edge),
                               len(edges))
    for a, b in zip(host, traced):
        assert isinstance(a, np.ndarray)
        np.testing.assert_allclose(a, np.asarray(b), rtol=1e-14, atol=1e-15)
    assert host[0].sum() == pytest.approx(0.5 * 2.0, rel=1e-14)
    assert host[1].sum() == pytest.approx(0.25 * 2.0, rel=1e-14)
    lengths = np.sum((ref[edges[:, 1]] - ref[edges[:, 0]]) ** 2, axis=1)
    np.testing.assert_allclose(host[2], lengths, rtol=1e-14)
