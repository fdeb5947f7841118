"""Pruned pair list of the soft-min contact law (`contact.soft_pairs`): it gives the same
energy and forces as the soft minimum over every Verlet candidate (`soft_distance`, the
definition, assembled into an energy here), also after the nodes have moved (within
margin / 4); it is rebuilt when they moved further, and it never drops pairs silently."""
import numpy as np
import pytest
import jax
import jax.numpy as jnp

from jaxvalve.contact import SmoothContact, build_neighbours_checked, node_areas
from jaxvalve.contact.smooth import soft_energy_reference
from jaxvalve.contact.soft_pairs import build_soft_pairs, refresh
from sheets import combine, grid_sheet

MARGIN = 0.25
SKIN = 0.6


def _scene(seed=3):
    """Two crumpled sheets 0.15 mm apart (within the 0.2 mm gap in places)."""
    rng = np.random.default_rng(seed)
    sheets = []
    for k in range(2):
        p, t = grid_sheet(7, 3.0, z=0.15 * k)
        p[:, :2] += 0.15 * (3.0 / 7) * rng.uniform(-1, 1, (len(p), 2))
        p[:, 2] += 0.25 * np.sin(1.1 * p[:, 0] + k) * np.cos(0.8 * p[:, 1])
        p[:, 2] += 0.03 * rng.standard_normal(len(p))
        if k == 1:   # upper sheet faces down: the sheets face each other with their +n
            t = t[:, ::-1].copy()
        sheets.append((p, t))
    x, tri, body = combine(*sheets)
    return jnp.asarray(x), jnp.asarray(tri), body


@pytest.fixture(scope="module")
def scene():
    x, tri, body = _scene()
    law = SmoothContact(soft_min=True, one_sided=False)
    base = build_neighbours_checked(x, tri, body, law.gap + SKIN)
    return x, tri, jnp.asarray(body), node_areas(x, tri), law, base


_vg = jax.jit(jax.value_and_grad(lambda x, c, tri, nb, area: c.energy(x, tri, nb, area)))
_vg_ref = jax.jit(jax.value_and_grad(
    lambda x, c, tri, nb, area: soft_energy_reference(c, x, tri, nb, area)))
_build = jax.jit(build_soft_pairs, static_argnums=(4,))
_refresh = jax.jit(refresh)


@pytest.mark.parametrize("one_sided", [False, True])
def test_pruned_energy_and_forces_equal_the_full_soft_minimum(scene, one_sided):
    x, tri, body, area, law, base = scene
    law = SmoothContact(soft_min=True, one_sided=one_sided)
    pairs = _build(base, x, tri, law, 4096, MARGIN)
    e_full, g_full = _vg_ref(x, law, tri, base, area)
    e_pr, g_pr = _vg(x, law, tri, pairs, area)
    assert float(e_full) > 1e-4                     # the sheets do touch
    assert abs(float(e_pr) - float(e_full)) <= 1e-12 * float(e_full)
    np.testing.assert_allclose(g_pr, g_full, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(g_full))))
    # given the Verlet list itself, the energy prunes at x with no margin: every dropped
    # triangle weighs < exp(-25) = 1.4e-11 of the nearest, hence a bound of 1e-10
    e_nb, g_nb = _vg(x, law, tri, base, area)
    assert abs(float(e_nb) - float(e_full)) <= 1e-10 * float(e_full)
    np.testing.assert_allclose(g_nb, g_full, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(g_full))))
    # and it is a real pruning: fewer pairs than Verlet candidates (h = 0.43 mm here, so
    # reach + margin = 0.5 mm holds more triangles than on the valve, where 6750 of 39336)
    assert 0 < int(pairs.n) < 0.7 * int(base.n_pairs)


def test_a_stale_list_stays_exact_for_moves_below_a_quarter_margin(scene):
    x, tri, body, area, law, base = scene
    pairs = _build(base, x, tri, law, 4096, MARGIN)
    rng = np.random.default_rng(0)
    for trial in range(3):
        step = rng.standard_normal(x.shape)
        step *= 0.24 * MARGIN / np.linalg.norm(step, axis=1, keepdims=True)
        y = x + jnp.asarray(step)
        e_full, g_full = _vg_ref(y, law, tri, base, area)
        e_pr, g_pr = _vg(y, law, tri, pairs, area)
        assert abs(float(e_pr) - float(e_full)) <= 1e-12 * float(e_full)
        np.testing.assert_allclose(g_pr, g_full, rtol=0,
                                   atol=1e-12 * float(jnp.max(jnp.abs(g_full))))


def test_pruning_would_be_wrong_without_the_margin(scene):
    """The checks above can fail: built with no margin, the list misses triangles after a
    move (those that come within reach were not listed), and the energy is off by far
    more than the 1e-12 those checks allow."""
    x, tri, body, area, law, base = scene
    tight = SmoothContact(soft_min=True, softness=0.004)       # reach 0.1 mm
    pairs = _build(base, x, tri, tight, 4096, 0.0)
    y = x.at[:, 0].add(0.3 * jnp.sin(3.0 * x[:, 1]))        # a shear of up to 0.3 mm
    e_full = float(_vg_ref(y, tight, tri, base, area)[0])
    e_pr = float(_vg(y, tight, tri, pairs, area)[0])
    assert abs(e_pr - e_full) > 1e-10 * e_full


