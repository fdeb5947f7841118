"""Scenes: defaults are the benchmark, TOML round trip, clear errors."""
import numpy as np
import pytest

from jaxvalve.mechanics import materials as m
from jaxvalve.errors import ParameterError
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.scene import BENCHMARK_H, BENCHMARK_TEMPLATE, Scene


def test_benchmark_template_fits_the_anatomical_root():
    """The benchmark template's sutured edge gives the 16.8 mm valve height (Labrosse) and
    its mesh has about the paper's 1313 triangles a leaflet."""
    root = Scene().load_root()
    np.testing.assert_allclose(root.dimensions["commissure_height"], 16.8, atol=0.05)
    np.testing.assert_allclose(root.path_lengths, BENCHMARK_TEMPLATE.sutured_length, rtol=1e-9)
    n = len(mesh_leaflet(BENCHMARK_TEMPLATE, BENCHMARK_H).triangles)
    assert abs(n - 1313) < 40
    assert BENCHMARK_TEMPLATE.free_length > root.commissure_distance(0)


@pytest.mark.parametrize("model,cls", [("stvk", m.StVenantKirchhoff), ("neo-hookean", m.NeoHookean),
                                       ("gent", m.Gent), ("mass-spring", m.MassSpring)])
def test_materials_follow_the_paper_conventions(model, cls):
    mat = Scene(model=model, E=1.5).material()
    assert isinstance(mat, cls)
    if model in ("neo-hookean", "gent"):
        np.testing.assert_allclose(float(mat.mu), 0.5)  # mu = E / 3


def test_toml_scene_with_overrides(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('model = "gent"\nE = 2.0\nJm = 3.0\nh = 2.5\n')
    s = Scene.from_toml(p, E=4.0)
    assert (s.model, s.E, s.Jm, s.h) == ("gent", 4.0, 3.0, 2.5)
    p.write_text('modle = "gent"\n')
    with pytest.raises(ParameterError, match="unknown keys"):
        Scene.from_toml(p)
    p.write_text('model = \n')
    with pytest.raises(ParameterError, match="not valid TOML"):
        Scene.from_toml(p)
    with pytest.raises(ParameterError, match="does not exist"):
        Scene.from_toml(tmp_path / "missing.toml")


@pytest.mark.parametrize("kw,match", [
    (dict(model="linear"), "model must be one of"),
    (dict(solver="cg"), "solver must be one of"),
    (dict(h=0.0), "h must be"),
    (dict(pressure=float("nan")), "pressure must be"),
    (dict(b=10.0), "b must exceed"),
    (dict(model="mass-spring", E1=0.1), "give all of E1, E2, E3"),
    (dict(precision="float16"), r"precision must be one of \('float64', 'float32'\)"),
    (dict(alpha=200.0), r"alpha must lie in \(0, 180\] degrees"),
    (dict(pressure=2.0), "he_pressure must be at most pressure = 2 mmHg"),
])
def test_bad_scenes_are_rejected(kw, match):
    with pytest.raises(ParameterError, match=match):
        Scene(**kw).material()
