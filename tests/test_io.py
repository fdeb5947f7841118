"""I/O: surfaces with data, root round trips (JSON/TOML, .vtu/.stl), and bad input files."""
import json

import numpy as np
import pytest

from jaxvalve.errors import JaxvalveError, MeshError, ParameterError
from jaxvalve.io import (LandmarksFileError, SurfaceFileError, read_landmarks, read_root,
                         read_surface, write_landmarks, write_root, write_surface)
from jaxvalve.geometry.root import benchmark_root


@pytest.fixture(scope="module")
def root():
    return benchmark_root(60.0, wall_theta_cells=120, wall_dz=0.5)


@pytest.fixture()
def files(tmp_path, root):
    """A valid benchmark root written as .vtu + .json; returns (surface, landmarks dict)."""
    surf = tmp_path / "wall.vtu"
    write_surface(surf, *root.wall)
    lm = json.loads(json.dumps({"name": "patient", "units": "mm", "axis": root.axis.tolist(),
                                "origin": root.origin.tolist(),
                                "commissures": root.commissures.tolist(),
                                "paths": [p.tolist() for p in root.paths]}))
    return surf, lm


def dump(tmp_path, data, name="lm.json"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


def same_root(a, b, exact=True):
    check = np.testing.assert_array_equal if exact else (
        lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12))
    check(a.axis, b.axis)
    check(a.origin, b.origin)
    check(a.commissures, b.commissures)
    for p, q in zip(a.paths, b.paths):
        check(p, q)


# ----------------------------------------------------------------------- round trips
@pytest.mark.parametrize("surface, landmarks", [("wall.vtu", "lm.json"), ("wall.stl", "lm.toml"),
                                                ("wall.vtu", "lm.toml"), ("wall.stl", "lm.json")])
def test_root_round_trip(tmp_path, root, surface, landmarks):
    write_root(root, tmp_path / surface, tmp_path / landmarks)
    back = read_root(tmp_path / surface, tmp_path / landmarks, wall_tolerance=0.05)
    same_root(back, root)
    assert back.name == root.name
    assert back.dimensions == root.dimensions
    assert back.annulus_level == root.annulus_level
    np.testing.assert_array_equal(back.path_lengths, root.path_lengths)
    if surface.endswith(".vtu"):
        np.testing.assert_array_equal(back.wall[0], root.wall[0])
        np.testing.assert_array_equal(back.wall[1], root.wall[1])
    else:  # STL: float32 points, vertices merged in its own order
        assert len(back.wall[1]) == len(root.wall[1])
        np.testing.assert_allclose(back.wall_distance(), root.wall_distance(), atol=1e-5)


def test_surface_round_trip_with_point_and_cell_data(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(30, 3))
    tri = np.array([[i, i + 1, i + 2] for i in range(28)])
    pdata = {"displacement": rng.normal(size=(30, 3)), "gap": rng.uniform(size=30),
             "zone": rng.uniform(size=30) > 0.5, "stretches": rng.uniform(1, 2, size=(30, 2)),
             "leaflet": np.arange(30) % 3}
    cdata = {"area": rng.uniform(size=28), "strain": rng.normal(size=(28, 3))}
    path = write_surface(tmp_path / "leaf.vtu", pts, tri, point_data=pdata, cell_data=cdata)
    p, t, pd, cd = read_surface(path, return_cell_data=True)
    np.testing.assert_array_equal(p, pts)
    np.testing.assert_array_equal(t, tri)
    assert t.dtype == np.int32 and p.dtype == np.float64
    assert set(pd) == set(pdata)
    for k, v in pdata.items():
        np.testing.assert_array_equal(pd[k], v.astype(np.uint8) if v.dtype == bool else v)
        assert pd[k].shape == v.shape
    for k, v in cdata.items():
        np.testing.assert_array_equal(cd[k], v)
    p3, t3, pd3 = read_surface(path)
    assert set(pd3) == set(pdata)


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".obj", ".vtk", ".off"])
def test_surface_formats(tmp_path, suffix):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]])
    tri = np.array([[0, 1, 2], [1, 3, 2]])
    p, t, _ = read_surface(write_surface(tmp_path / f"s{suffix}", pts, tri))
    np.testing.assert_allclose(p[t], pts[tri], atol=1e-6)


