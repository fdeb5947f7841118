"""Strain energies: the closed-form TBS force (eq. 2.6), rest and rigid invariance, analytic
membrane tensions under homogeneous stretch, gradient checks and the Gent barrier."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxvalve.mechanics import assembly

from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem

H = 0.3
MODELS = {
    "stvk": StVenantKirchhoff(E=1.3, nu=0.45),
    "neo-hookean": NeoHookean(mu=0.4),
    "gent": Gent(mu=0.4, Jm=2.3),
    "mass-spring": MassSpring(E1=0.137, E2=0.568, E3=0.968, E1_cf=0.063, E2_cf=0.57,
                              E3_cf=1.4),
}


def _setup(material, ref, tri, fibre_angle=0.3):
    prob, ref = make_problem(ref, tri)
    params = Params(ref=ref, material=material, thickness=H, fibre_angle=fibre_angle)
    return prob, params, assembly.prepare(prob, params)


def _energy(x, prob, params, r):
    return assembly.elastic_energy(x, prob, params, r)


def tbs_forces(X, x, E, nu):
    """Paper eq. 2.6, transcribed directly: forces (3, 3) on one triangle."""
    X = np.c_[X, np.zeros(3)] if X.shape[1] == 2 else X
    A = 0.5 * np.linalg.norm(np.cross(X[1] - X[0], X[2] - X[0]))

    def angle(i):
        u, v = X[(i + 1) % 3] - X[i], X[(i + 2) % 3] - X[i]
        return np.arccos(u @ v / np.linalg.norm(u) / np.linalg.norm(v))

    cot = [1 / np.tan(angle(i)) for i in range(3)]
    kap = [E * (2 * cot[k] ** 2 + 1 - nu) / (16 * (1 - nu**2) * A) for k in range(3)]
    c = [E * (2 * cot[(k + 1) % 3] * cot[(k + 2) % 3] + nu - 1) / (16 * (1 - nu**2) * A)
         for k in range(3)]

    def d2l(i):  # squared length change of the edge opposite vertex i
        j, k = (i + 1) % 3, (i + 2) % 3
        return np.sum((x[j] - x[k]) ** 2) - np.sum((X[j] - X[k]) ** 2)

    F = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            if j != i:
                k = 3 - i - j
                F[i] += (kap[k] * d2l(k) + c[j] * d2l(i) + c[i] * d2l(j)) * (x[j] - x[i])
    return F


@pytest.mark.parametrize("seed", range(5))
def test_stvk_autodiff_force_equals_tbs_closed_form(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(3, 2))
    a, b = X[1] - X[0], X[2] - X[0]
    if a[0] * b[1] - a[1] * b[0] < 0:
        X = X[[0, 2, 1]]
    x = np.c_[X, np.zeros(3)] + 0.3 * rng.normal(size=(3, 3))
    E, nu = rng.uniform(0.1, 10), rng.uniform(-0.5, 0.5)
    mat = StVenantKirchhoff(E=E, nu=nu)
    prob, params, r = _setup(mat, X, [[0, 1, 2]])
    # the paper's potential is per unit area (thickness folded into E): H = 1 here
    params = params.replace(thickness=1.0)
    F = -jax.grad(_energy)(jnp.asarray(x), prob, params, r)
    np.testing.assert_allclose(F, tbs_forces(X, x, E, nu), rtol=1e-11, atol=1e-12)


def _random_sheet(seed=0):
    p, t = meshgen.rectangle(3.0, 2.0, 3, 2)
    rng = np.random.default_rng(seed)
    p = p + 0.05 * rng.normal(size=p.shape)
    return p, t


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("name", MODELS)
def test_zero_energy_and_force_at_rest_and_under_rigid_motion(name):
    p, t = _random_sheet()
    prob, params, r = _setup(MODELS[name], p, t)
    x_rest = jnp.asarray(meshgen.lift(p))
    Q = _rotation(1)
    x_rigid = x_rest @ Q.T + np.array([1.0, -2.0, 0.5])
    for x in (x_rest, x_rigid):
        e = _energy(x, prob, params, r)
        f = -jax.grad(_energy)(x, prob, params, r)
        assert abs(float(e)) < 1e-12
        assert float(jnp.max(jnp.abs(f))) < 1e-11


@pytest.mark.parametrize("name", MODELS)
def test_energy_and_forces_invariant_under_rigid_motion_of_deformed_state(name):
    p, t = _random_sheet(2)
    prob, params, r = _setup(MODELS[name], p, t)
    x = jnp.asarray(meshgen.lift(p)) + 0.1 * np.random.default_rng(3).normal(size=(len(p), 3))
    Q = _rotation(4)
    e1 = _energy(x, prob, params, r)
    e2 = _energy(x @ Q.T + 3.0, prob, params, r)
    f1 = -jax.grad(_energy)(x, prob, params, r)
    f2 = -jax.grad(_energy)(x @ Q.T + 3.0, prob, params, r)
    np.testing.assert_allclose(e2, e1, rtol=1e-12)
    np.testing.assert_allclose(f2, f1 @ Q.T, atol=1e-12 * float(jnp.max(jnp.abs(f1))) + 1e-14)
    # internal forces balance: zero total force and zero total moment
    np.testing.assert_allclose(jnp.sum(f1, 0), 0, atol=1e-12)
    np.testing.assert_allclose(jnp.sum(jnp.cross(x, f1), 0), 0, atol=1e-11)


# ---------------------------------------------------------------- analytic tensions
def analytic_tension(name, mat, l1, l2):
    """Nominal membrane tension T1 = d(H W)/d lambda1 (N/mm) under F = diag(l1, l2)."""
    if name == "stvk":
        lam = mat.E * mat.nu / (1 - mat.nu**2)
        mu = mat.E / (2 * (1 + mat.nu))
        e1, e2 = (l1**2 - 1) / 2, (l2**2 - 1) / 2
        return H * l1 * (lam * (e1 + e2) + 2 * mu * e1)
    if name == "neo-hookean":
        return H * mat.mu * (l1 - 1 / (l1**3 * l2**2))
    if name == "gent":
        i1 = l1**2 + l2**2 + 1 / (l1 * l2) ** 2
        return H * mat.mu * mat.Jm / (mat.Jm - (i1 - 3)) * (l1 - 1 / (l1**3 * l2**2))
    if name == "mass-spring":
        # square cells: each triangle has a horizontal, a vertical and a 45-degree spring
        theta_f = 0.3  # fibre angle

        def sigma(eps, Ef, Ecf):
            Ek = [np.sqrt(ef**2 * c2 + ecf**2 * (1 - c2)) for ef, ecf in zip(Ef, Ecf)]
            b1, b2 = 0.175, 0.3
            s1 = Ek[0] * min(eps, b1)
            s2 = Ek[1] * (np.clip(eps, b1, b2) - b1)
            s3 = Ek[2] * (max(eps, b2) - b2)
            return s1 + s2 + s3

        total = 0.0
        Ef = (mat.E1, mat.E2, mat.E3)
        Ecf = (mat.E1_cf, mat.E2_cf, mat.E3_cf)
        # springs of the two triangle kinds (diagonal at 45 or 135 degrees), half each
        for diag in (np.pi / 4, 3 * np.pi / 4):
            for ang in (0.0, np.pi / 2, diag):
                c, s = np.cos(ang), np.sin(ang)
                c2 = np.cos(ang - theta_f) ** 2
                eps = np.sqrt((l1 * c) ** 2 + (l2 * s) ** 2) - 1
                total += 0.5 * sigma(eps, Ef, Ecf) * l1 * c**2 / (1 + eps)
        return H * total
    raise KeyError(name)


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("kind", ["uniaxial", "equibiaxial"])
def test_homogeneous_stretch_tension_matches_analytic(name, kind):
    lx, ly = 2.0, 2.0
    p, t = meshgen.rectangle(lx, ly, 4, 4)
    mat = MODELS[name]
    prob, params, r = _setup(mat, p, t)
    for l1 in (1.05, 1.2, 1.35):
        l2 = 1.0 if kind == "uniaxial" else l1
        x = jnp.asarray(meshgen.lift(p * np.array([l1, l2])))
        f = -jax.grad(_energy)(x, prob, params, r)
        # virtual work: dU/dl1 = -sum_i F_ix X_i, and dU/dl1 = T1 * area
        t1 = -float(jnp.sum(f[:, 0] * p[:, 0])) / (lx * ly)
        np.testing.assert_allclose(t1, analytic_tension(name, mat, l1, l2), rtol=1e-10)


@pytest.mark.parametrize("name", MODELS)
def test_check_grads_on_energy_density(name):
    mat = MODELS[name]
    rng = np.random.default_rng(0)
    Fd = np.eye(3, 2)[None] + 0.1 * rng.normal(size=(4, 3, 2))
    C = jnp.asarray(np.swapaxes(Fd, 1, 2) @ Fd)
    geom = None
    if mat.needs_springs:
        p, t = meshgen.rectangle(2.0, 1.0, 2, 1)
        _, params, r = _setup(mat, p, t)
        geom = r.springs
        C = C[: len(t)]
    check_grads(lambda c: jnp.sum(mat.energy_density(c, geom)), (C,), order=2,
                modes=["fwd", "rev"], atol=1e-6, rtol=1e-6)


def test_gent_past_stretch_limit_is_infinite_energy_and_finite_gradient():
    p, t = meshgen.rectangle(1.0, 1.0, 1, 1)
    mat = Gent(mu=0.4, Jm=0.5)
    prob, params, r = _setup(mat, p, t)
    x = jnp.asarray(meshgen.lift(p * np.array([2.0, 1.0])))  # I1 - 3 = 1.5 > Jm
    assert np.isinf(float(_energy(x, prob, params, r)))
    g = jax.grad(_energy)(x, prob, params, r)
    assert np.all(np.isfinite(np.asarray(g)))
    assert not bool(assembly.stretch_admissible(x, prob, params, r))


def test_mass_spring_anisotropy_fibre_direction_is_stiffer():
    """A spring along the fibres takes E_f (eq. 2.4), across them E_cf."""
    p, t = meshgen.rectangle(2.0, 2.0, 4, 4)
    mat = MassSpring(E1=1.0, E2=1.0, E3=1.0, E1_cf=0.2, E2_cf=0.2, E3_cf=0.2)
    x = jnp.asarray(meshgen.lift(p * np.array([1.1, 1.0])))
    energies = []
    for ang in (0.0, np.pi / 2):
        prob, params, r = _setup(mat, p, t, fibre_angle=ang)
        energies.append(float(_energy(x, prob, params, r)))
    assert energies[0] > 3 * energies[1]
    # per-spring angles give the same energy as the template direction
    prob, params, r = _setup(mat, p, t, fibre_angle=0.0)
    u = np.asarray(r.springs.unit)
    per_spring = np.arccos(np.clip(np.abs(u[..., 0]), 0, 1))
    params2 = params.replace(fibre_angle=jnp.asarray(per_spring))
    r2 = assembly.prepare(prob, params2)
    np.testing.assert_allclose(float(_energy(x, prob, params2, r2)), energies[0], rtol=1e-12)


def test_mass_spring_linear_small_strain_matches_isotropic_membrane():
    """Linear springs (eq. 2.3) under equibiaxial strain eps: every spring stretches by eps,
    w = 3 H E eps^2 / 2 per unit area, so T1 = 1.5 E H eps on any mesh (the effective
    membrane of an equilateral spring net has Young's modulus E H and Poisson ratio 1/3)."""
    p, t = meshgen.rectangle(2.0, 2.0, 4, 4)
    mat = MassSpring.linear(1.0)
    prob, params, r = _setup(mat, p, t)
    eps = 1e-4
    x = jnp.asarray(meshgen.lift(p * (1 + eps)))
    f = -jax.grad(_energy)(x, prob, params, r)
    t1 = -float(jnp.sum(f[:, 0] * p[:, 0])) / 4.0
    # each triangle: 3 springs with energy H A E eps^2 / 2 -> w = 3/2 H E eps^2, T1 = dw/dl1 / 2
    np.testing.assert_allclose(t1, 1.5 * H * 1.0 * eps, rtol=1e-9)


@pytest.mark.parametrize("E_cf", [None, 0.4])
@pytest.mark.parametrize("stretch", [1.02, 1.25, 1.6])
def test_mass_spring_linear_law_equals_piecewise_with_equal_moduli(stretch, E_cf):
    """The linear law (E2 = E3 = None, issue 5 skip) gives the piecewise law's energy and
    forces with E1 = E2 = E3 to rounding, for strains below (1.02), between (1.25) and
    above (1.6) the breaks 0.175 and 0.3, with and without anisotropy."""
    p, t = meshgen.rectangle(2.0, 1.5, 4, 3)
    lin = MassSpring.linear(0.7, E_cf)
    cf = {} if E_cf is None else dict(E1_cf=E_cf, E2_cf=E_cf, E3_cf=E_cf)
    pw = MassSpring(E1=0.7, E2=0.7, E3=0.7, **cf)
    assert lin.is_linear and not pw.is_linear and lin.stiffest() is lin
    rng = np.random.default_rng(1)
    x = jnp.asarray(meshgen.lift(p * np.array([stretch, 1.0]))
                    + 0.01 * rng.normal(size=(len(p), 3)))
    out = []
    for mat in (lin, pw):
        prob, params, r = _setup(mat, p, t)
        e, g = jax.value_and_grad(_energy)(x, prob, params, r)
        out.append((float(e), np.asarray(g)))
    assert out[0][0] > 0
    np.testing.assert_allclose(out[0][0], out[1][0], rtol=1e-13)
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=1e-11, atol=1e-13 * np.abs(
        out[1][1]).max())


