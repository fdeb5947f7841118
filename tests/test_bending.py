"""Discrete hinge bending (jaxvalve.mechanics.bending): topology, invariances, the plate limit on a
cylinder, an exact fold, forces vs finite differences, the plate modulus, validation and
the wiring into the membrane assembly."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp

from jaxvalve.mechanics import assembly, bending as B
from jaxvalve.errors import ParameterError
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.geometry.meshgen import disk, rectangle
from jaxvalve.mechanics.problem import Params, make_problem, validate_params

_energy = jax.jit(B.bending_energy)
_grad = jax.jit(jax.grad(B.bending_energy))


def _unit(v):
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def four_node_energy(x, hinge, w, D):
    """Independent reference: the hinge energy from each hinge's four nodes (i, j, k, l),
    normals (x_j - x_i) x (x_k - x_i) and (x_l - x_i) x (x_j - x_i)."""
    xi, xj, xk, xl = (x[hinge[:, c]] for c in range(4))
    e = xj - xi
    n1, n2 = _unit(jnp.cross(e, xk - xi)), _unit(jnp.cross(xl - xi, e))
    return D * jnp.sum(w * (1.0 - jnp.sum(n1 * n2, -1)))


def _lift(p):
    return np.concatenate([p, np.zeros((len(p), 1))], axis=1)


def _cylinder(p, R):
    """Isometric map of the flat (X, Y) plane onto a cylinder of radius R (axis along Y)."""
    X, Y = p[:, 0], p[:, 1]
    return np.stack([R * np.sin(X / R), Y, R * (1.0 - np.cos(X / R))], axis=1)


def _area(p, t):
    e1, e2 = p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _setup(p, t):
    h = B.hinges(t)
    return jnp.asarray(h), B.hinge_weights(jnp.asarray(p), jnp.asarray(h))


def _both(x, h, w, D, t):
    """Energy of the library (per-triangle normals) checked against the four-node
    reference, to rounding: relative 1e-11, and absolute 1e-14 of D sum(w) (the size of
    the terms 1 - n1.n2 cancel against; on an AVX-512 host the two sums differed by
    6e-15 on a flat sheet and by 2e-12 relative on a cylinder, where an AVX2 host met
    1e-15 and 1e-12)."""
    x = jnp.asarray(x)
    e = float(_energy(x, h, w, D, jnp.asarray(t)))
    scale = float(D) * float(jnp.sum(w))
    assert e == pytest.approx(float(four_node_energy(x, h, w, D)), rel=1e-11,
                              abs=1e-14 * scale)
    return e


# ----------------------------------------------------------------------------- topology
@pytest.mark.parametrize("nx,ny", [(3, 2), (4, 4)])
def test_hinges_are_the_interior_edges_with_consistent_orientation(nx, ny):
    p, t = rectangle(2.0, 1.5, nx, ny)
    h = B.hinges(t)
    assert h.dtype == np.int32 and h.shape[1] == 6
    # interior edges: those shared by two triangles; 3 nx ny - nx - ny for this mesh
    und = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    edges, count = np.unique(und, axis=0, return_counts=True)
    interior = {tuple(e) for e in edges[count == 2]}
    assert len(interior) == 3 * nx * ny - nx - ny
    assert len(h) == len(interior)
    assert {tuple(sorted(r)) for r in h[:, :2].tolist()} == interior     # each one once
    rot = {}
    for m, (a, b, c) in enumerate(t.tolist()):
        for r in ((a, b, c), (b, c, a), (c, a, b)):
            rot[r] = m
    for row in h.tolist():
        i, j, k, l = row[:4]
        assert (i, j, k) in rot and (j, i, l) in rot      # oriented as in the input
        assert k != l and len({i, j, k, l}) == 4
        if len(row) >= 6:                                  # the two triangles' ids
            assert rot[(i, j, k)] == row[4] and rot[(j, i, l)] == row[5]


# ----------------------------------------------------------------------------- invariance
def test_zero_on_flat_reference_and_rigid_motions_and_invariant_when_bent():
    rng = np.random.default_rng(0)
    p, t = rectangle(2.0, 1.5, 4, 3)
    h, w = _setup(p, t)
    x0 = _lift(p)
    assert abs(_both(x0, h, w, 1.0, t)) < 1e-14
    Q, c = _rotation(rng), rng.normal(size=3) * 5
    assert abs(_both(x0 @ Q.T + c, h, w, 1.0, t)) < 1e-13
    # a flat sheet rotated within its own plane and moved, lifted to z = 0
    assert abs(_both(_lift(p @ np.array([[0.6, -0.8], [0.8, 0.6]]) + 3.0), h, w, 1.0, t)) < 1e-13
    xb = x0 + 0.15 * rng.normal(size=x0.shape)
    e = _both(xb, h, w, 0.7, t)
    assert e > 1e-2
    e_rot = _both(xb @ Q.T + c, h, w, 0.7, t)
    assert abs(e_rot - e) < 1e-12 * e
    # the energy depends on the mirror image neither (1 - n1 . n2 is even in the normals)
    assert abs(_both(xb * np.array([1, 1, -1.0]), h, w, 0.7, t) - e) < 1e-12 * e


# ----------------------------------------------------------------------------- plate limit
def test_cylinder_structured_mesh_tends_to_plate_energy_and_scales_as_inverse_r_squared():
    """E_b -> (D/2) A / R^2 on a cylinder of radius R (kappa = 1/R): the structured mesh
    misses ~1/n of it (no hinge on the boundary), 3 % at 32 x 24 cells."""
    p, t = rectangle(4.0, 3.0, 32, 24)
    h, w = _setup(p, t)
    A = _area(p, t)
    ratios = []
    for R in (3.0, 6.0):
        e = _both(_cylinder(p, R), h, w, 1.0, t)
        ratios.append(e / (0.5 * A / R**2))
    assert all(abs(r - 1.0) < 0.05 for r in ratios), ratios
    assert abs(ratios[0] / ratios[1] - 1.0) < 1e-2          # E ~ 1 / R^2
    # D enters linearly
    assert _both(_cylinder(p, 3.0), h, w, 2.5, t) == pytest.approx(2.5 * ratios[0] * 0.5 * A / 9,
                                                                   rel=1e-12)


def test_cylinder_delaunay_leaflet_mesh_tends_to_plate_energy():
    from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
    from jaxvalve.geometry.template import Template
    lm = mesh_leaflet(Template(12, 7.1, 15), h=0.5)
    p, t = np.asarray(lm.points), np.asarray(lm.triangles)
    h, w = _setup(p, t)
    A = _area(p, t)
    ratios = [_both(_cylinder(p, R), h, w, 1.0, t) / (0.5 * A / R**2) for R in (10.0, 20.0)]
    assert all(abs(r - 1.0) < 0.05 for r in ratios), ratios
    assert abs(ratios[0] / ratios[1] - 1.0) < 1e-2


@pytest.mark.parametrize("theta", [0.05, 0.3, 2.0])
def test_fold_along_a_grid_line_is_exact(theta):
    """Folding a flat structured sheet by a dihedral angle theta along the grid line x = 1
    bends exactly the ny hinges on it, each with w_e = hy^2 / (hx hy): E = D (1 - cos theta)
    ly / hx, for any angle."""
    lx, ly, nx, ny = 2.0, 1.5, 4, 3
    p, t = rectangle(lx, ly, nx, ny)
    h, w = _setup(p, t)
    x = _lift(p)
    right = p[:, 0] > 1.0
    u = p[right, 0] - 1.0
    x[right, 0] = 1.0 + u * np.cos(theta)
    x[right, 2] = u * np.sin(theta)
    D = 0.37
    hx = lx / nx
    assert _both(x, h, w, D, t) == pytest.approx(D * (1 - np.cos(theta)) * ly / hx, rel=1e-12)


# ----------------------------------------------------------------------------- forces
def test_gradient_matches_central_differences_and_forces_balance():
    rng = np.random.default_rng(1)
    p, t = rectangle(1.5, 1.0, 3, 2)
    h, w = _setup(p, t)
    x = _lift(p) + 0.2 * rng.normal(size=(len(p), 3))
    D = 1.3
    g = np.asarray(_grad(x, h, w, D, jnp.asarray(t)))
    eps = 1e-6
    fd = np.zeros_like(g)
    for a in range(x.shape[0]):
        for c in range(3):
            e = np.zeros_like(x)
            e[a, c] = eps
            fd[a, c] = (float(_energy(x + e, h, w, D, t)) - float(_energy(x - e, h, w, D, t))) / (2 * eps)
    scale = np.max(np.abs(g))
    assert scale > 1e-2
    assert np.max(np.abs(g - fd)) < 1e-7 * scale
    g_ref = np.asarray(jax.grad(four_node_energy)(x, h, w, D))   # the independent reference
    assert np.max(np.abs(g_ref - g)) < 1e-12 * scale
    F = -g
    total = np.sum(np.abs(F))
    assert np.max(np.abs(F.sum(0))) < 1e-13 * total                       # no net force
    assert np.max(np.abs(np.cross(np.asarray(x), F).sum(0))) < 1e-13 * total  # no net torque


# ----------------------------------------------------------------------------- modulus
def test_plate_modulus_per_material_and_its_gradient():
    H = 0.4
    assert float(B.plate_modulus(StVenantKirchhoff(E=2.0, nu=0.3), H)) == pytest.approx(
        2.0 * H**3 / (12 * (1 - 0.09)), rel=1e-14)
    for mat in (NeoHookean(mu=0.5), Gent(mu=0.5, Jm=2.3)):
        assert float(B.plate_modulus(mat, H)) == pytest.approx(1.5 * H**3 / (12 * 0.75), rel=1e-14)
    assert float(B.plate_modulus(MassSpring.linear(3.0), H)) == pytest.approx(
        3.0 * H**3 / (12 * (1 - 1 / 9)), rel=1e-14)
    dE = jax.grad(lambda E: B.plate_modulus(StVenantKirchhoff(E=E, nu=0.3), H))(2.0)
    assert float(dE) == pytest.approx(H**3 / (12 * 0.91), rel=1e-14)
    dH = jax.grad(lambda H: B.plate_modulus(StVenantKirchhoff(E=2.0, nu=0.3), H))(H)
    assert float(dH) == pytest.approx(3 * 2.0 * H**2 / (12 * 0.91), rel=1e-14)
    dmu = jax.grad(lambda mu: B.plate_modulus(NeoHookean(mu=mu), H))(0.5)
    assert float(dmu) == pytest.approx(3 * H**3 / (12 * 0.75), rel=1e-14)
    dE1 = jax.jit(jax.grad(lambda E: B.plate_modulus(MassSpring.linear(E), H)))(3.0)
    assert float(dE1) == pytest.approx(H**3 / (12 * (1 - 1 / 9)), rel=1e-14)


# ----------------------------------------------------------------------------- validation
def _disk_problem():
    p, t, edge = disk(1.0, 2)
    prob, ref = make_problem(p, t, fixed=edge)
    return p, prob, ref


@pytest.mark.parametrize("scale", [-1.0, float("nan"), float("inf")])
def test_bending_validate_rejects_bad_scale(scale):
    with pytest.raises(ParameterError, match="bending"):
        B.Bending(scale).validate()
    _, _, ref = _disk_problem()
    with pytest.raises(ParameterError, match="bending"):
        validate_params(Params(ref=ref, material=StVenantKirchhoff(), bending=B.Bending(scale)))


def test_bending_validate_accepts_zero_and_positive_and_tracers():
    assert B.Bending(0.0).validate().scale == 0.0
    B.Bending(3.0).validate()
    jax.jit(lambda s: B.Bending(s).validate().scale)(1.0)        # tracers are not checked
    _, _, ref = _disk_problem()
    validate_params(Params(ref=ref, material=StVenantKirchhoff(), bending=B.Bending(1.0)))


# ----------------------------------------------------------------------------- assembly
def test_assembly_zero_scale_equals_membrane_and_unit_scale_adds_bending_force():
    """Bending(0) gives the membrane residual (bending=None); Bending(s) adds -s D grad E_b
    at the free nodes; the stiffness bound grows with the hinge term."""
    rng = np.random.default_rng(2)
    p, prob, ref = _disk_problem()
    assert prob.hinges is not None and prob.hinges.shape[0] > 0
    r = np.linalg.norm(p, axis=1)
    x = _lift(p) + 0.02 * rng.normal(size=(len(p), 3))
    x[:, 2] += 0.3 * (1 - r**2)
    x[np.asarray(prob.fixed)] = _lift(p)[np.asarray(prob.fixed)]
    x = jnp.asarray(x)
    mat = StVenantKirchhoff(E=1.0, nu=0.45)
    base = Params(ref=ref, material=mat, thickness=0.3, pressure=0.002)

    @jax.jit
    def membrane(params):                       # bending=None
        g = assembly.prepare(prob, params)
        return (assembly.membrane_force(x, prob, params, g)[0],
                assembly.internal_energy(x, prob, params, g))

    @jax.jit
    def parts(params):                          # bending=Bending(scale): one compilation
        g = assembly.prepare(prob, params)
        return (assembly.membrane_force(x, prob, params, g)[0], assembly.stiffness_bound(x, prob, params, g),
                assembly.internal_energy(x, prob, params, g))

    def res(params):
        r, b, e = parts(params)
        return np.asarray(r), np.asarray(b), float(e)

    r0, e0 = (np.asarray(v) for v in membrane(base))
    r_zero, b0, e_zero = res(base.replace(bending=B.Bending(0.0)))
    scale = np.max(np.abs(r0))
    assert scale > 1e-4
    assert np.max(np.abs(r_zero - r0)) <= 1e-14 * scale
    assert e_zero == pytest.approx(float(e0), rel=1e-14)

    s = 50.0
    r_s, b_s, e_s = res(base.replace(bending=B.Bending(s)))
    D = s * float(B.plate_modulus(mat, 0.3))
    hw = B.hinge_weights(ref, prob.hinges)
    e_b = float(four_node_energy(x, prob.hinges, hw, D))
    f_b = -np.asarray(jax.grad(four_node_energy)(x, prob.hinges, hw, D))
    f_b[np.asarray(prob.fixed)] = 0.0
    assert e_b > 0 and e_s == pytest.approx(e0 + e_b, rel=1e-12)
    assert np.max(np.abs(f_b)) > 1e-2 * scale
    assert np.max(np.abs(r_s - (r0 + f_b))) < 1e-12 * np.max(np.abs(r_s))
    assert np.all(b_s >= b0) and np.any(b_s > b0)
    # the bound bounds the stiffness: lambda_max of the Hessian of the conservative energy
    bent = base.replace(bending=B.Bending(s))
    K = jax.jit(jax.hessian(lambda y: assembly.internal_energy(
        y, prob, bent, assembly.prepare(prob, bent))))(x)
    n = x.size
    lam = np.max(np.abs(np.linalg.eigvalsh(np.asarray(K).reshape(n, n))))
    assert lam <= np.max(b_s)


def test_fold_barrier_is_c2_at_its_threshold_and_unbounded_at_a_flat_fold():
    """`fold_barrier`: zero, with its first two derivatives, at cos(FOLD_BARRIER_DEG);
    positive and growing past it; +inf as the hinge folds flat (n1 . n2 -> -1)."""
    import jax
    from jaxvalve.mechanics.bending import FOLD_BARRIER_DEG, fold_barrier
    c0 = float(np.cos(np.radians(FOLD_BARRIER_DEG)))
    b = jax.jit(fold_barrier)
    d1, d2 = jax.grad(fold_barrier), jax.grad(jax.grad(fold_barrier))
    for c in (c0 + 1e-9, 0.0, 0.9):
        assert float(b(c)) == 0.0 and float(d1(c)) == 0.0
    assert abs(float(d1(c0 - 1e-7))) < 1e-9 and abs(float(d2(c0 - 1e-7))) < 1e-4
    vals = [float(b(c)) for c in np.linspace(c0 - 1e-3, -1 + 1e-9, 20)]
    assert all(v > 0 for v in vals) and np.all(np.diff(vals) > 0)
    assert float(b(-1 + 1e-30)) > 10 * float(b(-1 + 1e-6)) > 0
