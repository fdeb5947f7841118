"""The differentiable chain theta = (r, a, b, alpha) -> reference mesh, suturing paths,
sutured positions, equilibrium and smooth coaptation metrics (`jaxvalve.valve.design`)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.solvers import adjoint, equilibrium
from jaxvalve.solvers.equilibrium import Engine
from jaxvalve import valve as V
from jaxvalve.coaptation import annulus_level
from jaxvalve.coaptation.smooth import smooth_metrics, smooth_plan
from jaxvalve.valve.design import BenchmarkPaths, FixedPaths, ValveDesign
from jaxvalve.errors import MeshError, ParameterError
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.geometry.leaflet_mesh import _edge_counts
from jaxvalve.valve.placement import along_path
from jaxvalve.geometry.root import benchmark_root
from jaxvalve.scene import Scene
from jaxvalve.geometry.template import Template
from jaxvalve.geometry.template_map import template_map

BASE = (12.0, 7.1, 15.0, 160.0)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled():
    """The gradient of a whole closure compiles large programs: free them afterwards."""
    yield
    jax.clear_caches()


def _fd(fun, theta, k, e):
    d = np.zeros(4)
    d[k] = e
    return (np.asarray(fun(jnp.asarray(theta) + d)) - np.asarray(fun(jnp.asarray(theta) - d))) / (2 * e)


@pytest.mark.parametrize("h", [1.2, 3.0])
def test_template_map_reproduces_the_mesher_and_its_jacobian_matches_fd(h):
    m = mesh_leaflet(Template(*BASE), h)
    tm = template_map(m)
    np.testing.assert_allclose(np.asarray(tm.points(*BASE)), m.points, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(tm.sutured_t(12.0, 7.1, 160.0)), m.sutured_t,
                               rtol=0, atol=1e-14)
    theta = jnp.asarray((12.5, 6.8, 15.4, 150.0))
    J = jax.jacfwd(lambda t: tm.points(*t))(theta)
    for k in range(4):
        fd = _fd(lambda t: tm.points(*t), theta, k, 1e-6)
        np.testing.assert_allclose(np.asarray(J[..., k]), fd, rtol=0, atol=1e-7)


def test_template_map_boundary_equals_the_mesher_at_a_new_template():
    """Where the edge node counts agree, the mapped boundary is the mesher's boundary."""
    new = Template(12.5, 6.8, 15.4, 150.0)
    assert _edge_counts(new, 1.2) == _edge_counts(Template(*BASE), 1.2)
    tm = template_map(mesh_leaflet(Template(*BASE), 1.2))
    q = mesh_leaflet(new, 1.2)
    K = len(q.sutured) + len(q.free) - 2
    np.testing.assert_allclose(np.asarray(tm.points(12.5, 6.8, 15.4, 150.0))[:K],
                               q.points[:K], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(tm.sutured_t(12.5, 6.8, 150.0)), q.sutured_t,
                               rtol=0, atol=1e-12)


def test_remesh_flag_and_wrong_mesh():
    tm = template_map(mesh_leaflet(Template(*BASE), 2.0))
    assert not tm.needs_remesh(12.5, 7.5, 15.5)
    assert tm.quality(12.5, 7.5, 15.5)["min_angle"] > 20.0
    assert tm.needs_remesh(20.0, 1.0, 25.0)          # far away: distorted triangles
    m = mesh_leaflet(Template(*BASE), 2.0)
    bad = type(m)(m.template, m.h, m.points + 0.1, m.triangles, m.sutured, m.sutured_t,
                  m.free, m.free_t)
    with pytest.raises(MeshError, match="boundary"):
        template_map(bad)


def test_benchmark_height_solves_the_fit_and_its_implicit_derivative():
    root = benchmark_root(47.71, wall=False)
    bp = BenchmarkPaths.from_root(root)
    assert abs(float(bp.height(47.71)) - root.dimensions["commissure_height"]) < 1e-9
    e = 1e-5
    fd = (benchmark_root(47.71 + e, wall=False).dimensions["commissure_height"]
          - benchmark_root(47.71 - e, wall=False).dimensions["commissure_height"]) / (2 * e)
    assert abs(float(jax.grad(bp.height)(47.71)) - fd) < 1e-7 * abs(fd)
    # the paths at L have length L, and reproduce the root's paths
    paths = bp(jnp.asarray(47.71))
    for p, q in zip(paths, root.paths):
        np.testing.assert_allclose(np.asarray(p), q, atol=1e-9)
        assert abs(float(jnp.sum(jnp.linalg.norm(jnp.diff(p, axis=0), axis=1))) - 47.71) < 1e-9


def test_along_path_interpolates_by_arc_length_and_is_differentiable():
    """Points at fraction t lie at arc length t L (checked per segment by hand), a
    repeated vertex changes nothing, and d/dt matches central differences."""
    rng = np.random.default_rng(3)
    path = np.cumsum(rng.normal(size=(9, 3)), axis=0)
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.sort(rng.uniform(0, 1, 15))
    k = np.searchsorted(s, t * s[-1], side="right") - 1
    want = path[k] + ((t * s[-1] - s[k]) / seg[k])[:, None] * (path[k + 1] - path[k])
    np.testing.assert_allclose(np.asarray(along_path(path, t)), want, atol=1e-12)
    doubled = np.insert(path, 4, path[4], axis=0)
    np.testing.assert_allclose(np.asarray(along_path(doubled, t)), want, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(along_path(np.vstack([path, path[-1:]]), [1.0]))))
    g = jax.jacfwd(lambda tt: along_path(jnp.asarray(path), tt))(jnp.asarray(t))
    fd = (np.asarray(along_path(path, t + 1e-7)) - np.asarray(along_path(path, t - 1e-7))) / 2e-7
    np.testing.assert_allclose(np.einsum("kik->ki", np.asarray(g)), fd, atol=1e-6)