def test_mass_spring_linear_law_traces_no_breaks():
    """A linear scene compiles only the linear law: its energy's jaxpr holds fewer
    operations than the piecewise law's and no clamp / min / max of the breaks, and its
    pytree has one modulus leaf less per unused field."""
    p, t = meshgen.rectangle(1.0, 1.0, 2, 2)
    x = jnp.asarray(meshgen.lift(p * 1.1))
    n_eqn = {}
    for name, mat in (("lin", MassSpring.linear(1.0)), ("pw", MassSpring(1.0, 1.0, 1.0))):
        prob, params, r = _setup(mat, p, t)
        jaxpr = jax.make_jaxpr(lambda y: _energy(y, prob, params, r))(x).jaxpr
        prims = {str(e.primitive) for e in jaxpr.eqns}
        n_eqn[name] = len(jaxpr.eqns)
        if name == "lin":
            assert not prims & {"min", "max", "clamp"}, prims
    assert n_eqn["lin"] < n_eqn["pw"] - 5, n_eqn
    assert len(jax.tree_util.tree_leaves(MassSpring.linear(1.0))) == 3   # E1, breaks


def test_mass_spring_moduli_given_in_part_are_rejected():
    from jaxvalve.errors import ParameterError
    with pytest.raises(ParameterError, match="give E2 and E3 together"):
        MassSpring(E1=1.0, E2=0.5, E3=None).validate()
    with pytest.raises(ParameterError, match="E2_cf / E3_cf need E2 and E3"):
        MassSpring(E1=1.0, E2=None, E3=None, E2_cf=0.3).validate()
    mat = MassSpring(E1=1.0, E2=0.5, E3=None)
    p, t = meshgen.rectangle(1.0, 1.0, 1, 1)
    prob, params, r = _setup(MassSpring.linear(1.0), p, t)
    with pytest.raises(ParameterError, match="give E2 and E3 together"):
        mat.energy_density(jnp.eye(2)[None].repeat(len(t), 0), r.springs)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_spectral_bound_brackets_the_spectral_radius(dtype):
    # rho(H) <= bound <= n^(1/16) rho(H): indefinite, rank-one, equal-eigenvalue and zero
    # matrices, and scales far beyond float32's range of H^16
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 9, 9))
    H = [A + np.swapaxes(A, 1, 2)]
    v = rng.normal(size=(5, 9))
    H.append(v[:, :, None] * v[:, None, :] * np.array([1.0, -2.0, 1e3, 1e-3, 7.0])[:, None, None])
    H.append(np.stack([np.eye(9), -np.eye(9), np.zeros((9, 9))]))
    H = np.concatenate(H) * np.concatenate([np.logspace(-8, 8, 40), np.ones(8)])[:, None, None]
    exact = np.max(np.abs(np.linalg.eigvalsh(H)), axis=-1)
    b = np.asarray(assembly.spectral_bound(jnp.asarray(H, dtype)), np.float64)
    assert np.all(np.isfinite(b))
    tol = 1e-5 if dtype == np.float32 else 1e-12
    assert np.all(b >= exact * (1 - tol))
    assert np.all(b <= exact * 9 ** (1 / 16) * (1 + tol))
    # equal eigenvalues are the worst case: exactly n^(1/16) above
    np.testing.assert_allclose(b[-3:-1], 9 ** (1 / 16), rtol=10 * tol)
    assert b[-1] == 0.0


