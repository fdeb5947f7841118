"""Placement of three leaflets in a root (paper Section 1) and the P = 0 start."""
import numpy as np
import pytest

from jaxvalve import valve as V
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.mechanics.materials import StVenantKirchhoff
from jaxvalve.valve.placement import along_polyline
from jaxvalve.geometry.root import benchmark_root
from jaxvalve.geometry.template import Template

TPL = Template(r=12.0, a=7.1, b=15.0)


@pytest.fixture(scope="module")
def valve():
    root = benchmark_root(TPL.sutured_length)
    return V.build_valve(root, mesh_leaflet(TPL, 3.0))


def _normals(x, tri):
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    return n / np.linalg.norm(n, axis=1)[:, None]


def test_along_polyline_is_exact_on_a_polyline():
    p = np.array([[0, 0, 0], [3, 0, 0], [3, 4, 0.0]])  # length 7
    q = along_polyline(p, np.array([0, 3 / 7, 5 / 7, 1]))
    np.testing.assert_allclose(q, [[0, 0, 0], [3, 0, 0], [3, 2, 0], [3, 4, 0]], atol=1e-12)


def test_sutured_nodes_sit_on_the_paths_uniformly_by_arc_length(valve):
    lm, root = valve.leaflet, valve.root
    np.testing.assert_allclose(valve.suture_strain, 0.0, atol=1e-8)
    for i in range(3):
        x = valve.x_placed[valve.leaflet_slice(i)]
        xs = x[lm.sutured]
        # A and D on the two commissures of this leaflet
        ends = {tuple(np.round(xs[0], 9)), tuple(np.round(xs[-1], 9))}
        com = {tuple(np.round(root.commissures[i], 9)),
               tuple(np.round(root.commissures[(i + 1) % 3], 9))}
        assert ends == com
        # each sutured node lies on the path polyline, at the arc-length fraction of its
        # position along the template's sutured edge
        frac, dist = _project(root.paths[i], xs)
        assert dist.max() < 1e-9
        t = lm.sutured_t if frac[0] < 0.5 else 1 - lm.sutured_t
        np.testing.assert_allclose(frac, t, atol=1e-9)


def _project(path, pts):
    """Arc-length fraction and distance of each point's nearest point on the polyline."""
    a, b = path[:-1], path[1:]
    ab = b - a
    seg = np.linalg.norm(ab, axis=1)
    s0 = np.concatenate([[0], np.cumsum(seg)])
    fr, dist = [], []
    for p in pts:
        u = np.clip(np.sum((p - a) * ab, 1) / seg ** 2, 0, 1)
        q = a + u[:, None] * ab
        d = np.linalg.norm(p - q, axis=1)
        k = np.argmin(d)
        fr.append((s0[k] + u[k] * seg[k]) / s0[-1])
        dist.append(d[k])
    return np.array(fr), np.array(dist)


def test_placed_leaflets_face_the_axis(valve):
    """Normals point from the aortic to the ventricular side: toward the valve axis."""
    x, tri = valve.x_placed, valve.triangles
    inner = ~np.any(valve.problem.fixed[tri], axis=1)
    n = _normals(x, tri)[inner]
    c = x[tri].mean(1)[inner]
    radial_in = -c[:, :2] / np.linalg.norm(c[:, :2], axis=1)[:, None]
    assert np.all(np.sum(n[:, :2] * radial_in, axis=1) > 0.5)


def test_placement_is_equivariant_under_rigid_motion(valve):
    th = 0.7
    R = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
    t = np.array([1.0, -2.0, 3.0])
    moved = V.build_valve(valve.root.transformed(R, t), valve.leaflet)
    np.testing.assert_allclose(moved.x_placed, valve.x_placed @ R.T + t, atol=1e-9)


def test_start_is_fold_free_and_leaflets_do_not_cross(valve):
    """The harmonic start: every triangle keeps the orientation of its leaflet's plane
    (no flipped triangle), areas stay positive, and no two leaflets intersect."""
    from jaxvalve.valve.intersect import leaflets_intersect
    from jaxvalve.valve.placement import leaflet_frame

    x, tri, root = valve.x_start, valve.triangles, valve.root
    n = _normals(x, tri)
    body = valve.body[tri[:, 0]]
    for i in range(3):
        _, _, en, _ = leaflet_frame(root.commissures[i], root.commissures[(i + 1) % 3],
                                    root.axis, root.origin)
        assert np.min(n[body == i] @ en) > 0.5
    assert len(V.leaflet_crossings(valve, x)) == 0
    # the only contacts are the 4 triangle pairs at each of the 3 shared commissures
    assert len(leaflets_intersect(x, tri, valve.body)) == 12


def test_crossing_leaflets_are_detected(valve):
    """Push leaflet 0's belly through the others: the independent check finds it."""
    x = valve.x_start.copy()
    sl = valve.leaflet_slice(0)
    free = ~np.asarray(valve.problem.fixed)[sl]
    xs = x[sl]
    xs[free, :2] *= -1.0  # mirror the free nodes through the axis
    x[sl] = xs
    assert len(V.leaflet_crossings(valve, x)) > 0


def test_closure_at_zero_pressure_keeps_the_sutures_and_lowers_the_residual(valve):
    v, sol = V.settle(valve, StVenantKirchhoff(1.0, 0.45))
    fixed = np.asarray(v.problem.fixed)
    np.testing.assert_array_equal(v.x_start[fixed], valve.x_placed[fixed])
    assert np.all(np.isfinite(v.x_start))
    assert float(sol.stats.residual) < 1e-2