def test_quads_are_split(tmp_path):
    f = tmp_path / "quad.obj"
    f.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nf 1 2 3 4\nf 2 5 3\n")
    p, t, _ = read_surface(f)
    assert len(p) == 5 and len(t) == 3
    assert sorted(map(sorted, t.tolist())) == [[0, 1, 2], [0, 2, 3], [1, 2, 4]]


def test_units_are_converted_to_mm(tmp_path, root, files):
    surf, lm = files
    m = tmp_path / "wall_m.vtu"
    write_surface(m, root.wall[0] / 1000, root.wall[1])
    lm_m = dict(lm, units="m", origin=(root.origin / 1000).tolist(),
                commissures=(root.commissures / 1000).tolist(),
                paths=[(p / 1000).tolist() for p in root.paths])
    back = read_root(m, dump(tmp_path, lm_m), wall_tolerance=0.05)
    same_root(back, root, exact=False)
    np.testing.assert_allclose(back.wall[0], root.wall[0], rtol=1e-14)
    cm = dict(lm, units="cm", commissures=(root.commissures / 10).tolist(),
              paths=[(p / 10).tolist() for p in root.paths])
    write_surface(m, root.wall[0] / 10, root.wall[1])
    same_root(read_root(m, dump(tmp_path, cm)), root, exact=False)


def test_default_axis_and_origin(tmp_path, root, files):
    surf, lm = files
    del lm["axis"], lm["origin"]
    back = read_root(surf, dump(tmp_path, lm))
    np.testing.assert_allclose(back.axis, [0, 0, -1], atol=1e-15)
    np.testing.assert_allclose(back.origin, [0, 0, 0], atol=1e-12)
    assert back.annulus_level == pytest.approx(0.0, abs=1e-12)
    assert back.name == "patient"
    del lm["name"]
    assert read_root(surf, dump(tmp_path, lm, "case7.json")).name == "case7"


def test_landmarks_toml_hand_written(tmp_path, root, files):
    surf, _ = files
    rows = lambda a: "[" + ", ".join("[" + ", ".join(repr(float(x)) for x in r) + "]"  # noqa
                                      for r in a) + "]"
    text = ('name = "toml case"\nunits = "mm"\naxis = [0, 0, -1]\n'
            f"commissures = {rows(root.commissures)}\n"
            f"paths = [{', '.join(rows(p) for p in root.paths)}]\n"
            '[meta]\nsurgeon = "x"\n')
    back = read_root(surf, dump(tmp_path, text, "lm.toml"))
    same_root(back, root, exact=False)
    assert back.name == "toml case"


# ----------------------------------------------------------------------- bad input
def expect(err, *words):
    class Ctx:
        def __enter__(self):
            self.cm = pytest.raises(err)
            self.info = self.cm.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.cm.__exit__(*exc)
            msg = str(self.info.value)
            assert isinstance(self.info.value, JaxvalveError)
            for w in words:
                assert w in msg, (w, msg)
            return out
    return Ctx()


def test_missing_files(tmp_path, files):
    surf, lm = files
    lmp = dump(tmp_path, lm)
    with expect(SurfaceFileError, "nope.vtu", "does not exist"):
        read_root(tmp_path / "nope.vtu", lmp)
    with expect(LandmarksFileError, "nope.json", "does not exist"):
        read_root(surf, tmp_path / "nope.json")
    with expect(SurfaceFileError, "does not exist"):
        read_surface(tmp_path / "nope.stl")
    with expect(SurfaceFileError, "not a regular file"):
        read_surface(tmp_path)


@pytest.mark.parametrize("name, content", [("bad.stl", "this is not a mesh"),
                                           ("bad.vtu", "<VTKFile> garbage"),
                                           ("bad.txt", "1 2 3"),
                                           ("bad", "")])
