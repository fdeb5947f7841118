"""Aortic root: the benchmark root's fit, symmetry and anatomy; AorticRoot geometry/checks."""
import numpy as np
import pytest

from jaxvalve.errors import JaxvalveError, MeshError, ParameterError
from jaxvalve.geometry.mesh import validate_mesh
from jaxvalve.geometry.root import (BENCHMARK_HEIGHT_RANGE, AorticRoot, benchmark_length_range,
                           benchmark_path_length, benchmark_root, distance_to_surface)

RA, RC = 12.0, 13.0  # default annulus / STJ radii


@pytest.fixture(scope="module")
def root60():
    return benchmark_root(60.0)


def rot_z(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ----------------------------------------------------------------------- fit of the length
@pytest.mark.parametrize("L", [40.0, 50.0, 52.7, 55.0, 59.5, 60.0, 62.3, 65.0, 80.0])
def test_fitted_path_length_equals_sutured_length(L):
    r = benchmark_root(L, wall=False)
    np.testing.assert_allclose(r.path_lengths, L, rtol=1e-9, atol=0)
    assert r.dimensions["fitted_parameter"] == "commissure_height"
    H = r.dimensions["commissure_height"]
    assert benchmark_path_length(H) == pytest.approx(L, rel=1e-9)


def test_length_is_strictly_increasing_in_commissure_height():
    lo, hi = (f * RA for f in BENCHMARK_HEIGHT_RANGE)
    H = np.linspace(lo, hi, 200)
    L = np.array([benchmark_path_length(h) for h in H])
    assert np.all(np.diff(L) > 0)  # monotone -> the fitted height is unique
    Ls = np.linspace(35, 80, 10)
    Hs = [benchmark_root(x, wall=False).dimensions["commissure_height"] for x in Ls]
    assert np.all(np.diff(Hs) > 0)
    assert benchmark_length_range() == pytest.approx((L[0], L[-1]))


def test_commissure_heights_for_ozaki_lengths():
    H = {L: benchmark_root(L, wall=False).dimensions["commissure_height"]
         for L in (50, 55, 60, 65)}
    for L, h in zip(H, (18.08, 20.86, 23.60, 26.30)):
        assert H[L] == pytest.approx(h, abs=0.005)
        # no path on this wall can be shorter-walled than a rectangle: H >= (L - 2 pi Rc/3)/2
        assert H[L] > (L - 2 * np.pi * RC / 3) / 2
    # 50-60 mm: within 1.6 sd of the measured sinus height 1.69 +- 0.18 annulus radii
    for L in (50, 55, 60):
        assert abs(H[L] / RA - 1.69) < 1.6 * 0.18


def test_interleaflet_triangles_open_at_the_commissures(root60):
    """Neighbouring paths meet at a finite angle (2 beta), not tangentially."""
    H = root60.dimensions["commissure_height"]
    beta = np.degrees(np.arctan(np.pi * RC / 3 / (4 * H)))
    assert 7.0 < beta < 11.0  # ~ the 10 degree lean of the template's segments A-B, C-D
    for i in range(3):
        a, b = root60.paths[i], root60.paths[(i + 1) % 3]
        ta = np.degrees(np.arctan2(a[:, 1], a[:, 0]))
        tb = np.degrees(np.arctan2(b[:, 1], b[:, 0]))
        za = np.interp(H / 2, a[len(a) // 2:, 2], ta[len(a) // 2:])  # rising half of path i
        zb = np.interp(H / 2, b[len(b) // 2::-1, 2], tb[len(b) // 2::-1])  # falling half
        gap = np.radians((zb - za) % 360) * (RA + RC) / 2
        assert gap == pytest.approx(2 * (1 - 0.5 ** 0.25) * np.pi * RC / 3, rel=0.08)


@pytest.mark.parametrize("L", [10.0, 30.0, 95.0, 500.0])
def test_out_of_range_length_names_sutured_length_and_range(L):
    lo, hi = benchmark_length_range()
    with pytest.raises(ParameterError, match="sutured_length") as e:
        benchmark_root(L)
    assert f"{lo:.4f}" in str(e.value) and f"{hi:.4f}" in str(e.value)


@pytest.mark.parametrize("L", [0.0, -5.0, float("nan"), float("inf"), "60", True])
def test_bad_sutured_length(L):
    with pytest.raises(ParameterError, match="sutured_length"):
        benchmark_root(L)


@pytest.mark.parametrize("kw, name", [
    (dict(path_exponent=0.5), "path_exponent"),
    (dict(path_exponent=40.0), "path_exponent"),
    (dict(n_path=400), "n_path"),
    (dict(n_path=3), "n_path"),
    (dict(sinus_radius_ratio=1.0), "sinus_radius_ratio"),
    (dict(annulus_diameter=-24.0), "annulus_diameter"),
    (dict(stj_diameter=0.0), "stj_diameter"),
    (dict(wall_theta_cells=100), "wall_theta_cells"),
    (dict(wall_dz=0.0), "wall_dz"),
    (dict(lvot_length=-1.0), "lvot_length"),
    (dict(aorta_length="10"), "aorta_length"),
    (dict(first_commissure_angle=float("nan")), "first_commissure_angle"),
])
def test_bad_benchmark_parameters(kw, name):
    with pytest.raises(ParameterError, match=name):
        benchmark_root(60.0, **kw)


# ----------------------------------------------------------------------- symmetry / anatomy
def test_paths_are_rotations_of_each_other(root60):
    for i in range(3):
        j = (i + 1) % 3
        np.testing.assert_allclose(root60.paths[i] @ rot_z(120.0).T, root60.paths[j],
                                   atol=1e-12)
        np.testing.assert_allclose(root60.commissures[i] @ rot_z(120.0).T,
                                   root60.commissures[j], atol=1e-12)


def test_each_path_is_mirror_symmetric_about_its_mid_plane(root60):
    for i, p in enumerate(root60.paths):
        phi = np.radians(120.0 * i + 60.0)  # nadir direction of leaflet i
        n = np.array([-np.sin(phi), np.cos(phi), 0.0])  # normal of the mid-plane
        mirrored = p - 2 * (p @ n)[:, None] * n
        np.testing.assert_allclose(mirrored[::-1], p, atol=1e-12)


def test_commissures_at_stj_and_nadirs_on_annulus(root60):
    H = root60.dimensions["commissure_height"]
    np.testing.assert_allclose(root60.radial(root60.commissures), RC, rtol=1e-14)
    np.testing.assert_allclose(root60.commissures[:, 2], H, rtol=1e-14)
    np.testing.assert_allclose(root60.commissure_heights, H, rtol=1e-14)
    low = root60.lowest_points
    np.testing.assert_allclose(low[:, 2], 0.0, atol=1e-14)
    np.testing.assert_allclose(root60.radial(low), RA, rtol=1e-14)
    ang = np.degrees(np.arctan2(low[:, 1], low[:, 0])) % 360
    np.testing.assert_allclose(ang, [60.0, 180.0, 300.0], atol=1e-9)
    assert root60.annulus_level == 0.0 and root60.annulus_spread == 0.0
    # every path point between the annulus and the STJ, on the annulus-STJ cone
    for p in root60.paths:
        assert p[:, 2].min() >= 0 and p[:, 2].max() <= H
        np.testing.assert_allclose(root60.radial(p), RA + (RC - RA) * p[:, 2] / H, rtol=1e-12)
    for i in range(3):
        assert root60.commissure_distance(i) == pytest.approx(np.sqrt(3) * RC, rel=1e-14)
    np.testing.assert_array_equal(root60.axis, [0, 0, -1])
    np.testing.assert_array_equal(root60.origin, [0, 0, 0])


def test_commissures_counter_clockwise_seen_from_aorta(root60):
    ang = np.degrees(np.arctan2(root60.commissures[:, 1], root60.commissures[:, 0])) % 360
    np.testing.assert_allclose(ang, [0.0, 120.0, 240.0], atol=1e-9)


def test_wall_surface_anatomy(root60):
    pts, tri = root60.wall
    validate_mesh(pts, tri)  # manifold, consistently oriented, no degenerate triangles
    H = root60.dimensions["commissure_height"]
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert r.max() == pytest.approx(1.45 * RA, abs=0.02)  # sinus max radius
    np.testing.assert_allclose(r[pts[:, 2] < 0], RA, rtol=1e-12)  # LVOT stub
    np.testing.assert_allclose(r[pts[:, 2] > H + 1e-9], RC, rtol=1e-12)  # ascending aorta
    assert pts[:, 2].max() == pytest.approx(H + 10.0)
    # normals point away from the axis
    x = pts[tri]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    c = x.mean(axis=1)
    assert np.all(np.einsum("md,md->m", n[:, :2], c[:, :2]) > 0)


def test_paths_lie_on_the_wall(root60):
    d = root60.wall_distance()
    assert d.max() < 0.02  # mm; the continuous wall contains them exactly (see root.py)
    assert root60.wall_distance(root60.commissures).max() < 1e-9
    # a point 1 mm inside the annulus is 1 mm from the wall (less the 1-degree chord sag)
    assert root60.wall_distance([[RA - 1.0, 0.0, 0.0]])[0] == pytest.approx(1.0, abs=1e-4)


def test_distance_to_surface_matches_brute_force():
    rng = np.random.default_rng(0)
    r = benchmark_root(60.0, wall_theta_cells=24, wall_dz=4.0)
    V, T = r.wall
    q = rng.uniform([-20, -20, -3], [20, 20, 32], size=(40, 3))
    from jaxvalve.contact.geometry import point_triangle_distance_np as ptd
    brute = np.array([ptd(np.repeat(p[None], len(T), 0), V[T[:, 0]],
                          V[T[:, 1]], V[T[:, 2]]).min() for p in q])
    np.testing.assert_allclose(distance_to_surface(q, V, T), brute, rtol=1e-12)
    # and the closest-point routine itself on a unit triangle
    a, b, c = np.eye(3)[None, 0] * 0, np.eye(3)[None, 0], np.eye(3)[None, 1]
    for p, d in [((0.2, 0.2, 0.5), 0.5), ((2.0, 0.0, 0.0), 1.0), ((-1, -1, 0), np.sqrt(2)),
                 ((1, 1, 0), np.sqrt(0.5))]:
        assert ptd(np.array([p], float), a, b, c)[0] == pytest.approx(d)
    # a degenerate triangle (a segment, a point: a wall mesh may hold them) is measured
    # by its edges, never NaN
    s, e, m = np.array([[0.0, 0, 0]]), np.array([[2.0, 0, 0]]), np.array([[1.0, 0, 0]])
    assert ptd(np.array([[1.0, 1.0, 0.0]]), s, e, m)[0] == pytest.approx(1.0)
    assert ptd(np.array([[3.0, 1.0, 0.0]]), s, e, m)[0] == pytest.approx(np.sqrt(2.0))
    assert ptd(np.array([[3.0, 4.0, 0.0]]), s, s, s)[0] == pytest.approx(5.0)


# ----------------------------------------------------------------------- resampling
def test_resample_path_equal_arc_length_spacing(root60):
    for i in range(3):
        pts, s = root60.resample_path(i, 61)
        L = root60.path_lengths[i]
        np.testing.assert_array_equal(pts[0], root60.commissures[i])
        np.testing.assert_array_equal(pts[-1], root60.commissures[(i + 1) % 3])
        np.testing.assert_allclose(np.diff(s), L / 60, rtol=1e-12)
        assert s[0] == 0.0 and s[-1] == pytest.approx(L, rel=1e-15)
        chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        assert np.all(chord <= L / 60 * (1 + 1e-12)) and np.all(chord > 0.99 * L / 60)


def v_root(depth=10.0, nadir_frac=0.5):
    """Three V-shaped paths with a single interior point: exact arc-length expectations."""
    ang = np.radians([0.0, 120.0, 240.0])
    com = np.stack([10 * np.cos(ang), 10 * np.sin(ang), np.full(3, depth)], 1)
    paths = []
    for i in range(3):
        c0, c1 = com[i], com[(i + 1) % 3]
        mid = (1 - nadir_frac) * c0 + nadir_frac * c1
        paths.append(np.stack([c0, [mid[0], mid[1], 0.0], c1]))
    return AorticRoot(axis=[0, 0, -2.0], origin=[0, 0, 0], commissures=com, paths=paths)


def test_resample_path_exact_on_polyline():
    r = v_root()
    p = r.paths[0]
    pts, s = r.resample_path(0, 5)
    leg = np.linalg.norm(p[1] - p[0])
    np.testing.assert_allclose(s, np.arange(5) * leg / 2, rtol=1e-15)
    np.testing.assert_allclose(pts[1], (p[0] + p[1]) / 2, atol=1e-14)
    np.testing.assert_allclose(pts[2], p[1], atol=1e-14)
    np.testing.assert_allclose(pts[3], (p[1] + p[2]) / 2, atol=1e-14)
    np.testing.assert_array_equal(r.axis, [0, 0, -1])  # normalised
    pts2, _ = r.resample_path(0, 2)
    np.testing.assert_array_equal(pts2, p[[0, -1]])
    for bad in (1, 0, 2.5, "3"):
        with pytest.raises(ParameterError, match="n ="):
            r.resample_path(0, bad)
    with pytest.raises(ParameterError, match="leaflet index"):
        r.resample_path(3, 10)


def test_annulus_level_uses_mean_of_uneven_lowest_points():
    r = v_root()
    paths = [p.copy() for p in r.paths]
    paths[1][1, 2] = -3.0  # deeper nadir (axis is -z: axial coordinate +3)
    r2 = AorticRoot(axis=r.axis, origin=r.origin, commissures=r.commissures, paths=paths)
    assert r2.annulus_level == pytest.approx(1.0)
    assert r2.annulus_spread == pytest.approx(3.0)


# ----------------------------------------------------------------------- rigid motions
def test_rigid_motion_invariance(root60):
    rng = np.random.default_rng(1)
    R = random_rotation(rng)
    t = rng.normal(size=3) * 20
    m = root60.transformed(R, t)
    np.testing.assert_allclose(m.path_lengths, root60.path_lengths, rtol=1e-12)
    assert m.annulus_level == pytest.approx(root60.annulus_level, abs=1e-11)
    np.testing.assert_allclose(m.commissure_heights, root60.commissure_heights, rtol=1e-12)
    for i in range(3):
        assert m.commissure_distance(i) == pytest.approx(root60.commissure_distance(i),
                                                         rel=1e-12)
    np.testing.assert_allclose(m.radial(m.commissures), root60.radial(root60.commissures),
                               rtol=1e-12)
    np.testing.assert_allclose(m.axis, R @ root60.axis, atol=1e-15)
    pts, s = m.resample_path(1, 33)
    pts0, s0 = root60.resample_path(1, 33)
    np.testing.assert_allclose(pts, pts0 @ R.T + t, atol=1e-11)
    np.testing.assert_allclose(s, s0, rtol=1e-12)
    assert m.wall_distance().max() == pytest.approx(root60.wall_distance().max(), abs=1e-9)
    # a moved annulus: origin off the annulus plane shifts the level by the axial offset
    shifted = AorticRoot(axis=root60.axis, origin=[0, 0, 5.0], commissures=root60.commissures,
                         paths=root60.paths)
    assert shifted.annulus_level == pytest.approx(5.0)
    refl = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ParameterError, match="proper rotation"):
        root60.transformed(refl)


# ----------------------------------------------------------------------- validation
def _fields():
    r = v_root()
    return dict(axis=r.axis, origin=r.origin, commissures=r.commissures,
                paths=[p.copy() for p in r.paths])


def _bad(**change):
    f = _fields()
    f.update(change)
    return f


def test_arrays_are_read_only():
    r = v_root()
    with pytest.raises(ValueError):
        r.paths[0][1, 0] = 3.0
    with pytest.raises(Exception):
        r.name = "x"


@pytest.mark.parametrize("make, err, words", [
    (lambda: _bad(axis=[0, 0, 0]), ParameterError, ["axis", "zero length"]),
    (lambda: _bad(axis=[0, 0]), ParameterError, ["axis", "(3,)"]),
    (lambda: _bad(axis=[0, 0, 1.0]), ParameterError, ["paths[0]", "axis"]),
    (lambda: _bad(origin=[0, np.nan, 0]), ParameterError, ["origin", "non-finite"]),
    (lambda: _bad(commissures=np.zeros((2, 3))), ParameterError, ["commissures", "(3, 3)"]),
    (lambda: _bad(commissures=np.full((3, 3), np.nan)), ParameterError, ["commissures", "NaN"]),
    (lambda: _bad(paths=_fields()["paths"][:2]), ParameterError, ["paths", "3 polylines"]),
    (lambda: _bad(paths=[p[[0, 2]] for p in _fields()["paths"]]), ParameterError,
     ["paths[0]", "at least 3"]),
    (lambda: _bad(paths=[np.vstack([p[:2], p[1:]]) for p in _fields()["paths"]]), MeshError,
     ["paths[0]", "repeats a point"]),
    (lambda: _bad(paths=[p + [0.01, 0, 0] for p in _fields()["paths"]]), ParameterError,
     ["paths[0]", "commissures[0]"]),
    (lambda: _bad(paths=_fields()["paths"][::-1]), ParameterError, ["paths[0]", "commissures"]),
    (lambda: _bad(commissures=_fields()["commissures"][::-1],
                  paths=[_fields()["paths"][k][::-1] for k in (1, 0, 2)]), ParameterError,
     ["counter-clockwise"]),
    (lambda: _bad(wall=(np.zeros((3, 3)), [[0, 1, 5]])), MeshError, ["wall", "indices"]),
    (lambda: _bad(wall=(np.zeros((3, 3)),)), MeshError, ["wall"]),
    (lambda: _bad(name=3), ParameterError, ["name"]),
])
def test_validation_errors(make, err, words):
    with pytest.raises(err) as e:
        AorticRoot(**make())
    assert isinstance(e.value, JaxvalveError)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_endpoints_within_tolerance_are_snapped():
    f = _fields()
    f["paths"][0][0] += 1e-9
    r = AorticRoot(**f)
    np.testing.assert_array_equal(r.paths[0][0], r.commissures[0])


def test_first_commissure_angle_rotates_the_root(root60):
    r = benchmark_root(60.0, first_commissure_angle=30.0, wall=False)
    assert r.wall is None
    for p, q in zip(r.paths, root60.paths):
        np.testing.assert_allclose(p, q @ rot_z(30.0).T, atol=1e-12)
    with pytest.raises(ParameterError, match="wall"):
        r.wall_distance()