def test_bad_design_inputs_raise_with_the_bound():
    bp = BenchmarkPaths.from_root(benchmark_root(47.71, wall=False))
    with pytest.raises(ParameterError, match="sutured_length .* accepted range"):
        bp.height(200.0)
    assert np.isnan(float(jax.jit(bp.height)(200.0)))      # traced: NaN, never a wrong H
    with pytest.raises(ParameterError, match="BenchmarkPaths needs"):
        BenchmarkPaths.from_root(type("R", (), {"dimensions": {}})())


@pytest.fixture(scope="module")
def design():
    sc = Scene(h=2.5)
    lm = mesh_leaflet(sc.template(), 2.5)
    valve = V.build_valve(sc.load_root(), lm)
    return sc, valve, ValveDesign.build(valve, template_map(lm))


def test_design_at_base_reproduces_the_valve_and_fixed_positions_have_fd_jacobian(design):
    sc, valve, d = design
    th = jnp.asarray(BASE)
    np.testing.assert_allclose(np.asarray(d.ref(th)), np.asarray(valve.ref), atol=1e-12)
    fixed = np.asarray(valve.problem.fixed)
    xf = np.asarray(d.x_fixed(th))
    np.testing.assert_allclose(xf[fixed], valve.x_placed[fixed], atol=1e-9)
    np.testing.assert_array_equal(xf[~fixed], valve.x_start[~fixed])
    J = jax.jacfwd(lambda t: d.x_fixed(t)[fixed])(th)
    for k in range(4):
        np.testing.assert_allclose(np.asarray(J[..., k]),
                                   _fd(lambda t: d.x_fixed(t)[fixed], th, k, 1e-6), atol=1e-7)
    # b moves neither the sutured edge nor the root
    assert float(jnp.max(jnp.abs(J[..., 2]))) == 0.0
    with pytest.raises(ParameterError, match="template b must exceed"):
        d.ref((12.0, 7.1, 10.0, 160.0))                  # 2b < |AD|
    with pytest.raises(ParameterError, match="template r must be > 0"):
        d.x_fixed((-1.0, 7.1, 15.0, 160.0))


def test_fixed_paths_put_sutured_nodes_on_the_given_paths(design):
    sc, valve, d = design
    fp = ValveDesign.build(valve, d.tmap, FixedPaths(valve.root.paths))
    pos = np.asarray(fp.sutured_positions(jnp.asarray((12.3, 7.3, 15.0, 160.0))))
    for i in range(3):
        path = np.asarray(valve.root.paths[i])
        # every point lies on a segment of the polyline
        seg = np.diff(path, axis=0)
        rel = pos[i][:, None, :] - path[None, :-1]
        t = np.clip(np.sum(rel * seg, -1) / np.sum(seg * seg, -1), 0, 1)
        dist = np.linalg.norm(rel - t[..., None] * seg, axis=-1).min(axis=1)
        assert dist.max() < 1e-9


def test_metric_gradients_through_the_closure_match_central_differences(design):
    """d(smooth h_E, h_c, h_avr, h_C-C at 3 mmHg)/d(r, a, b) by the implicit adjoint
    (`adjoint.implicit_state`, one LU solve) vs central differences of the same chain,
    each re-closed by the engine from the closed state (relative error < 1e-3)."""
    sc, valve, d = design
    mat, con, ben = sc.material(), sc.contact_law(), sc.bending_law()
    engine = Engine(rtol=1e-10)
    base = valve.params(mat, 3.0, con, bending=ben)

    def closed(theta, x_free):
        params = base.replace(ref=d.ref(theta))
        return equilibrium.solve(valve.problem, params, d.x_fixed(theta, x_free=x_free),
                                 engine, throw=False, topo=valve.contact_topology)

    th = jnp.asarray(BASE)
    first = closed(th, jnp.asarray(valve.x_start))
    assert first.converged, float(first.stats.residual)
    x = np.asarray(first.x)
    root = valve.root
    s0 = annulus_level(x, np.asarray(valve.problem.fixed), valve.body, root.axis, root.origin)
    plan = smooth_plan(x, valve.triangles, valve.body, valve.free_edge, axis=root.axis,
                       origin=root.origin, annulus_level=s0)
    w = jnp.asarray([1.0, 0.7, 0.5, 0.3])

    def metrics(y):
        m = smooth_metrics(y, plan, 0.1)
        return jnp.stack([m["h_e"], m["h_c"], m["h_avr_valve"], m["h_cc"]])

    sol = closed(th, jnp.asarray(x))
    assert sol.converged

    def chain(t):
        params = base.replace(ref=d.ref(t))
        y = adjoint.implicit_state(valve.problem, params, d.x_fixed(t, x_free=x), sol)
        return jnp.sum(w * metrics(y))

    metrics_jit = jax.jit(metrics)

    def closed_metrics(t):
        s = closed(t, jnp.asarray(x))
        assert s.converged, float(s.stats.residual)
        return metrics_jit(s.x)

    v, g = jax.jit(jax.value_and_grad(chain))(th)
    assert float(v) == pytest.approx(float(jnp.sum(w * metrics_jit(sol.x))), abs=1e-12)
    for k in range(3):
        fd = float(np.sum(np.asarray(w) * _fd(closed_metrics, th, k, 1e-3)))
        assert abs(float(g[k]) - fd) < 1e-3 * abs(fd), (k, float(g[k]), fd)
    assert float(g[3]) != 0.0     # alpha moves the sutured edge: it has a gradient too
