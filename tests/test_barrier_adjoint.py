"""The adjoint of a barrier closure (`jaxvalve.solvers.adjoint.solve_lu` on the closure's
fixed pair list, and `residual_vjp` with the collision weights as functions of the
reference): derivatives
of a function of the equilibrium with respect to the modulus and to the reference
geometry match central differences of re-solved equilibria.

Two clamped disks, their normals facing, 0.3 mm apart: the pressure bulges each toward
the other, and they meet at the centre on the barrier, so the derivatives pass through
the contact (its weights move with the reference, and the closing distance with E)."""
import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.solvers import adjoint

from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.bending import Bending
from jaxvalve.contact.barrier import BarrierContact
from jaxvalve.contact.ipc_pairs import barrier_topology, build_pairs
from jaxvalve.mechanics.materials import StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem
from jaxvalve.solvers import RESULTS, equilibrium
from jaxvalve.solvers.equilibrium import Engine

R, GAP, P = 5.0, 0.3, 0.004        # mm, mm, MPa
#: disk 1's reference is 2 % smaller than its placed size (pre-stretched, so stiffer):
#: the disks are not mirror images, and where they meet moves with E
SCALE = 0.98


def _disks(scale=SCALE):
    """(problem, params, topology, x0, up): disk 0 at z = 0 (normal +z), disk 1 at z = GAP
    (normal -z) whose reference is ``scale`` times its placed size; up: disk 1's nodes."""
    p, t, edge = meshgen.disk(R, 4)
    n = len(p)
    # disk 1: the mirror image of disk 0 turned over (y -> -y, z -> -z), so its triangles
    # are counter-clockwise in its reference and its normal is -z where it is placed
    tri = np.concatenate([t, t[:, [0, 2, 1]] + n])
    ref = np.concatenate([p, scale * p * [1.0, -1.0]])
    x0 = np.concatenate([meshgen.lift(p), meshgen.lift(p) + [0.0, 0.0, GAP]])
    body = np.repeat([0, 1], n)
    fixed = np.concatenate([edge, edge])
    prob, jref = make_problem(ref, tri, fixed=fixed, body=body)
    params = Params(ref=jref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.1,
                    pressure=P, contact=BarrierContact(), bending=Bending())
    topo = barrier_topology(tri, body, ref, fixed, x0)
    return prob, params, topo, x0, np.arange(n, 2 * n)


def _solve(prob, params, topo, x0):
    sol = equilibrium.solve(prob, params, x0, Engine(rtol=1e-11), throw=False)
    assert int(sol.result) == RESULTS.successful, (int(sol.result), float(sol.stats.residual))
    return sol


def _g(x, up):
    """The function differentiated: the mean height of disk 1 (mm)."""
    return float(np.mean(np.asarray(x)[up, 2]))


@pytest.fixture(scope="module")
def closed():
    prob, params, topo, x0, up = _disks()
    sol = _solve(prob, params, topo, x0)
    return prob, params, topo, x0, up, sol


def test_the_disks_meet_on_the_barrier(closed):
    prob, params, topo, x0, up, sol = closed
    x = np.asarray(sol.x)
    gap = build_pairs(topo, x, 1.0).min_distance
    assert 0.0 < gap < float(params.contact.dhat)
    assert int(sol.lists.act.n_pt) > 0 and int(sol.lists.act.n_ee) > 0