@pytest.mark.parametrize("name", ["stvk", "mass-spring"])
def test_element_stiffness_bound_is_tight_on_a_stretched_sheet(name):
    # element blocks are dominated by one eigenvalue: the bound is far below its worst
    # case 9^(1/16) = 1.147 (StVK within 0.1 %, the mass-spring model's fibres within 5 %)
    p, t = _random_sheet(4)
    prob, params, r = _setup(MODELS[name], p, t)
    x = np.c_[p * np.array([1.15, 0.95]), 0.1 * np.sin(p[:, 0])]
    Hs = np.asarray(assembly._element_hessians(jnp.asarray(x), prob, params, r, stiffest=True))
    exact = np.max(np.abs(np.linalg.eigvalsh(Hs)), axis=-1)
    q = np.asarray(assembly.spectral_bound(jnp.asarray(Hs))) / exact
    assert np.all(q >= 1 - 1e-12)
    assert np.all(q <= (1 + 1e-3 if name == "stvk" else 1.05))


def _squashed_square(s, E=0.8):
    """Energy of a unit square (two triangles) of linear springs squashed to height s, and
    its closed form: per triangle a spring unchanged, one at strain s - 1 and the diagonal
    at sqrt((1 + s^2) / 2) - 1, each H A_T E eps^2 / 2 (A_T = 1/2); below the collapse
    threshold both triangles (J = s) add H A_T E b(s)."""
    p, t = meshgen.rectangle(1.0, 1.0, 1, 1)
    mat = MassSpring.linear(E)
    prob, params, r = _setup(mat, p, t)
    x = jnp.asarray(meshgen.lift(p * np.array([1.0, s])))
    springs = (s - 1.0) ** 2 + (np.sqrt((1 + s * s) / 2) - 1.0) ** 2
    J_hat = MassSpring.collapse_J
    b = -(s - J_hat) ** 2 * np.log(s / J_hat) if s < J_hat else 0.0
    expected = 2 * H * 0.5 * (0.5 * E * springs + E * b)
    return float(_energy(x, prob, params, r)), expected, (x, prob, params, r)


