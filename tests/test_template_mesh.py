"""Leaflet template geometry and its quasi-uniform mesh."""
import math

import numpy as np
import pytest

from jaxvalve.errors import ParameterError
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet, mesh_quality
from jaxvalve.geometry.template import PAPER_TEMPLATES, Template, free_point, sutured_point

TPL = Template(r=12.0, a=6.7, b=15.0)


def _polyline_length(p):
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


@pytest.mark.parametrize("alpha", [90.0, 160.0, 180.0])
def test_corners_satisfy_the_template_definition(alpha):
    t = Template(r=12.0, a=5.0, b=16.0, alpha=alpha)
    P = t.points
    O, A, B, C, D, E = (P[k] for k in "OABCDE")
    np.testing.assert_allclose([np.linalg.norm(B - O), np.linalg.norm(C - O)], [t.r, t.r])
    ang = math.degrees(math.acos(np.dot(B - O, C - O) / t.r ** 2))
    np.testing.assert_allclose(ang, min(alpha, 360 - alpha), rtol=1e-12)
    np.testing.assert_allclose([np.linalg.norm(A - B), np.linalg.norm(D - C)], [t.a, t.a])
    np.testing.assert_allclose([np.dot(A - B, B - O), np.dot(D - C, C - O)], [0, 0], atol=1e-12)
    np.testing.assert_allclose([np.linalg.norm(E - A), np.linalg.norm(D - E)], [t.b, t.b])
    assert E[0] == 0 and E[1] > A[1]
    np.testing.assert_allclose(np.linalg.norm(D - A), t.chord)


def test_edge_lengths_match_the_formulas():
    u = np.linspace(0, 1, 20001)
    np.testing.assert_allclose(_polyline_length(sutured_point(u, TPL.r, TPL.a, TPL.alpha)),
                               2 * TPL.a + math.pi * TPL.r * TPL.alpha / 180, rtol=1e-7)
    np.testing.assert_allclose(_polyline_length(free_point(u, TPL.r, TPL.a, TPL.b, TPL.alpha)),
                               2 * TPL.b, rtol=1e-12)
    # the sutured parametrisation is by arc length: equal steps in t, equal lengths
    steps = np.linalg.norm(np.diff(sutured_point(u, TPL.r, TPL.a, TPL.alpha), axis=0), axis=1)
    np.testing.assert_allclose(steps, TPL.sutured_length / 20000, rtol=1e-6)


@pytest.mark.parametrize("field,kw,match", [
    ("r", dict(r=0.0, a=5, b=15), "r must be > 0"),
    ("a", dict(r=12, a=-1, b=15), "a must be > 0"),
    ("b", dict(r=12, a=5, b=0), "b must be > 0"),
    ("alpha", dict(r=12, a=5, b=15, alpha=360), r"alpha must lie in \(0, 180\]"),
    ("alpha", dict(r=12, a=5, b=15, alpha=180.5), r"alpha must lie in \(0, 180\]"),
    ("alpha", dict(r=12, a=5, b=15, alpha=0.0), r"alpha must lie in \(0, 180\]"),
    ("b", dict(r=12, a=5, b=12.0), "b must exceed"),
    ("r", dict(r=float("nan"), a=5, b=15), "r must be finite"),
])
def test_impossible_templates_are_rejected_with_the_bound(field, kw, match):
    with pytest.raises(ParameterError, match=match):
        Template(**kw)


def test_paper_fig3_templates_violate_the_design_validity_rule():
    """Documented discrepancy (docs/benchmark-notes.md): under the template geometry 2b < |AD|
    for all three."""
    for kw in PAPER_TEMPLATES.values():
        with pytest.raises(ParameterError, match="b must exceed"):
            Template(**kw)


def test_mesh_is_deterministic_and_labels_its_edges():
    m1, m2 = mesh_leaflet(TPL, 1.5), mesh_leaflet(TPL, 1.5)
    np.testing.assert_array_equal(m1.points, m2.points)
    np.testing.assert_array_equal(m1.triangles, m2.triangles)
    P = TPL.points
    np.testing.assert_allclose(m1.points[m1.sutured[0]], P["A"], atol=1e-12)
    np.testing.assert_allclose(m1.points[m1.sutured[-1]], P["D"], atol=1e-12)
    np.testing.assert_allclose(m1.points[m1.free[0]], P["A"], atol=1e-12)
    np.testing.assert_allclose(m1.points[m1.free[-1]], P["D"], atol=1e-12)
    assert np.any(np.all(np.isclose(m1.points[m1.free], P["E"]), axis=1))
    # sutured nodes lie on A-B-C-D at their recorded arc-length fractions
    np.testing.assert_allclose(m1.points[m1.sutured],
                               sutured_point(m1.sutured_t, TPL.r, TPL.a, TPL.alpha), atol=1e-12)
    np.testing.assert_allclose(m1.points[m1.free],
                               free_point(m1.free_t, TPL.r, TPL.a, TPL.b, TPL.alpha), atol=1e-12)
    # boundary = sutured + free nodes exactly
    t = m1.triangles
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    bnodes = np.unique(u[c == 1])
    np.testing.assert_array_equal(bnodes, np.union1d(m1.sutured, m1.free))


def test_boundary_nodes_are_evenly_spaced_on_each_edge():
    m = mesh_leaflet(TPL, 1.0)
    L = TPL.sutured_length
    u = m.sutured_t * L
    arc = math.radians(TPL.alpha) * TPL.r
    for lo, hi in [(0, TPL.a), (TPL.a, TPL.a + arc), (TPL.a + arc, L)]:
        s = np.diff(u[(u >= lo - 1e-9) & (u <= hi + 1e-9)])
        np.testing.assert_allclose(s, s.mean(), rtol=1e-9)
        assert s.mean() <= 1.0 + 1e-9
    f = np.diff(m.free_t * TPL.free_length)
    np.testing.assert_allclose(f, f.mean(), rtol=1e-9)


def test_mesh_quality_and_size():
    m = mesh_leaflet(TPL, 1.0)
    q = m.quality()
    assert q["min_angle"] >= 25.0
    assert q["edge_cv"] < 0.2
    assert 0.85 < q["edge_mean"] < 1.15
    assert np.all(_signed(m) > 0)
    # the triangle count scales like area / h^2
    q2 = mesh_leaflet(TPL, 2.0).quality()
    assert 3.0 < q["n_triangles"] / q2["n_triangles"] < 5.0


def test_mesh_area_converges_to_the_exact_template_area_at_second_order():
    """Chords replace the arc: the area error is O(h^2)."""
    errs = []
    hs = [2.0, 1.0, 0.5]
    for h in hs:
        m = mesh_leaflet(TPL, h)
        errs.append(abs(_signed(m).sum() - TPL.area))
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 1.8), rates


def test_mesh_quality_report_of_an_equilateral_triangle():
    p = np.array([[0, 0], [1, 0], [0.5, math.sqrt(3) / 2]])
    q = mesh_quality(p, np.array([[0, 1, 2]]))
    np.testing.assert_allclose([q["min_angle"], q["edge_ratio"], q["edge_cv"]], [60, 1, 0],
                               atol=1e-12)


def test_bad_mesh_size_is_rejected():
    for h in (0.0, -1.0, float("nan"), 100.0):
        with pytest.raises(ParameterError, match="mesh size h"):
            mesh_leaflet(TPL, h)


def _signed(m):
    p, t = m.points, m.triangles
    e1, e2 = p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
