"""Implicit (adjoint) gradients of functions of the equilibrium vs central finite differences."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.solvers import adjoint, equilibrium

from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import NewtonKrylov
from jaxvalve.errors import ParameterError

SOLVER = NewtonKrylov(rtol=1e-12)


@pytest.fixture(scope="module")
def disk():
    p, t, b = meshgen.disk(5.0, 3)
    prob, ref = make_problem(p, t, fixed=b)
    return prob, ref, jnp.asarray(meshgen.lift(p)), b


def objective(prob):
    def f(params, x0):
        x = equilibrium.solve(prob, params, x0, SOLVER).x
        return jnp.sum(x[:, 2] ** 2) + jnp.sum(x[:, 0] * x[:, 2])
    return f


def _fd(fun, h):
    return (fun(h) - fun(-h)) / (2 * h)


@pytest.mark.parametrize("mat", [StVenantKirchhoff(1.0, 0.45), NeoHookean(1 / 3),
                                 Gent(1 / 3, 2.3), MassSpring(0.5, 1.0, 2.0, break1=0.01,
                                                              break2=0.03)],
                         ids=["stvk", "nh", "gent", "ms"])
def test_implicit_gradient_matches_central_differences(disk, mat):
    prob, ref, x0, fixed = disk
    params = Params(ref=ref, material=mat, thickness=0.3, pressure=mmhg(80.0))
    # jitted: each finite difference then reuses one compiled solve (op by op, the
    # adjoint and the objective ran as hundreds of small programs)
    f = jax.jit(objective(prob))
    g, gx0 = jax.jit(jax.grad(f, argnums=(0, 1)))(params, x0)
    leaves, tdef = jax.tree_util.tree_flatten(params)
    gleaves = jax.tree_util.tree_leaves(g)
    checked = 0
    for i, (leaf, gl) in enumerate(zip(leaves, gleaves)):
        if jnp.ndim(leaf) != 0 or float(leaf) == 0.0:
            continue
        h = 1e-5 * abs(float(leaf))

        def fun(e, i=i, leaf=leaf):
            new = list(leaves)
            new[i] = leaf + e
            return f(jax.tree_util.tree_unflatten(tdef, new), x0)

        num = float(_fd(fun, h))
        assert abs(float(gl) - num) <= 1e-4 * abs(num) + 1e-9, (i, float(gl), num)
        checked += 1
    assert checked >= 3  # material moduli, thickness, pressure
    rng = np.random.default_rng(0)
    d = rng.normal(size=ref.shape)
    num = float(_fd(lambda e: f(params.replace(ref=ref + e * d), x0), 1e-5))
    np.testing.assert_allclose(float(jnp.sum(g.ref * d)), num, rtol=1e-4)
    d = rng.normal(size=x0.shape) * fixed[:, None]
    num = float(_fd(lambda e: f(params, x0 + e * d), 1e-5))
    np.testing.assert_allclose(float(jnp.sum(gx0 * d)), num, rtol=1e-4)
    # the equilibrium does not depend on the start position of free nodes
    assert float(jnp.max(jnp.abs(gx0[~fixed]))) == 0.0


def test_implicit_state_gives_the_solve_gradient_without_rerunning_the_solver(disk):
    """`implicit_state(problem, params, x0, solution)` is the converged state as a function
    of params and fixed positions: same value and same adjoint gradient as `solve`; an
    unconverged solution has no adjoint."""
    from jaxvalve.errors import ConvergenceError

    prob, ref, x0, fixed = disk
    params = Params(ref=ref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.3,
                    pressure=mmhg(80.0))
    sol = equilibrium.solve(prob, params, x0, SOLVER)
    lift = jnp.asarray(np.where(fixed[:, None], [[0.0, 0.0, 0.3]], 0.0))

    def through_solve(p, x):
        y = equilibrium.solve(prob, p, x, SOLVER).x
        return jnp.sum(y[:, 2] ** 2) + jnp.sum(y[:, 0] * y[:, 2])

    def through_state(p, x):
        y = adjoint.implicit_state(prob, p, x, sol)
        return jnp.sum(y[:, 2] ** 2) + jnp.sum(y[:, 0] * y[:, 2])

    g1 = jax.jit(jax.grad(through_solve, argnums=(0, 1)))(params, x0)
    g2 = jax.grad(through_state, argnums=(0, 1))(params, x0)
    assert float(through_state(params, x0)) == float(through_solve(params, x0))
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-9, atol=1e-12)
    assert float(jnp.sum(jnp.abs(g2[1] * lift))) > 0       # fixed positions do matter
    bad = equilibrium.solve(prob, params, x0, NewtonKrylov(rtol=1e-12, max_steps=1),
                            throw=False)
    with pytest.raises(ConvergenceError, match="relative residual"):
        adjoint.implicit_state(prob, params, x0, bad)


def test_an_adjoint_off_equilibrium_is_refused_not_returned(disk):
    """`solve_lu` checks each solution by the residual's VJP: at the equilibrium the check
    passes; on a tangent that is not the residual's Jacobian (a state the solve never
    reached, with a pair list that does not belong to it) it would fail, so here the check
    is driven by a right-hand side the LU solves exactly and a tolerance of zero."""
    from jaxvalve.errors import ConvergenceError

    prob, ref, x0, fixed = disk
    params = Params(ref=ref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.3,
                    pressure=mmhg(80.0))
    sol = equilibrium.solve(prob, params, x0, SOLVER)
    g = np.ones(x0.shape)
    mu, rep = adjoint.solve_lu(prob, params, sol.x, None, g)
    assert rep.residual <= 1e-12
    old = adjoint.ADJOINT_RTOL
    try:
        adjoint.ADJOINT_RTOL = 0.0
        with pytest.raises(ConvergenceError, match="relative residual of .* by the residual"):
            adjoint.solve_lu(prob, params, sol.x, None, g)
    finally:
        adjoint.ADJOINT_RTOL = old


def test_assembled_stiffness_is_the_exact_jacobian_without_contact(disk):
    """Without contact, `tangent.Tangent` (element Hessians, the follower pressure's
    Jacobian, hinge Hessians) is K = -dR/dx on the free dofs exactly: it equals the
    Jacobian of the residual by autodiff, and the LU adjoint solves to round-off.  With the whole rim held, the follower load is conservative on
    the free dofs, so K is symmetric there although the pressure blocks are not."""
    from jaxvalve.mechanics.bending import Bending
    from jaxvalve.solvers.adjoint import solve_lu
    from jaxvalve.solvers.tangent import Tangent

    prob, ref, x0, fixed = disk
    rng = np.random.default_rng(4)
    r = np.linalg.norm(np.asarray(ref)[:, :2], axis=1)
    x = np.asarray(x0) + 0.05 * rng.normal(size=x0.shape)
    x[:, 2] += 0.8 * (1 - (r / 5.0) ** 2)
    x[fixed] = np.asarray(x0)[fixed]
    x = jnp.asarray(x)
    params = Params(ref=ref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.3,
                    pressure=mmhg(80.0), bending=Bending(1.0))
    K = Tangent(prob).matrix(x, params).toarray()
    J = jax.jit(jax.jacfwd(lambda y: adjoint.residual(y, prob, params, None)))(x)
    free = np.repeat(np.asarray(prob.free), 3)
    Kx = -np.asarray(J).reshape(3 * len(free) // 3, -1)[free][:, free]
    assert K.shape == Kx.shape == (free.sum(), free.sum())
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    np.testing.assert_allclose(K, Kx, rtol=0, atol=1e-10 * np.abs(Kx).max())
    g = jnp.asarray(rng.normal(size=x.shape))
    mu, rep = solve_lu(prob, params, x, None, g)
    assert rep.residual < 1e-10
    assert np.all(mu[~np.asarray(prob.free)] == 0.0)
    # a right-hand side with a NaN, or of the wrong shape, is refused before any assembly
    bad = np.array(g)
    bad[3, 1] = np.nan
    with pytest.raises(ParameterError, match="g must be finite; it holds 1 NaN"):
        solve_lu(prob, params, x, None, bad)
    with pytest.raises(ParameterError, match=r"g must be \(\d+, 3\) or \(k, \d+, 3\)"):
        solve_lu(prob, params, x, None, np.asarray(g)[:-1])