@pytest.mark.parametrize("s", [1.0, 0.5, 0.1, 0.08, 0.03, 0.002])
def test_mass_spring_collapse_barrier_matches_closed_form(s):
    """A square of springs squashed to height s: the springs' energy alone down to the
    threshold J = 0.1, the barrier added below it; it grows without bound as s -> 0."""
    e, expected, _ = _squashed_square(s)
    np.testing.assert_allclose(e, expected, rtol=1e-12, atol=1e-15)


def test_mass_spring_collapse_barrier_is_c2_at_its_threshold_and_pushes_apart():
    """b(J) = -(J - J_hat)^2 ln(J / J_hat), J = sqrt(det C): value, slope and curvature
    tend to 0 at J_hat (a C2 join with the springs' energy), the slope is the closed form
    below it and negative (the force opens the triangle), and it is exactly zero above."""
    from jaxvalve.mechanics.materials import collapse_barrier
    J_hat = MassSpring.collapse_J

    def b(J):
        C = jnp.stack([jnp.stack([J * J, 0.0]), jnp.stack([0.0, 1.0])])[None]
        return collapse_barrier(C, J_hat)[0]

    db, d2b = jax.grad(b), jax.grad(jax.grad(b))
    for J in (0.02, 0.05, 0.09):
        slope = -2 * (J - J_hat) * np.log(J / J_hat) - (J - J_hat) ** 2 / J
        np.testing.assert_allclose(float(db(J)), slope, rtol=1e-12)
        assert float(db(J)) < 0 and float(d2b(J)) > 0
    # just below J_hat, with D = J_hat - J: b ~ D^3 / J_hat, b' ~ -3 D^2 / J_hat,
    # b'' ~ 6 D / J_hat, all -> 0 (leading order; relative error ~ D / J_hat)
    D = 1e-7
    for got, lead in ((b(J_hat - D), D**3 / J_hat), (db(J_hat - D), -3 * D**2 / J_hat),
                      (d2b(J_hat - D), 6 * D / J_hat)):
        np.testing.assert_allclose(float(got), lead, rtol=1e-4)
    for J in (J_hat, 0.3, 1.0, 1.7):
        assert float(b(J)) == 0.0 and float(db(J)) == 0.0 and float(d2b(J)) == 0.0
    assert float(b(1e-200)) > float(b(1e-3)) > float(b(0.05))


