"""Valve landmarks: 3D Slicer markups files (round trips, RAS/LPS, errors), projection
onto the wall, and suture paths fitted to the template's sutured edge
(`jaxvalve.io.markups`, `jaxvalve.geometry.landmarks`)."""
import json

import numpy as np
import pytest

from jaxvalve.errors import LandmarksFileError, ParameterError
from jaxvalve.geometry.landmarks import (ValveLandmarks, landmarks_from_markups,
                                         landmarks_to_markups, root_from_landmarks)
from jaxvalve.geometry.root import benchmark_root
from jaxvalve.geometry.surface_query import distance_to_surface
from jaxvalve.io.files import read_root, write_surface
from jaxvalve.io.markups import Markup, MarkupsFileError, read_markups, write_markups

L = 47.71032163829112           # the benchmark template's sutured edge, mm


@pytest.fixture(scope="module")
def bench():
    return benchmark_root(L, wall_theta_cells=180, wall_dz=0.5)


def _nadirs(root):
    return np.array([p[int(np.argmax(root.axial(p)))] for p in root.paths])


def _polyline_distance(points, line):
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.einsum("pnd,nd->pn", points[:, None] - a[None], ab)
                / np.einsum("nd,nd->n", ab, ab), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - q, axis=-1).min(axis=1)


# ------------------------------------------------------------------------ markups files
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_markups_round_trip_in_either_frame(tmp_path, system):
    rng = np.random.default_rng(0)
    ms = [Markup("Fiducial", ["C1", "C2", "N1"], rng.normal(size=(3, 3)) * 20, "points"),
          Markup("Curve", ["P-1", "P-2", "P-3", "P-4"], rng.normal(size=(4, 3)), "path",
                 "a curve")]
    f = write_markups(tmp_path / "x.mrk.json", ms, system)
    raw = json.loads(f.read_text())
    assert raw["markups"][0]["coordinateSystem"] == system
    stored = np.array(raw["markups"][0]["controlPoints"][0]["position"])
    flip = np.array([-1, -1, 1]) if system == "RAS" else np.ones(3)
    np.testing.assert_array_equal(stored, ms[0].points[0] * flip)
    back = read_markups(f)
    assert [(m.kind, m.labels, m.name) for m in back] == [(m.kind, m.labels, m.name) for m in ms]
    for m, n in zip(ms, back):
        np.testing.assert_array_equal(n.points, m.points)      # exact: JSON keeps float64


def test_markups_reader_takes_slicers_forms_and_names_the_file_on_errors(tmp_path):
    f = tmp_path / "s.mrk.json"
    f.write_text(json.dumps({"@schema": "x", "markups": [{
        "type": "Fiducial", "coordinateSystem": "RAS",
        "coordinateUnits": ["um", "UCUM", "micrometer"],
        "controlPoints": [{"label": "C1", "position": [1000.0, 2000.0, 3000.0]},
                          {"label": "C2", "position": [0, 0, 0], "positionStatus": "undefined"}
                          ]}]}))
    (m,) = read_markups(f)
    assert m.labels == ("C1",)                       # the unplaced placeholder is left out
    np.testing.assert_allclose(m.points, [[-1.0, -2.0, 3.0]])
    bad = {"not json": "{", "no markups": json.dumps({"a": 1}),
           "frame": json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "XYZ"}]}),
           "position": json.dumps({"markups": [{"type": "Fiducial", "controlPoints": [
               {"label": "C1", "position": [1, "a", 3]}]}]}),
           "nan": '{"markups": [{"type": "Fiducial", "controlPoints": [{"position": [1, NaN, 3]}]}]}'}
    for what, text in bad.items():
        g = tmp_path / f"{what.replace(' ', '_')}.mrk.json"
        g.write_text(text)
        with pytest.raises(MarkupsFileError, match=g.name):
            read_markups(g)
    with pytest.raises(MarkupsFileError, match="does not exist"):
        read_markups(tmp_path / "missing.mrk.json")
    with pytest.raises(MarkupsFileError, match="mrk.json"):
        write_markups(tmp_path / "x.json", [])


def test_landmarks_are_found_by_label_and_missing_ones_named():
    c, n = np.eye(3), 2 * np.eye(3)
    ms = [Markup("Fiducial", ["Commissure 2", "c1", "C-3", "nadir 1", "N2", "N_3", "F-7"],
                 np.concatenate([c[[1, 0, 2]], n, [[9, 9, 9]]]))]
    lm = landmarks_from_markups(ms)
    np.testing.assert_array_equal(lm.commissures, c)
    np.testing.assert_array_equal(lm.nadirs, n)
    assert lm.curves is None
    with pytest.raises(ParameterError, match=r"three commissures.*found 2"):
        landmarks_from_markups([Markup("Fiducial", ["C1", "C2", "N1"], np.eye(3))])
    with pytest.raises(ParameterError, match="all three nadirs"):
        landmarks_from_markups([Markup("Fiducial", ["C1", "C2", "C3", "N1"], np.ones((4, 3)))])
    with pytest.raises(ParameterError, match="nadirs .* or the three suture path curves"):
        landmarks_from_markups([Markup("Fiducial", ["C1", "C2", "C3"], np.eye(3))])
    with pytest.raises(ParameterError, match="given twice"):
        landmarks_from_markups([Markup("Fiducial", ["C1", "C1"], np.eye(3)[:2])])


