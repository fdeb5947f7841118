"""The closure engine on the benchmark valve (`jaxvalve.solvers.equilibrium.Engine`: FIRE
on the barrier contact in one compiled loop, a Newton finish where FIRE stagnates):
converged, never crossed (the project's exact test and the IPC toolkit's), the leaflets
coapting inside the barrier's range, and the finish's tangent the exact Jacobian."""
import numpy as np
import pytest
import jax.numpy as jnp

from jaxvalve import Scene
from jaxvalve.contact import pairs as pair_lists
from jaxvalve.contact.barrier import BarrierContact, collision_weights
from jaxvalve.simulation import build_scene_valve, measure
from jaxvalve.solvers import adjoint
from jaxvalve.solvers.tangent import Tangent
from jaxvalve.valve import leaflet_crossings
from jaxvalve.valve.closure import close_valve
from stress_suite import ipctk_intersects

#: the benchmark valve at a coarse mesh (3 x 457 triangles)
H = 1.5
SCENE = Scene(h=H)


@pytest.fixture(scope="module")
def valve():
    return build_scene_valve(SCENE)


@pytest.fixture(scope="module")
def closed(valve):
    return close_valve(valve, SCENE)


def _ipctk_intersects(valve, x):
    pytest.importorskip("ipctk")
    return ipctk_intersects(valve, x)


def test_engine_closure_converges_without_crossing(valve, closed):
    for ls in closed:
        assert ls.converged, ls.report.describe()
        assert ls.report.residual < SCENE.rtol
        assert len(leaflet_crossings(valve, ls.x)) == 0
        assert not _ipctk_intersects(valve, ls.x)
    x = closed[1].x
    # the leaflets coapt: their smallest gap lies inside the barrier's range, above zero
    gap = pair_lists.min_distance(valve.contact_topology, jnp.asarray(valve.ref), x)
    assert 0.0 < gap < BarrierContact().dhat
    m = measure(valve, x, SCENE.g_c)
    assert m.ncca_valve > 0.3 and m.h_cc > 5.0 and m.h_c > 2.0


def test_ipctk_sees_a_crossing_that_the_check_must_catch(valve, closed):
    """The independent check is not blind: leaflet 0 pushed 1.5 mm through its neighbours."""
    x = closed[1].x.copy()
    centre = x.mean(axis=0)
    sl = valve.leaflet_slice(0)
    d = centre - x[sl].mean(axis=0)
    x[sl] += 1.5 * d / np.linalg.norm(d)
    assert _ipctk_intersects(valve, x)
    assert len(leaflet_crossings(valve, x)) > 0


def test_tangent_is_the_exact_jacobian_at_the_closed_valve(valve, closed):
    """`Tangent` (membrane, bending with its fold barrier, follower pressure, barrier
    pairs) times v against a central difference of the residual over the closure's fixed
    pair list; it is not symmetric (the follower pressure)."""
    sol = closed[1].solution
    x = np.asarray(sol.x)
    params = valve.params(SCENE.material(), SCENE.pressure, SCENE.contact_law(),
                          SCENE.thickness, 0.0, SCENE.bending_law())
    pairs = adjoint.fixed_pairs(sol)
    assert int(pairs.n_pt) > 50 and int(pairs.n_ee) > 50
    free = np.asarray(valve.problem.free)
    v = np.random.default_rng(1).normal(size=x.shape) * free[:, None] * 1e-3
    R = lambda y: np.asarray(adjoint.residual(jnp.asarray(y), valve.problem, params, pairs))
    eps = 1e-3
    fd = (R(x + eps * v) - R(x - eps * v)) / (2 * eps)
    w = collision_weights(params.ref, valve.problem.triangles, pairs.tri_edge, pairs.n_edges)
    K = Tangent(valve.problem).matrix(x, params, pairs, w)
    jv = np.zeros_like(x)
    jv[free] = -(K @ v[free].reshape(-1)).reshape(-1, 3)
    np.testing.assert_allclose(jv, fd, atol=1e-6 * np.abs(fd).max())
    assert abs(K - K.T).max() > 1e-6 * abs(K).max()


def test_newton_finish_converges_quadratically_from_a_disturbed_equilibrium(valve, closed):
    """`finish.newton_finish` from the closed valve with every free node moved by up to
    0.05 mm (a relative residual of order 1e-1): converged within 6 steps, the residual at
    least squared (to a constant) by the last steps, and no crossing."""
    from jaxvalve import progress
    from jaxvalve.solvers import Engine
    from jaxvalve.solvers.finish import newton_finish

    sol = closed[1].solution
    params = valve.params(SCENE.material(), SCENE.pressure, SCENE.contact_law(),
                          SCENE.thickness, 0.0, SCENE.bending_law())
    x = np.asarray(sol.x)
    free = np.asarray(valve.problem.free)[:, None]
    rng = np.random.default_rng(3)
    # a smooth disturbance: a random combination of low-order functions of position
    c = x - x.mean(axis=0)
    x0 = x + 0.05 * free * np.tanh(c @ rng.normal(size=(3, 3)) / 10.0)
    seen = []
    real = progress.beacon
    progress.beacon = lambda n, r, s="": seen.append(float(r))
    try:
        out = newton_finish(valve.problem, params, jnp.asarray(x0), Engine(rtol=1e-10), sol)
    finally:
        progress.beacon = real
    assert out.converged, out.describe()
    assert out.newton_steps <= 6, seen
    r = np.asarray(seen)                 # the best residual at each step, the last the final
    assert r[0] > 1e-3
    # quadratic convergence at the end: r_{k+1} <= C r_k^2, C bounded by the first step
    assert r[-1] <= 1e3 * r[-2] ** 2, r
    assert len(leaflet_crossings(valve, np.asarray(out.x))) == 0