def test_mass_spring_collapsed_triangle_has_infinite_energy_and_finite_force():
    _, _, (x, prob, params, r) = _squashed_square(1.0)
    flat = x.at[:, 1].set(0.0)                # both triangles collapsed onto a line
    assert np.isinf(float(_energy(flat, prob, params, r)))
    assert np.all(np.isfinite(np.asarray(jax.grad(_energy)(flat, prob, params, r))))


def test_check_grads_on_the_spring_energy_with_the_collapse_barrier_active():
    p, t = meshgen.rectangle(2.0, 1.0, 2, 1)
    mat = MODELS["mass-spring"]
    _, params, r = _setup(mat, p, t)
    rng = np.random.default_rng(3)
    Fd = np.diag([1.0, 0.05, 0.0])[:, :2][None] + 0.01 * rng.normal(size=(len(t), 3, 2))
    C = jnp.asarray(np.swapaxes(Fd, 1, 2) @ Fd)
    from jaxvalve.mechanics.materials import collapse_barrier
    assert np.all(np.asarray(collapse_barrier(C, mat.collapse_J)) > 0)     # all active
    # det C ~ 2.5e-3: difference steps well below it
    check_grads(lambda c: jnp.sum(mat.energy_density(c, r.springs)), (C,), order=2,
                modes=["fwd", "rev"], atol=1e-6, rtol=1e-6, eps=1e-7)