def test_unreadable_surface(tmp_path, files, name, content):
    _, lm = files
    f = tmp_path / name
    f.write_text(content)
    with expect(SurfaceFileError, name, "cannot be read"):
        read_root(f, dump(tmp_path, lm))


def test_surface_without_triangles_or_with_nan(tmp_path, files):
    _, lm = files
    f = tmp_path / "lines.obj"
    f.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n")
    with expect(SurfaceFileError, "lines.obj", "no triangles"):
        read_root(f, dump(tmp_path, lm))
    g = tmp_path / "nan.obj"
    g.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with expect(SurfaceFileError, "nan.obj", "non-finite"):
        read_surface(g)


def _mutations(lm):
    p = lm["paths"]
    c = lm["commissures"]
    return {
        "missing commissures": ({k: v for k, v in lm.items() if k != "commissures"},
                                ["commissures", "missing"]),
        "missing paths": ({k: v for k, v in lm.items() if k != "paths"}, ["paths", "missing"]),
        "missing units": ({k: v for k, v in lm.items() if k != "units"}, ["units", "missing"]),
        "two commissures": (dict(lm, commissures=c[:2]), ["commissures", "(3, 3)"]),
        "2d commissures": (dict(lm, commissures=[r[:2] for r in c]), ["commissures", "(3, 3)"]),
        "two paths": (dict(lm, paths=p[:2]), ["paths", "3 polylines"]),
        "ragged path": (dict(lm, paths=[p[0][:3] + [[1.0, 2.0]] + p[0][3:], p[1], p[2]]),
                        ["paths[0]"]),
        "short path": (dict(lm, paths=[[p[0][0], p[0][-1]], p[1], p[2]]),
                       ["paths[0]", "K >= 3"]),
        "string coords": (dict(lm, axis=["0", "0", "-1"]), ["axis", "numbers"]),
        "bool coords": (dict(lm, origin=[True, 0, 0]), ["origin", "numbers"]),
        "nan": (dict(lm, commissures=[[float("nan"), 0, 0]] + c[1:]), ["commissures", "NaN"]),
        "bad units": (dict(lm, units="inch"), ["units", "inch"]),
        "unknown key": (dict(lm, comissures=c), ["comissures", "unknown"]),
        "axis shape": (dict(lm, axis=[0, -1]), ["axis", "(3,)"]),
        "zero axis": (dict(lm, axis=[0, 0, 0]), ["axis", "zero length"]),
        "flipped axis": (dict(lm, axis=[0, 0, 1]), ["paths[0]", "axis"]),
        "path off commissure": (dict(lm, paths=[[[x + 0.5, y, z] for x, y, z in p[0]], p[1],
                                                p[2]]), ["paths[0]", "commissures[0]"]),
        "paths swapped": (dict(lm, paths=[p[1], p[0], p[2]]), ["paths[0]", "commissures"]),
        "name not str": (dict(lm, name=7), ["name"]),
        "dimensions not table": (dict(lm, dimensions=[1, 2]), ["dimensions"]),
        "not an object": ([1, 2, 3], ["top level"]),
    }


CASES = ["missing commissures", "missing paths", "missing units", "two commissures",
         "2d commissures", "two paths", "ragged path", "short path", "string coords",
         "bool coords", "nan", "bad units", "unknown key", "axis shape", "zero axis",
         "flipped axis", "path off commissure", "paths swapped", "name not str",
         "dimensions not table", "not an object"]


@pytest.mark.parametrize("case", CASES)
def test_bad_landmarks(tmp_path, files, case):
    surf, lm = files
    cases = _mutations(lm)
    assert sorted(cases) == sorted(CASES)
    data, words = cases[case]
    f = tmp_path / "lm.json"
    f.write_text(json.dumps(data))  # json writes NaN as a bare NaN literal, which it reads
    with expect(LandmarksFileError, "lm.json", *words):
        read_root(surf, f)