def test_refresh_rebuilds_only_after_a_quarter_margin(scene):
    x, tri, body, area, law, base = scene
    pairs = _build(base, x, tri, law, 4096, MARGIN)
    small = _refresh(pairs, x.at[0, 2].add(0.2 * MARGIN), tri, body, SKIN, law)
    np.testing.assert_array_equal(small.x_build, pairs.x_build)
    big = _refresh(pairs, x.at[0, 2].add(0.3 * MARGIN), tri, body, SKIN, law)
    assert float(big.x_build[0, 2]) == pytest.approx(float(x[0, 2]) + 0.3 * MARGIN)
    # a Verlet rebuild always rebuilds the pruned list (its groups refer to that layout)
    far = _refresh(pairs, x.at[0, 2].add(0.6 * SKIN), tri, body, SKIN, law)
    assert float(far.base.x_build[0, 2]) == pytest.approx(float(x[0, 2]) + 0.6 * SKIN)
    assert float(far.x_build[0, 2]) == pytest.approx(float(x[0, 2]) + 0.6 * SKIN)


def test_overflow_is_flagged_and_sticky(scene):
    x, tri, body, area, law, base = scene
    full = _build(base, x, tri, law, 4096, MARGIN)
    n = int(full.n)
    small = _build(base, x, tri, law, n // 2, MARGIN)
    assert bool(small.soft_overflow) and bool(small.overflow)
    assert int(small.soft_count) == n and int(small.n) == n // 2
    again = _refresh(small, x.at[0, 2].add(MARGIN), tri, body, SKIN, law)
    assert bool(again.soft_overflow)                   # sticky across rebuilds


def test_stale_lists_are_rebuilt_at_the_first_update_exactly(scene):
    """The solve starts from empty lists (`stale_list`, `stale_soft_pairs`) that its first
    update builds: the result equals a list built directly."""
    from jaxvalve.contact import stale_list
    from jaxvalve.contact.soft_pairs import stale_soft_pairs
    x, tri, body, area, law, base = scene
    stale = stale_soft_pairs(stale_list(x.shape[0], tri, np.asarray(body), base.cutoff,
                                        capacity=base.capacity), 4096, MARGIN)
    assert stale.base.capacity == base.capacity and int(stale.n) == 0
    fresh = _refresh(stale, x, tri, body, SKIN, law)
    np.testing.assert_array_equal(fresh.base.cand, base.cand)
    np.testing.assert_array_equal(fresh.base.row_group, base.row_group)
    direct = _build(base, x, tri, law, 4096, MARGIN)
    assert int(fresh.n) == int(direct.n) > 0
    np.testing.assert_array_equal(fresh.tri, direct.tri)
    np.testing.assert_array_equal(fresh.group, direct.group)


def test_whole_lists_give_the_same_energy_forces_and_second_derivatives(scene):
    """`neighbours.whole_lists` (used to trace the adjoint's programs) evaluates the whole
    pruned list in one branch instead of a `lax.switch` over prefixes: the energy, forces
    and a Hessian-vector product are the same, and the program has fewer branches."""
    from jaxvalve.contact.neighbours import whole_lists

    x, tri, body, area, law, base = scene
    law = SmoothContact(soft_min=True, one_sided=True)
    pairs = _build(base, x, tri, law, 8192, MARGIN)
    v = jnp.asarray(np.random.default_rng(1).standard_normal(x.shape))

    def hvp(x, pairs):
        f = lambda z: jax.grad(lambda y: law.energy(y, tri, pairs, area))(z)
        return law.energy(x, tri, pairs, area), f(x), jax.jvp(f, (x,), (v,))[1]

    def whole(x, pairs):
        with whole_lists():
            return hvp(x, pairs)

    e0, g0, h0 = jax.jit(hvp)(x, pairs)
    e1, g1, h1 = jax.jit(whole)(x, pairs)
    assert float(e0) > 1e-4 and int(pairs.n) < pairs.soft_capacity // 2  # a prefix is used
    assert abs(float(e1) - float(e0)) <= 1e-13 * float(e0)
    np.testing.assert_allclose(g1, g0, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(g0))))
    np.testing.assert_allclose(h1, h0, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(h0))))
    # lax.switch is a `cond` over its branches: the whole-list program has fewer of them
    n_cond = lambda f: str(jax.make_jaxpr(f)(x, pairs)).count("cond[")
    assert n_cond(whole) < n_cond(hvp)


@pytest.mark.parametrize("one_sided", [False, True])
def test_law_parameter_derivatives_are_finite_and_match_differences(scene, one_sided):
    # the one-sided law's groups without pairs had side -inf; masked in the energy, it
    # still put 0 * inf = NaN into d/d(gap) of the energy and of the forces
    x, tri, body, area, _, base = scene
    law0 = SmoothContact(soft_min=True, one_sided=one_sided)
    pairs = _build(base, x, tri, law0, 4096, MARGIN)
    assert int(pairs.n) > 0 and float(law0.gap) > 0
    v = jnp.asarray(np.random.default_rng(1).normal(size=x.shape))

    @jax.jit
    def f(theta):
        law = SmoothContact(stiffness=theta[0], gap=theta[1], softness=theta[2],
                            soft_min=True, one_sided=one_sided)
        e, g = jax.value_and_grad(lambda y: law.energy(y, tri, pairs, area))(x)
        return jnp.stack([e, jnp.sum(v * g)])

    theta = jnp.array([1.0, 0.2, 0.01])
    J = np.asarray(jax.jacrev(f)(theta))
    assert np.all(np.isfinite(J))
    for k, h in enumerate((1e-4, 1e-6, 1e-7)):
        d = jnp.zeros(3).at[k].set(h)
        fd = (np.asarray(f(theta + d)) - np.asarray(f(theta - d))) / (2 * h)
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-5, atol=1e-9 * np.max(np.abs(J)))
    assert abs(J[0, 1]) > 0      # the energy does depend on the gap
