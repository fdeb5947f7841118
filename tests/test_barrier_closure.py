"""The valve closed with the barrier contact and the projected Newton solver: converged,
never crossed (the project's exact test and the IPC toolkit's), forces that obey Newton's
third law, and an exact Jacobian that matches finite differences."""
import numpy as np
import pytest
import jax.numpy as jnp

from jaxvalve import Scene
from jaxvalve.contact.barrier import BarrierContact
from jaxvalve.contact.ipc_pairs import build_pairs
from jaxvalve.errors import ParameterError
from jaxvalve.simulation import build_scene_valve, measure
from jaxvalve.solvers import RESULTS, BarrierNewton, solve_barrier
from jaxvalve.solvers.barrier_newton import _Model
from stress_suite import ipctk_intersects
from jaxvalve.valve import leaflet_crossings

#: the benchmark valve at a coarse mesh (3 x 457 triangles); at h = 2-2.5 mm the solve
#: jumps into creased states or stagnates (docs/known-limits.md)
H = 1.5


@pytest.fixture(scope="module")
def valve():
    return build_scene_valve(Scene(h=H))


@pytest.fixture(scope="module")
def closed(valve):
    """The two closures of `simulate`, by the solver itself, so that its logs are kept."""
    sc = Scene(h=H)
    x, out = valve.x_start, {}
    for p in (3.0, 80.0):
        params = valve.params(sc.material(), p, BarrierContact(), 0.3, 0.0, sc.bending_law())
        sol, log = solve_barrier(valve.problem, params, x, BarrierNewton(rtol=1e-6),
                                 valve.barrier_topology)
        x = np.asarray(sol.x)
        out[p] = (sol, log, x)
    return out


def _ipctk_intersects(valve, x):
    pytest.importorskip("ipctk")
    return ipctk_intersects(valve, x)


def test_barrier_closure_converges_without_crossing(valve, closed):
    for p, (sol, log, x) in closed.items():
        assert int(sol.result) == RESULTS.successful, sol.describe()
        assert float(sol.stats.residual) < 1e-6
        # every accepted iterate kept all its pairs apart (CCD-filtered steps)
        assert min(log.min_gap) > 0
        assert len(leaflet_crossings(valve, x)) == 0
        assert not _ipctk_intersects(valve, x)
    x = closed[80.0][2]
    # the leaflets coapt: their smallest gap lies inside the barrier's range, above zero
    gap = build_pairs(valve.barrier_topology, x, 1.0).min_distance
    assert 0.0 < gap < BarrierContact().dhat
    m = measure(valve, x, 0.5)
    assert m.ncca_valve > 0.3 and m.h_cc > 5.0 and m.h_c > 2.0


def test_ipctk_sees_a_crossing_that_the_check_must_catch(valve, closed):
    """The independent check is not blind: leaflet 0 pushed 1.5 mm through its neighbours."""
    x = closed[80.0][2].copy()
    centre = x.mean(axis=0)
    sl = valve.leaflet_slice(0)
    d = centre - x[sl].mean(axis=0)
    x[sl] += 1.5 * d / np.linalg.norm(d)
    assert _ipctk_intersects(valve, x)


def _model(valve, p=80.0):
    sc = Scene(h=H)
    params = valve.params(sc.material(), p, BarrierContact(), 0.3, 0.0, sc.bending_law())
    return _Model(valve.problem, params, valve.barrier_topology)