# ------------------------------------------------------------------------ suture paths
def test_paths_fitted_from_nadirs_recover_the_benchmark_paths(bench):
    # the benchmark's paths are the family of the fit (power law p = 4 in depth, linear in
    # angle), on its own wall: the fit must find p = 4, the sutured length and the paths
    root, rep = root_from_landmarks(bench.wall, ValveLandmarks(bench.commissures,
                                                               _nadirs(bench)),
                                    sutured_length=L)
    np.testing.assert_allclose(rep["path_shape_exponent"], 4.0, atol=0.02)
    np.testing.assert_allclose(rep["path_length_mm"], L, rtol=1e-3)
    np.testing.assert_allclose(root.axis, bench.axis, atol=1e-12)
    np.testing.assert_allclose(root.commissures, bench.commissures, atol=1e-9)
    for mine, theirs in zip(root.paths, bench.paths):
        assert _polyline_distance(mine, theirs).max() < 0.02
        assert distance_to_surface(mine, *bench.wall).max() < 1e-9


def test_landmarks_off_the_wall_are_projected_and_order_does_not_matter(bench):
    rng = np.random.default_rng(1)
    c = bench.commissures + rng.normal(scale=0.5, size=(3, 3))
    n = _nadirs(bench) + rng.normal(scale=0.5, size=(3, 3))
    a, rep = root_from_landmarks(bench.wall, ValveLandmarks(c, n), sutured_length=L)
    b, _ = root_from_landmarks(bench.wall, ValveLandmarks(c[[2, 1, 0]], n[[1, 2, 0]]),
                               sutured_length=L)
    assert max(rep["commissure_wall_distance_mm"]) > 0.1       # they were off the wall
    assert distance_to_surface(a.commissures, *bench.wall).max() < 1e-9
    # reordered input: the same valve, counter-clockwise from the aorta
    k = int(np.argmin(np.linalg.norm(b.commissures - a.commissures[0], axis=1)))
    np.testing.assert_allclose(np.roll(b.commissures, -k, axis=0), a.commissures, atol=1e-12)
    for i in range(3):
        np.testing.assert_allclose(b.paths[(i + k) % 3], a.paths[i], atol=1e-9)


def test_unfittable_templates_and_far_landmarks_are_refused(bench):
    lm = ValveLandmarks(bench.commissures, _nadirs(bench))
    with pytest.raises(ParameterError, match=r"sutured edge \(30.00 mm\) does not fit leaflet "
                                             r"1: .* \d+\.\d\d to \d+\.\d\d mm long"):
        root_from_landmarks(bench.wall, lm, sutured_length=30.0)
    with pytest.raises(ParameterError, match="sutured_length"):
        root_from_landmarks(bench.wall, lm)
    far = ValveLandmarks(bench.commissures * np.array([-1, -1, 1]) + [0, 0, 40], lm.nadirs)
    with pytest.raises(ParameterError, match=r"commissure \d lies .*\(LPS or RAS\)"):
        root_from_landmarks(bench.wall, far, sutured_length=L)
    twice = ValveLandmarks(bench.commissures, lm.nadirs[[0, 0, 1]])
    with pytest.raises(ParameterError, match="exactly one nadir"):
        root_from_landmarks(bench.wall, twice, sutured_length=L)


def test_a_root_written_as_markups_reads_back_through_read_root(tmp_path, bench):
    root, _ = root_from_landmarks(bench.wall, ValveLandmarks(bench.commissures,
                                                             _nadirs(bench)), sutured_length=L)
    write_surface(tmp_path / "wall.stl", *bench.wall)
    write_markups(tmp_path / "lm.mrk.json", landmarks_to_markups(root), "RAS")
    back = read_root(tmp_path / "wall.stl", tmp_path / "lm.mrk.json")   # curves: no L needed
    np.testing.assert_allclose(back.commissures, root.commissures, atol=1e-5)  # STL: float32
    for p, q in zip(back.paths, root.paths):
        # the curve's own points are kept (on the wall already: moved by the STL's
        # float32 rounding only); the points added between them are projected onto the
        # wall, off the chord by its sag
        assert _polyline_distance(q, p).max() < 1e-5
        assert _polyline_distance(p, q).max() < 0.05
    # points only: the paths are fitted to the given sutured length
    write_markups(tmp_path / "pts.mrk.json", landmarks_to_markups(root)[:1])
    fitted = read_root(tmp_path / "wall.stl", tmp_path / "pts.mrk.json", sutured_length=L)
    np.testing.assert_allclose(fitted.path_lengths, L, rtol=1e-3)
    with pytest.raises(LandmarksFileError, match="pts.mrk.json.*sutured_length"):
        read_root(tmp_path / "wall.stl", tmp_path / "pts.mrk.json")