def test_mass_spring_collapse_barrier_holds_a_sliver_apex_off_its_base():
    """A sliver (apex v 0.05 mm above a 2 mm base, angle 2.9 degrees) whose apex spring to
    a node above is compressed (that node moved from 1 to 0.5 mm): along v's way down to
    the base the springs alone lose energy all the way to the collapse (J = 0); with the
    barrier the energy has an interior minimum at 0 < J < 0.1, an equilibrium with zero
    force on v, and grows without bound towards the collapse."""
    from scipy.optimize import minimize_scalar
    from jaxvalve.mechanics import materials as M

    p = np.array([[0, 0], [2, 0], [1, 0.05], [1, 1], [1, -1.0]])
    t = np.array([[0, 1, 2], [0, 2, 3], [2, 1, 3], [0, 4, 1]])       # t[0]: the sliver
    prob, params, r = _setup(MassSpring.linear(1.0), p, t)
    x = np.c_[p, np.zeros(5)]
    x[3, 1] = 0.5

    def energy(y):
        return _energy(jnp.asarray(x).at[2, 1].set(y), prob, params, r)

    grad_y = jax.grad(lambda y: energy(y))
    ys = np.geomspace(0.05, 1e-6, 40)
    e = np.array([float(energy(y)) for y in ys])
    J = ys / 0.05
    assert np.all(np.diff(e[J >= 0.1]) < 0)           # down to J = 0.1 it pays to collapse
    springs = e - np.array([float(H * 0.05 * M.collapse_barrier(
        jnp.asarray([[[1.0, 0.0], [0.0, (y / 0.05) ** 2]]]), 0.1)[0]) for y in ys])
    assert np.all(np.diff(springs) < 0)                # the springs alone: all the way down
    assert np.isinf(float(energy(0.0)))                # collapsed: no way through
    best = minimize_scalar(lambda y: float(energy(y)), bounds=(1e-7, 0.005),
                           method="bounded", options=dict(xatol=1e-12))
    J_star = best.x / 0.05
    assert 1e-4 < J_star < 0.1
    assert best.fun < e[-1] and best.fun < e[J >= 0.1].min()
    assert abs(float(grad_y(best.x))) < 1e-6 * abs(float(grad_y(0.05)))
