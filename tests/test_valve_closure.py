"""The three-leaflet valve closes: equilibrium, no crossing, symmetry, contact pressure,
invariance under a rigid motion of the root, and consistent coaptation metrics.

One coarse benchmark valve (h = 1.5 mm, 3 x ~400 triangles, St.Venant-Kirchhoff) is closed
once per module; the notebook test uses the same mesh, so the compiled solve is shared.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve import Scene, simulate

from jaxvalve.mechanics import assembly
from jaxvalve import valve as V
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.mechanics.problem import mmhg

H = 1.5


@pytest.fixture(scope="module")
def closed():
    return simulate(Scene(h=H, model="stvk"))


def _rot_z(deg):
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_closure_is_an_equilibrium(closed):
    """The residual recomputed from the returned state, outside the solver, is below the
    tolerance at both loads."""
    sc, v = closed.scene, closed.valve
    for x, p in ((closed.x_he, sc.he_pressure), (closed.x, sc.pressure)):
        params = v.params(sc.material(), p, sc.contact_law(), sc.thickness, 0.0,
                          sc.bending_law())
        params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), params)
        import types
        from jaxvalve.contact import pairs as pair_lists
        from jaxvalve.solvers import adjoint
        # the residual by autodiff of the energies, on pair lists built afresh at x
        lists, _ = pair_lists.allocate(v.contact_topology, params.ref, jnp.asarray(x),
                                       params.contact.dhat, 0.0, 0.0)
        pairs = adjoint.fixed_pairs(types.SimpleNamespace(lists=lists,
                                                          topo=v.contact_topology))
        R = jax.jit(adjoint.residual)(jnp.asarray(x), v.problem, params, pairs)
        scale = assembly.pressure_scale(jnp.asarray(x), v.problem, params)
        assert float(jnp.linalg.norm(R) / scale) < sc.rtol


def test_no_leaflets_cross(closed):
    """Exact triangle-triangle test (no code shared with contact): no crossing at 3 and
    at 80 mmHg, commissure touching excluded."""
    assert len(V.leaflet_crossings(closed.valve, closed.x_he)) == 0
    assert len(V.leaflet_crossings(closed.valve, closed.x)) == 0


def test_state_check_rejects_crossed_leaflets_and_folded_triangles(closed):
    """`state_failure`, which `simulate` applies to every state a solver accepts, passes
    the closed valve and catches leaflets pushed 1.5 mm through one another, a leaflet
    node pulled through its neighbours (a fold) and a NaN."""
    from jaxvalve.solvers import RESULTS
    from stress_suite import penetrated_start
    v = closed.valve
    assert V.state_failure(v, closed.x) is None and V.state_failure(v, closed.x_he) is None
    assert V.state_failure(v, penetrated_start(v, closed.x, 1.5)) == "leaflets_cross"
    x = np.array(closed.x)
    sl = v.leaflet_slice(0)
    free = np.flatnonzero(~np.asarray(v.problem.fixed)[sl])
    i = sl.start + free[len(free) // 2]                 # an interior node of leaflet 0
    nb = np.unique(v.triangles[np.any(v.triangles == i, axis=1)])
    far = nb[np.argmax(np.linalg.norm(x[nb] - x[i], axis=1))]
    x[i] = x[far] + 2.0 * (x[far] - x[i])               # through its star
    assert V.state_failure(v, x) in ("inverted_triangles", "leaflets_cross")
    x[i, 0] = np.nan
    assert V.state_failure(v, x) == RESULTS.nonfinite.name
    assert all(r.result == "successful" for r in closed.solves)


def test_a_failed_state_check_is_the_valves_outcome_not_the_solvers():
    """`ValveSolution`: the solver's code stays its own (the solver did converge), while
    ``converged`` is False and ``status`` and ``describe()`` name the valve's check; the
    check's names are not solver `RESULTS`."""
    from jaxvalve.solvers import RESULTS, Stats
    stats = Stats(steps=3, force_evals=3, hvps=0, residual=jnp.asarray(1e-7))
    ok = V.ValveSolution(x=jnp.zeros((1, 3)), result=jnp.asarray(0), stats=stats)
    assert ok.converged and ok.status == "successful"
    bad = V.ValveSolution(x=ok.x, result=ok.result, stats=stats, state="leaflets_cross")
    assert int(bad.result) == RESULTS.successful and not bad.converged
    assert bad.status == "leaflets_cross" and "leaflets cross" in bad.describe()
    assert not (set(V.STATE_FAILURES) - {"nonfinite"}) & set(RESULTS.__members__)
    leaves, tree = jax.tree_util.tree_flatten(bad)         # a pytree: state is static
    assert jax.tree_util.tree_unflatten(tree, leaves).state == "leaflets_cross"