def test_bad_landmarks_syntax_and_suffix(tmp_path, files):
    surf, lm = files
    with expect(LandmarksFileError, "lm.json", "not valid JSON"):
        read_root(surf, dump(tmp_path, "{'units': mm", "lm.json"))
    with expect(LandmarksFileError, "lm.toml", "not valid TOML"):
        read_root(surf, dump(tmp_path, "units = mm\n", "lm.toml"))
    with expect(LandmarksFileError, "lm.toml", "NaN"):
        read_root(surf, dump(tmp_path, 'units = "mm"\ncommissures = [[nan, 0, 0], [1, 0, 0], '
                                       '[0, 1, 0]]\npaths = []\n', "lm.toml"))
    with expect(LandmarksFileError, "lm.yaml", ".json or .toml"):
        read_root(surf, dump(tmp_path, "units: mm", "lm.yaml"))
    with expect(LandmarksFileError, ".json or .toml"):
        read_landmarks(dump(tmp_path, "", "lm.txt"))


def test_wall_tolerance(tmp_path, root, files):
    surf, lm = files
    shifted = dict(lm, origin=None)
    del shifted["origin"]
    shifted["commissures"] = (np.array(lm["commissures"]) * 1.2).tolist()
    shifted["paths"] = [(np.array(p) * 1.2).tolist() for p in lm["paths"]]
    f = dump(tmp_path, shifted)
    read_root(surf, f)  # no check by default
    with expect(SurfaceFileError, "wall.vtu", "wall_tolerance"):
        read_root(surf, f, wall_tolerance=0.1)
    with pytest.raises(ParameterError, match="wall_tolerance"):
        read_root(surf, dump(tmp_path, lm), wall_tolerance=-1.0)


def test_error_classes_are_jaxvalve_errors():
    assert issubclass(SurfaceFileError, MeshError)
    assert issubclass(LandmarksFileError, ParameterError)


def test_bad_writes(tmp_path, root):
    pts, tri = root.wall
    with pytest.raises(ParameterError, match=r"\.vtu"):
        write_surface(tmp_path / "a.stl", pts, tri, point_data={"gap": np.zeros(len(pts))})
    with pytest.raises(ParameterError, match="point_data\\['gap'\\]"):
        write_surface(tmp_path / "a.vtu", pts, tri, point_data={"gap": np.zeros(3)})
    with pytest.raises(ParameterError, match="cell_data\\['c'\\]"):
        write_surface(tmp_path / "a.vtu", pts, tri, cell_data={"c": np.zeros(len(pts))})
    with pytest.raises(MeshError, match="indices"):
        write_surface(tmp_path / "a.vtu", pts, tri + len(pts))
    with pytest.raises(MeshError, match="non-finite"):
        write_surface(tmp_path / "a.vtu", np.full_like(pts, np.nan), tri)
    with pytest.raises(SurfaceFileError, match="a.foo"):
        write_surface(tmp_path / "a.foo", pts, tri)
    bare = benchmark_root(60.0, wall=False)
    with pytest.raises(ParameterError, match="wall"):
        write_root(bare, tmp_path / "a.vtu", tmp_path / "a.json")
    with pytest.raises(LandmarksFileError, match=".json or .toml"):
        write_root(root, tmp_path / "a.vtu", tmp_path / "a.yaml")
    with pytest.raises(LandmarksFileError, match=".json or .toml"):
        write_landmarks(root, tmp_path / "a.yml")


def test_packages_named_after_a_module_offer_its_api():
    """`jaxvalve.io` offers `io.files`' API and `jaxvalve.valve` `valve.model`'s, read on
    first use (`jaxvalve.lazy_exports`): the same objects, listed by dir(), and an unknown
    name is an AttributeError."""
    from jaxvalve import io, valve
    from jaxvalve.io import files
    from jaxvalve.valve import model
    for pkg, mod in ((io, files), (valve, model)):
        assert set(mod.__all__) <= set(pkg._API) <= set(dir(pkg))
        for name in pkg._API:
            assert getattr(pkg, name) is getattr(mod, name)
        with pytest.raises(AttributeError, match="has no attribute 'nope'"):
            pkg.nope
