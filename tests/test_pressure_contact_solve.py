"""Pressure load and contact inside a solve."""
import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve.mechanics import assembly

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen
from jaxvalve.contact import SmoothContact
from jaxvalve.mechanics.materials import NeoHookean
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import FIRE


def test_pressure_force_sums_to_pressure_times_projected_area_and_flips_with_orientation():
    p, t = meshgen.rectangle(2.0, 3.0, 3, 4)
    rng = np.random.default_rng(0)
    x = jnp.asarray(meshgen.lift(p) + 0.2 * rng.normal(size=(len(p), 3)))
    P = 0.01
    f = assembly.pressure_force(x, jnp.asarray(t), P)
    an = assembly.area_normals(x, jnp.asarray(t))
    np.testing.assert_allclose(jnp.sum(f, 0), P * jnp.sum(an, 0), rtol=1e-12)
    flat = assembly.pressure_force(jnp.asarray(meshgen.lift(p)), jnp.asarray(t), P)
    np.testing.assert_allclose(jnp.sum(flat, 0), [0, 0, P * 6.0], atol=1e-14)
    f_rev = assembly.pressure_force(x, jnp.asarray(t[:, [0, 2, 1]]), P)
    np.testing.assert_allclose(f_rev, -f, atol=1e-15)


def test_pressure_on_closed_surface_is_gradient_of_p_times_volume():
    """For a closed surface the follower load is conservative: F = P dV/dx."""
    p, t = meshgen.icosphere(2.0, 1)
    x = jnp.asarray(p * (1 + 0.05 * np.random.default_rng(1).normal(size=(len(p), 1))))
    t = jnp.asarray(t)

    def volume(y):
        yt = y[t]
        return jnp.sum(jnp.einsum("mi,mi->m", yt[:, 0], jnp.cross(yt[:, 1], yt[:, 2]))) / 6.0

    np.testing.assert_allclose(assembly.pressure_force(x, t, 0.02), 0.02 * jax.grad(volume)(x),
                               atol=1e-14)


def test_two_sheets_pressed_together_meet_at_the_predicted_gap_and_never_cross():
    """Two clamped discs 1 mm apart, each pushed toward the other by 80 mmHg.  Where they
    touch, the contact pressure k (g0 - d) carries the load P, so d = g0 - P / k."""
    p, t, b = meshgen.disk(5.0, 4)
    n = len(p)
    pts = np.concatenate([p, p])
    tri = np.concatenate([t, t[:, [0, 2, 1]] + n])  # second sheet faces the first
    prob, ref = make_problem(np.c_[pts, np.zeros(2 * n)], tri, fixed=np.r_[b, b],
                             body=np.r_[np.zeros(n, int), np.ones(n, int)])
    x0 = jnp.asarray(np.c_[pts, np.r_[np.zeros(n), np.ones(n)]])
    c = SmoothContact(stiffness=1.0, gap=0.2)
    P = mmhg(80.0)
    params = Params(ref=ref, material=NeoHookean(1 / 3), thickness=0.3, pressure=P, contact=c)
    sol = equilibrium.solve(prob, params, x0, FIRE(rtol=1e-7))
    x = np.asarray(sol.x)
    gap = x[n:, 2] - x[:n, 2]
    assert np.all(gap > 0)  # never crossed
    np.testing.assert_allclose(gap[0], 0.2 - P / 1.0, rtol=2e-3)
    # without contact the sheets pass through each other
    free = equilibrium.solve(prob, params.replace(contact=None), x0, FIRE(rtol=1e-7))
    assert float(free.x[n, 2] - free.x[0, 2]) < 0


def test_whole_lists_solve_traces_one_contact_branch_and_checks_its_flag():
    """`solve(..., whole_lists=True)` traces the soft-min contact on its whole pair list:
    its program has fewer `cond`s (no `lax.switch` over list prefixes) than the default
    one.  (The two give the same energy, forces and second derivatives:
    test_soft_pairs.py; the optimiser's closures use it, test_optimize.py.)"""
    import pytest
    from jaxvalve.errors import ParameterError

    p, t, b = meshgen.disk(5.0, 3)
    n = len(p)
    prob, ref = make_problem(np.c_[p, np.zeros(n)], t, fixed=b)
    x0 = jnp.asarray(np.c_[p, np.zeros(n)])
    c = SmoothContact(soft_min=True, one_sided=True)
    params = Params(ref=ref, material=NeoHookean(1 / 3), thickness=0.3, pressure=mmhg(80.0),
                    contact=c)
    nbrs = equilibrium.stale_pairs(c, prob, x0, 0.5)
    assert nbrs.soft_capacity >= 1024          # three prefixes by default: 1024, 512, 256
    conds = {flag: str(jax.make_jaxpr(equilibrium._solve_jit, static_argnums=(0, 5, 6))(
        FIRE(), prob, params, x0, nbrs, 0.5, flag)).count("cond[") for flag in (False, True)}
    assert conds[True] < conds[False]
    with pytest.raises(ParameterError, match="whole_lists must be True or False"):
        equilibrium.solve(prob, params, x0, FIRE(), whole_lists=1)