def test_closed_valve_is_threefold_symmetric(closed):
    """The benchmark root and the loads are symmetric under 120-degree turns about the
    axis, and so is the closed valve: leaflet i+1 is leaflet i turned by 120 degrees."""
    v = closed.valve
    axis = np.asarray(v.root.axis)
    assert np.allclose(np.abs(axis), [0, 0, 1])
    for i in range(3):
        xi = closed.x[v.leaflet_slice(i)]
        xj = closed.x[v.leaflet_slice((i + 1) % 3)]
        turned = (xi - v.root.origin) @ _rot_z(120.0).T + v.root.origin
        assert np.max(np.abs(turned - xj)) < 0.05


def test_coapted_sheets_carry_the_pressure(closed):
    """Where two leaflets are pressed together over a wide zone, the barrier balances the
    diastolic pressure: the gap lies inside (0, d_hat), and there the point-triangle
    terms alone, p(d) = -2 kappa (d / d_hat) B'(d^2 / d_hat^2) for two parallel sheets,
    carry a part of the pressure P (the edge-edge terms the rest), not more than P."""
    m, sc = closed.metrics, closed.scene
    law = sc.contact_law()
    dhat, kappa = float(law.dhat), float(law.stiffness)
    gap = np.min(m.gap, axis=1)
    pressed = (gap > 0) & (gap < dhat)            # 0: the sewn commissure nodes
    assert pressed.sum() > 50
    d = float(np.median(gap[pressed]))
    z = d * d / (dhat * dhat)
    dB = -2.0 * (z - 1.0) * np.log(z) - (z - 1.0) ** 2 / z
    p_pt = -2.0 * kappa * (d / dhat) * dB
    assert 0.2 * mmhg(sc.pressure) < p_pt < mmhg(sc.pressure), (d, p_pt)


def test_metrics_are_consistent(closed):
    m, s = closed.metrics, closed.summary()
    assert closed.converged
    assert 0 < s["h_CC"] <= s["h"] + 1e-9
    assert 0 < s["h_c"] <= s["h_E"]
    assert np.all((m.ncca > 0) & (m.ncca < 1))
    # h_avr = zone area / free-edge length, NCCA = zone area / cusp area
    assert np.allclose(m.h_avr * m.free_edge_length, m.ncca * m.area)
    # loading from 3 to 80 mmHg widens the coaptation
    assert np.sum(closed.metrics.zone_area) > np.sum(closed.metrics_he.zone_area)
    for prof in m.profile:
        assert len(prof) > 0


def test_rigid_motion_of_the_root_moves_the_valve_rigidly(closed):
    """Closing the same valve in a turned and shifted root gives the turned and shifted
    closed state and the same metrics (the compiled solve is reused: same shapes)."""
    sc = closed.scene
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]) @ _rot_z(33.0)
    t = np.array([3.0, -2.0, 5.0])
    root = sc.load_root().transformed(R, t)
    valve = V.build_valve(root, mesh_leaflet(sc.template(), sc.h))
    moved = simulate(sc, valve=valve)
    assert np.max(np.abs(moved.x - (closed.x @ R.T + t))) < 0.05
    a, b = closed.summary(), moved.summary()
    for k in a:
        assert b[k] == pytest.approx(a[k], abs=0.05), k


def test_commissure_corners_are_found_in_the_state_not_at_the_roots_points(closed):
    """The leaflets' shared corners are the fixed nodes of different leaflets that coincide
    in the state: in the placement they are exactly the nodes at the root's three
    commissure points (two leaflets each), and under a rigid motion, which moves them off
    those points (as a design map does), the closed valve still has no crossing."""
    v = closed.valve
    g = V.commissure_groups(v, v.x_placed)
    com = np.asarray(v.root.commissures)
    at = np.linalg.norm(np.asarray(v.x_placed)[:, None] - com[None], axis=-1) < 1e-9
    assert sorted(np.bincount(g[g >= 0]).tolist()) == [2, 2, 2]
    np.testing.assert_array_equal(g >= 0, np.any(at, axis=1))
    R = _rot_z(17.0)
    moved = np.asarray(closed.x) @ R.T + np.array([3.0, -2.0, 5.0])
    assert len(V.leaflet_crossings(v, moved)) == 0
    assert len(V.leaflet_crossings(v, closed.x)) == 0