def test_barrier_forces_obey_newtons_third_law(valve, closed):
    """The barrier energy is invariant under rigid motions, so its forces sum to zero and
    have no net torque, at the closed state where hundreds of pairs are active."""
    from jaxvalve.solvers.barrier_newton import _chunks, _ee_value_grad, _pt_value_grad
    x_np = closed[80.0][2]
    model = _model(valve)
    pairs = build_pairs(valve.barrier_topology, x_np, BarrierContact().dhat)
    assert len(pairs.pt) > 100 and len(pairs.ee) > 100
    x = jnp.asarray(x_np)
    g = np.zeros_like(x_np)
    for _, _, (rows, w) in _chunks(pairs.pt, pairs.pt_w):
        g += np.asarray(_pt_value_grad(model.law, x, rows, w)[1])
    for _, _, (rows, w, eps) in _chunks(pairs.ee, pairs.ee_w, pairs.ee_eps):
        g += np.asarray(_ee_value_grad(model.law, x, rows, w, eps)[1])
    scale = np.abs(g).sum()
    assert scale > 0
    np.testing.assert_allclose(g.sum(axis=0), 0.0, atol=1e-12 * scale)
    torque = np.cross(x_np - x_np.mean(axis=0), g).sum(axis=0)
    np.testing.assert_allclose(torque, 0.0, atol=1e-11 * scale * 30)


def test_exact_jacobian_matches_finite_differences(valve, closed):
    """The assembled exact Jacobian of the Newton-Krylov directions, -dF/dx . v (membrane,
    bending, follower pressure, barrier), against a central difference of the force at
    the closed valve; it is not symmetric (the follower pressure), and the projected
    tangent assembled beside it is."""
    x = closed[80.0][2]
    model = _model(valve)
    pairs = build_pairs(valve.barrier_topology, x, 0.3)
    v = np.random.default_rng(1).normal(size=x.shape) * model.free[:, None] * 1e-3
    eps = 1e-3
    fd = (model.evaluate(x + eps * v, pairs)[1] - model.evaluate(x - eps * v, pairs)[1]) / (2 * eps)
    K, Kx = model.tangent(x, pairs, exact=True)
    free = model.free
    jv = np.zeros_like(x)
    jv[free] = -(Kx @ v[free].reshape(-1)).reshape(-1, 3)
    np.testing.assert_allclose(jv, fd, atol=1e-5 * np.abs(fd).max())
    assert abs(Kx - Kx.T).max() > 1e-6 * abs(Kx).max()
    assert abs(K - K.T).max() <= 1e-12 * abs(K).max()


def test_projected_barrier_blocks_clamp_only_the_negative_curvature():
    """The tangent's barrier blocks (`_pt_blocks`): the exact Hessian of the pair's energy
    (against jax.hessian of the energy) and its projection, which is positive
    semi-definite and differs from it by a positive semi-definite matrix (only negative
    eigenvalues are raised); stiff along the contact normal; zero beyond d_hat."""
    import jax
    from jaxvalve.contact.barrier import pt_energies
    from jaxvalve.solvers.barrier_newton import _pt_blocks
    law = BarrierContact()
    w = np.array([0.7])
    rows = np.array([[0, 1, 2, 3]])
    for h in (0.01, 0.05, 0.15):
        x = np.array([[0.3, 0.2, h], [0, 0, 0], [1, 0, 0.2], [0, 1, -0.1]], float)
        Hp, He = (np.asarray(a)[0] for a in _pt_blocks(law, jnp.asarray(x), rows, w))
        Hx = np.asarray(jax.hessian(lambda y: pt_energies(
            law, y.reshape(4, 3), jnp.arange(4)[None], w)[0])(jnp.asarray(x.reshape(-1))))
        np.testing.assert_allclose(He, Hx, rtol=1e-9, atol=1e-12 * np.abs(Hx).max())
        scale = np.abs(Hx).max()
        assert np.linalg.eigvalsh(Hx)[0] < -1e-6 * scale      # indefinite: a real test
        assert np.linalg.eigvalsh(Hp)[0] >= -1e-10 * scale
        assert np.linalg.eigvalsh(Hp - Hx)[0] >= -1e-10 * scale
        n = np.zeros(12)
        n[2], n[[5, 8, 11]] = 1.0, -1.0 / 3.0                 # node up, triangle down
        assert n @ Hp @ n > 0
    x = np.array([[0.3, 0.2, 0.25], [0, 0, 0], [1, 0, 0], [0, 1, 0]], float)   # beyond d_hat
    assert not np.any(np.asarray(_pt_blocks(law, jnp.asarray(x), rows, w)[0]))