def test_adjoint_derivatives_match_central_differences(closed):
    prob, params, topo, x0, up, sol = closed
    x = np.asarray(sol.x)
    g = np.zeros_like(x)
    g[up, 2] = 1.0 / len(up)
    pairs = adjoint.fixed_pairs(sol)
    mu, rep = adjoint.solve_lu(prob, params, x, pairs, g)
    assert rep.residual < 1e-8
    # several right-hand sides, one factorisation: each the single solve's
    mus, reps = adjoint.solve_lu(prob, params, x, pairs, np.stack([2.0 * g, 0.0 * g, g]))
    assert mus.shape == (3,) + x.shape and len(reps) == 3
    np.testing.assert_allclose(mus[0], 2.0 * mu, rtol=1e-12, atol=1e-14 * np.abs(mu).max())
    assert np.all(mus[1] == 0.0) and np.array_equal(mus[2], mu)
    _, gp = adjoint.residual_vjp(jnp.asarray(x), prob, params, pairs, jnp.asarray(mu))
    # d/dE: the modulus, warm-started re-solves at E (1 +- s); a smaller s lets the
    # re-solves' own tolerance show (s = 1e-4: 4e-5 relative, 1e-5: 1.4e-3)
    s, E = 1e-3, 1.0
    fd = []
    for sign in (1, -1):
        pe = params.replace(material=dataclasses.replace(params.material, E=E * (1 + sign * s)))
        fd.append(_g(_solve(prob, pe, topo, x).x, up))
    dE = (fd[0] - fd[1]) / (2 * s * E)
    assert abs(float(gp.material.E) - dE) <= 1e-5 * abs(dE), (float(gp.material.E), dE)
    # d/d(scale) of disk 1's reference: it moves the strain and the collision weights (the
    # topology rebuilt from the scaled reference), both in the adjoint's residual VJP
    p2 = np.asarray(params.ref)[up] / SCALE       # d ref / d scale on disk 1
    d_adj = float(np.sum(np.asarray(gp.ref)[up] * p2))
    # a small step: a chord over s = 1e-3 or 1e-4 crosses points where the equilibrium's
    # derivative jumps (the barrier is C1, not C2, where a pair's closest feature
    # changes); at 1e-5 the re-solves' own tolerance shows at about 2e-5
    s = 1e-5
    fd = []
    for sign in (1, -1):       # params.ref and the weights' topology, the problem as it is
        _, prm, tp, _, _ = _disks(SCALE * (1.0 + sign * s))
        fd.append(_g(_solve(prob, params.replace(ref=prm.ref), tp, x).x, up))
    d_fd = (fd[0] - fd[1]) / (2 * s * SCALE)
    assert abs(d_adj - d_fd) <= 5e-5 * abs(d_fd), (d_adj, d_fd)


def test_the_weights_part_of_the_reference_derivative_is_not_zero(closed):
    """Leaving the collision weights out of the residual's VJP changes the reference
    derivative: the check above would fail if the weights did not move with it."""
    prob, params, topo, x0, up, sol = closed
    x = jnp.asarray(sol.x)
    pairs = adjoint.fixed_pairs(sol)
    mu = np.zeros(x.shape)
    mu[up, 2] = 1.0
    full = adjoint.residual_vjp(x, prob, params, pairs, jnp.asarray(mu))[1].ref
    strain = adjoint.residual_vjp(x, prob, params.replace(contact=None), None,
                                  jnp.asarray(mu))[1].ref
    assert float(jnp.max(jnp.abs(full - strain))) > 1e-8


def test_grad_through_the_barrier_solve_is_the_adjoint(closed):
    """jax.grad of a function of `equilibrium.solve`'s state (its custom VJP, one adjoint
    solve) equals the host adjoint's derivative with respect to E."""
    import jax
    prob, params, topo, x0, up, sol = closed
    x = np.asarray(sol.x)
    g = np.zeros_like(x)
    g[up, 2] = 1.0 / len(up)
    mu, _ = adjoint.solve_lu(prob, params, x, adjoint.fixed_pairs(sol), g)
    _, gp = adjoint.residual_vjp(jnp.asarray(x), prob, params, adjoint.fixed_pairs(sol),
                                 jnp.asarray(mu))
    f = lambda p: jnp.mean(adjoint.implicit_state(prob, p, x0, sol)[up, 2])
    dE = jax.grad(f)(params).material.E
    np.testing.assert_allclose(float(dE), float(gp.material.E), rtol=1e-10)