def test_tangent_is_symmetric_and_its_membrane_part_semidefinite(valve, closed):
    """The assembled tangent is symmetric; without the pressure term (P = 0) it is a sum
    of projected blocks, so v^T K v >= 0 for every v."""
    x = closed[80.0][2]
    pairs = build_pairs(valve.barrier_topology, x, BarrierContact().dhat)
    K = _model(valve).tangent(x, pairs)
    assert abs(K - K.T).max() <= 1e-12 * abs(K).max()
    K0 = _model(valve, p=0.0).tangent(x, pairs)
    V = np.random.default_rng(2).normal(size=(K0.shape[0], 20))
    assert np.min(np.einsum("ik,ik->k", V, K0 @ V)) >= -1e-10 * abs(K0).max()


def test_barrier_scene_validation():
    with pytest.raises(ParameterError, match="solver='newton'"):
        Scene(contact="barrier", solver="fire")
    with pytest.raises(ParameterError, match="float64"):
        Scene(contact="barrier", solver="newton", precision="float32")


def test_simulate_starts_the_barrier_closures_from_the_valve_swung_shut_by_fire(valve, closed):
    """`simulate` on the barrier path first swings the valve shut at 3 mmHg by FIRE on the
    penalty contact, then settles it on the barrier by Newton: a few Newton steps instead
    of ~100 from the placement, and the same equilibria (the final states are the
    barrier law's; the metrics agree with the closures from the placement)."""
    from jaxvalve import simulate
    lines = []
    res = simulate(Scene(h=H, contact="barrier", solver="newton", rtol=1e-6), valve=valve,
                   progress=lines.append)
    assert res.converged, [s.describe() for s in res.solves]
    assert any(ln.startswith("swinging shut at 3 mmHg") for ln in lines)
    he, closing = res.solves
    assert he.steps <= 20 < int(closed[3.0][0].stats.steps)
    assert len(leaflet_crossings(valve, res.x)) == 0
    ref = measure(valve, closed[80.0][2], 0.5)
    for k, v in dict(h_CC=ref.h_cc, h_avr=ref.h_avr_valve, h=ref.h, h_c=ref.h_c).items():
        assert res.summary()[k] == pytest.approx(v, abs=0.01), k
    assert res.h_E == pytest.approx(measure(valve, closed[3.0][2], 0.5).h_e, abs=0.01)


def test_a_newton_krylov_direction_is_cut_at_most_exact_halvings_times(valve, closed):
    """`_line_search` on an uphill direction (against the force, at the closed valve):
    a Newton-Krylov direction (judged by the residual) is given up after
    ``exact_halvings`` trial states, the projected one (judged by the merit) only after
    ``max_halvings``; the cap is what hands a poor Krylov step to the projected direction
    instead of accepting a step of 1e-9 (module docstring)."""
    from jaxvalve.solvers.barrier_newton import _line_search
    x = closed[80.0][2]
    model = _model(valve)
    dhat = BarrierContact().dhat
    pairs = build_pairs(valve.barrier_topology, x, dhat)
    E, F, fp = model.evaluate(x, pairs)
    scale = float(np.linalg.norm(fp[model.free]))
    res = float(np.linalg.norm(F)) / scale
    solver = BarrierNewton(rtol=1e-6, exact_halvings=3, max_halvings=7)
    d = -F / float(np.max(np.linalg.norm(F, axis=1))) * 0.05     # uphill, 0.05 mm at most
    slope = float(np.sum(F * d))
    assert slope < 0
    for exact, tries in ((True, 3), (False, 7)):
        ok, alpha, *_, evals = _line_search(model, valve.barrier_topology, x, d, E, fp, res,
                                            scale, slope, exact, dhat, solver)
        assert not ok
        assert evals == tries
        assert alpha == pytest.approx(0.5 ** tries, rel=1e-12)
