"""`jaxvalve simulate` and its outputs (metrics.json, leaflet .vtu files, PNG figures).

One coarse, deliberately unconverged simulation (h = 3 mm, a few FIRE steps) runs once
for the module, through the CLI with a TOML scene and a flag override; the in-memory
result is captured so that the files can be checked against it.
"""
import contextlib
import io
import json
import math

import meshio
import numpy as np
import pytest

import jaxvalve
from jaxvalve.cli import main
from jaxvalve.io.report import metrics_json, nodal_average, principal_stretches
from jaxvalve.scene import Scene
import jaxvalve.simulation as sim_mod
from jaxvalve import progress

real = sim_mod.simulate

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(exit code, result, out dir, stdout, stderr) of one CLI run."""
    d = tmp_path_factory.mktemp("simulate")
    toml = d / "scene.toml"
    toml.write_text("h = 3.0\nmax_steps = 300\ng_c = 0.6\nmodel = 'stvk'\n")
    captured = []

    def spy(scene, **kw):
        captured.append(real(scene, **kw))
        return captured[-1]

    out, so, se = d / "out", io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sim_mod, "simulate", spy)
        # the heartbeat after 0.05 s of silence (the CLI's 2 s would make the lines depend
        # on how long this worker takes to compile: its programs may be cached already)
        mp.setattr(progress, "EVERY_S", 0.05)
        with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
            # a closure stopped at its step cap (continuation cuts the load step until
            # its budget of 10 such solves is spent)
            code = main(["simulate", str(toml), "--max-steps", "40",
                         "--out", str(out)])
    assert len(captured) == 1
    return code, captured[0], out, so.getvalue(), se.getvalue()


def test_unconverged_run_exits_3_with_a_warning_and_still_writes(run):
    code, result, out, stdout, stderr = run
    assert not result.converged
    assert code == 3
    assert "did NOT converge" in stderr and "residual" in stderr
    assert "[jaxvalve] closing at 80 mmHg" in stdout
    # the heartbeat spoke while the run was silent
    beats = [ln for ln in stdout.splitlines() if ln.startswith("[jaxvalve] ... ")]
    assert beats and all(" s in: " in ln for ln in beats)
    for key in ("h_E", "h_C-C", "h_avr", "NCCA", "compile time", "residual"):
        assert key in stdout
    names = {p.name for p in out.iterdir()}
    assert names == {"metrics.json", "leaflet_0.vtu", "leaflet_1.vtu", "leaflet_2.vtu",
                     "valve.png", "valve_aortic_view.png", "profiles.png",
                     "pair_heights.png", "report.html"}


def test_toml_scene_and_flag_override_are_honoured(run):
    _, result, out, _, _ = run
    data = json.loads((out / "metrics.json").read_text())
    assert data["scene"]["h"] == 3.0 and data["scene"]["g_c"] == 0.6   # from the TOML
    assert data["scene"]["max_steps"] == 40                             # flag wins
    assert result.scene == Scene(h=3.0, g_c=0.6, max_steps=40)
    assert [s["steps"] for s in data["solves"]] == [400, 0]   # 80 mmHg: not solved
    assert data["metrics"]["g_c"] == 0.6


def _finite_tree(v, path="$"):
    if isinstance(v, dict):
        for k, a in v.items():
            _finite_tree(a, f"{path}.{k}")
    elif isinstance(v, list):
        for i, a in enumerate(v):
            _finite_tree(a, f"{path}[{i}]")
    elif isinstance(v, float):
        assert math.isfinite(v), path


def test_metrics_json_round_trips_and_matches_the_result(run):
    _, result, out, _, _ = run
    text = (out / "metrics.json").read_text()
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in metrics.json"))
    _finite_tree(data)
    assert data == json.loads(json.dumps(metrics_json(result)))
    assert data["jaxvalve_version"] == jaxvalve.__version__
    assert data["converged"] is False is result.converged
    assert data["residual"] == pytest.approx(max(s.residual for s in result.solves))
    assert data["model"] == "stvk"
    assert data["scene"] == json.loads(json.dumps(result.scene.as_dict()))
    s = data["summary"]
    assert s["h_E"] == pytest.approx(result.metrics_he.h_e)
    assert s["h_CC"] == pytest.approx(result.metrics.h_cc)
    assert s["h_avr"] == pytest.approx(result.metrics.h_avr_valve)
    assert s["NCCA_pct"] == pytest.approx(100 * result.metrics.ncca_valve)
    assert s["h"] == pytest.approx(result.metrics.h)
    assert s["h_c"] == pytest.approx(result.metrics.h_c)
    for key in ("metrics", "metrics_he"):
        m = data[key]
        assert len(m["ncca"]) == len(m["h_avr"]) == len(m["area"]) == 3
        H = np.asarray(m["curves"]["H"], dtype=float)
        assert H.shape == (3, len(m["curves"]["w"]))
    np.testing.assert_allclose(data["metrics"]["curves"]["H"], result.metrics.curves.H)
    assert data["metrics_he"]["h_e"] == pytest.approx(result.h_E)
    assert len(data["solves"]) == 2
    for rep, d in zip(result.solves, data["solves"]):
        assert d["pressure"] == rep.pressure and d["converged"] == rep.converged
        assert d["result"] == rep.result == "max_steps_reached"
        assert d["residual"] == pytest.approx(rep.residual)
        # stopped at the step cap mid-swing, far from an equilibrium: the cause is in the
        # report, its JSON and status line
        assert d["cause"] == rep.cause and "no Newton finish" in rep.cause
        assert rep.cause in d["status"]
        for k in ("wall_s", "compile_s", "solve_s"):
            assert d[k] >= 0
    assert data["mesh"]["triangles_per_leaflet"] == len(result.valve.leaflet.triangles)
    assert set(data["timings"]) >= {"setup", "metrics", "total", "compile", "solve"}


def test_leaflet_vtu_files_hold_the_closed_state_and_its_fields(run):
    _, result, out, _, _ = run
    lm = result.valve.leaflet
    n, m = lm.n_nodes, len(lm.triangles)
    g_c = result.scene.g_c
    zones = 0
    for i in range(3):
        mesh = meshio.read(out / f"leaflet_{i}.vtu")
        sl = result.valve.leaflet_slice(i)
        assert mesh.points.shape == (n, 3)
        assert mesh.cells_dict["triangle"].shape == (m, 3)
        np.testing.assert_array_equal(mesh.cells_dict["triangle"], lm.triangles)
        np.testing.assert_allclose(mesh.points, result.x[sl])
        pd = mesh.point_data
        assert pd["displacement"].shape == (n, 3)
        np.testing.assert_allclose(pd["displacement"],
                                   result.x[sl] - np.asarray(result.valve.x_start)[sl])
        gap = pd["gap"]
        assert gap.shape == (n,) and np.all(np.isfinite(gap)) and np.all(gap >= 0)
        finite = np.isfinite(result.metrics.gap[sl].min(axis=1))
        np.testing.assert_allclose(gap[finite], result.metrics.gap[sl].min(axis=1)[finite])
        assert np.all(gap[~finite] > g_c)
        np.testing.assert_array_equal(pd["zone"], (gap < g_c).astype(np.uint8))
        zones += int(pd["zone"].sum())
        assert pd["principal_stretches"].shape == (n, 2)
        lam = pd["principal_stretches"]
        assert np.all(lam[:, 0] >= lam[:, 1] - 1e-12) and np.all(lam > 0)
        np.testing.assert_allclose(pd["template"][:, :2], lm.points)
        # the solve's status travels with the state (this run stopped at its step cap)
        assert pd["converged"].dtype == np.uint8
        np.testing.assert_array_equal(pd["converged"], np.zeros(n, np.uint8))
        np.testing.assert_array_equal(
            pd["residual"], np.full(n, json.loads((out / "metrics.json").read_text())["residual"]))
        assert pd["residual"][0] > result.scene.rtol
    assert zones > 0          # the coarse closure already touches


def test_principal_stretches_of_an_affine_map_and_the_template():
    rng = np.random.default_rng(0)
    ref = rng.uniform(-5, 5, (30, 2))
    from scipy.spatial import Delaunay
    tri = Delaunay(ref).simplices
    # an affine stretch diag(1.2, 0.9) rotated in the plane, then rotated in space
    th = 0.7
    R2 = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    F = R2 @ np.diag([1.2, 0.9]) @ R2.T
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    x = np.column_stack([ref @ F.T, np.zeros(len(ref))]) @ q.T + [1.0, 2.0, 3.0]
    lam = principal_stretches(x, tri, ref)
    np.testing.assert_allclose(lam, np.tile([1.2, 0.9], (len(tri), 1)), atol=1e-12)
    np.testing.assert_allclose(nodal_average(lam, tri, len(ref)),
                               np.tile([1.2, 0.9], (len(ref), 1)), atol=1e-12)
    flat = np.column_stack([ref, np.zeros(len(ref))])
    np.testing.assert_allclose(principal_stretches(flat, tri, ref), 1.0, atol=1e-12)


def test_principal_stretches_are_one_in_the_template_state(run):
    _, result, _, _, _ = run
    p, tri = result.leaflet(0, "template")
    lam = principal_stretches(p, tri, result.valve.leaflet.points)
    np.testing.assert_allclose(lam, 1.0, atol=1e-12)


def test_png_figures_are_written(run):
    _, _, out, _, _ = run
    for name in ("valve", "valve_aortic_view", "profiles", "pair_heights"):
        data = (out / f"{name}.png").read_bytes()
        assert data[:8] == PNG and len(data) > 5000


def test_aortic_view_looks_down_the_axis_with_the_zone_coloured_by_gap(run):
    """The surgeon's view: the frame is orthonormal and perpendicular to the axis, the
    commissures (counter-clockwise seen from the aorta) turn counter-clockwise on the
    figure, every triangle is drawn once, nearer ones later, and exactly the zone's
    triangles take the gap colours."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    import dataclasses
    from types import SimpleNamespace

    from jaxvalve.io.plots import _zone_faces, aortic_frame
    _, result, _, _, _ = run
    # this short run is still open: give the nodes nearest the aorta a gap below g_c, so
    # that the figure has a zone to colour (the gap 0.1-0.4 mm, the others far apart)
    x = np.asarray(result.x)
    lift = -(x - np.asarray(result.valve.root.origin)) @ np.asarray(result.valve.root.axis)
    g_c = result.metrics.g_c
    near = lift > np.quantile(lift, 0.7)
    gap = np.where(near, 0.1 + 0.3 * np.linspace(0, 1, len(x)), np.inf)[:, None]
    result = dataclasses.replace(result, metrics=SimpleNamespace(gap=gap, g_c=g_c, h_c=0.0))
    root = result.valve.root
    origin, e1, e2 = aortic_frame(root)
    axis = np.asarray(root.axis)
    np.testing.assert_allclose([e1 @ e1, e2 @ e2, e1 @ e2, e1 @ axis, e2 @ axis],
                               [1, 1, 0, 0, 0], atol=1e-12)
    uv = [((c - origin) @ e1, (c - origin) @ e2) for c in np.asarray(root.commissures)]
    ang = np.unwrap([np.arctan2(v, u) for u, v in uv])
    assert np.all(np.diff(ang) > 0) and abs(ang[0]) < 1e-12        # C0 on the +u axis
    try:
        fig = result.plot_aortic_view()
        ax = fig.axes[0]
        (polys,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
        m = len(result.valve.leaflet.triangles)
        assert len(polys.get_paths()) == 3 * m
        zones = _zone_faces(result)
        n_zone = sum(int(z.sum()) for z, _ in zones)
        assert n_zone > 0
        fc = polys.get_facecolor()
        base = {tuple(np.round(matplotlib.colors.to_rgba(c, 0.9), 6))
                for c in ("tab:blue", "tab:orange", "tab:green")}
        coloured = sum(tuple(np.round(f, 6)) not in base for f in fc)
        assert coloured == n_zone
        # the faces are in painter's order: the last one drawn is one of the nearest to
        # the aorta (the three leaflets tie)
        xs = np.asarray(result.x)[result.valve.triangles] - origin
        depth = (xs @ axis).mean(axis=1)
        last = np.sort(polys.get_paths()[-1].vertices[:3] @ [1.0, 0.0])
        nearest = np.flatnonzero(depth < depth.min() + 1e-9)
        assert any(np.allclose(np.sort(xs[k] @ e1), last, atol=1e-9) for k in nearest)
        assert "NOT CONVERGED" in ax.get_title()
    finally:
        plt.close("all")


def test_plot_helpers_return_figures(run):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    _, result, _, _, _ = run
    try:
        for fig in (result.plot_valve(), result.plot_profiles(), result.plot_pair_heights(),
                    result.plot_valve(state="effective"), result.plot_aortic_view()):
            assert fig.axes and fig.axes[0].get_xlabel().endswith("(mm)")
    finally:
        plt.close("all")


def test_help_mentions_the_flags(capsys):
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--model", "--pressure", "--root", "--max-steps", "--g-c", "--out"):
        assert flag in text
    assert "mmHg" in text and "MPa" in text


def _code(argv):
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


@pytest.mark.parametrize("argv, named", [
    (["--h", "-1"], "h must be"),
    (["--model", "foo"], "--model"),
    (["--pressure", "0"], "pressure"),
    (["missing_scene.toml"], "missing_scene.toml"),
    (["--root", "a.stl"], "--root"),
    (["--root", "nowhere.stl", "nowhere.json"], "nowhere"),
])
def test_bad_input_exits_2_naming_the_parameter(argv, named, capsys, tmp_path):
    argv = [tmp_path / a if a.endswith(".toml") else a for a in argv]
    assert _code(["simulate", *map(str, argv), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert named in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_bad_toml_key_exits_2(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text("hh = 3.0\n")
    assert main(["simulate", str(p)]) == 2
    assert "hh" in capsys.readouterr().err


def test_json_flag_prints_only_json_and_no_figures_skips_pngs(run, tmp_path, capsys):
    # same mesh and solver as the module run: the compiled solve is reused (fast)
    code = main(["simulate", "--h", "3", "--max-steps", "40", "--json", "--no-figures",
                 "--out", str(tmp_path)])
    cap = capsys.readouterr()
    assert code == 3
    data = json.loads(cap.out)
    assert data["converged"] is False and data["scene"]["g_c"] == 0.5
    assert "[jaxvalve]" in cap.err and "did NOT converge" in cap.err
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "leaflet_0.vtu", "leaflet_1.vtu", "leaflet_2.vtu", "metrics.json"]


def test_a_central_coaptation_point_above_the_commissures_is_flagged(run):
    """`SimulationResult.warnings` flags surplus tissue (h_E above every commissure) with
    both figures, and only then; metrics.json carries the same list."""
    from types import SimpleNamespace
    _, result, out, _, stderr = run
    root = SimpleNamespace(commissure_heights=np.array([16.8, 16.9, 16.7]))

    def with_h_E(h, converged=True):
        return sim_mod.SimulationResult(
            scene=result.scene, valve=SimpleNamespace(root=root), x=result.x,
            x_he=result.x_he, metrics=result.metrics,
            metrics_he=SimpleNamespace(h_e=h),
            solves=(SimpleNamespace(converged=converged, result="successful" if converged
                                     else "max_steps_reached"),) * 2, timings={})
    (w,) = with_h_E(18.5).warnings
    assert "surplus tissue" in w and "18.5 mm" in w and "16.7-16.9 mm" in w
    assert with_h_E(16.85).warnings == () and with_h_E(float("nan")).warnings == ()
    # an unconverged state is no design: nothing is flagged (the module's run is one)
    assert with_h_E(18.5, converged=False).warnings == ()
    assert not result.solves[0].converged and result.warnings == ()
    data = json.loads((out / "metrics.json").read_text())
    assert data["warnings"] == [] and "surplus" not in stderr


def test_coinciding_profiles_are_drawn_once_and_said_to_coincide(run):
    """`profile_distance` is 0 for identical profiles and the largest end-to-nearest-end
    distance otherwise; `plot_profiles` draws three coinciding profiles as one line whose
    label says so, and three distinct ones as three."""
    import dataclasses
    import matplotlib.pyplot as plt
    from jaxvalve.io.plots import COINCIDE_MM, plot_profiles, profile_distance
    _, result, _, _, _ = run
    seg = np.array([[[0.0, 0.0], [1.0, 0.0]], [[1.0, 0.0], [2.0, 1.0]]])
    assert profile_distance([seg, seg, seg]) == 0.0
    assert profile_distance([seg, seg, seg + [0.0, 0.3]]) == pytest.approx(0.3)
    assert profile_distance([seg, seg, seg[:0]]) == np.inf
    assert profile_distance([seg[:0]] * 3) == 0.0
    same = dataclasses.replace(result, metrics=dataclasses.replace(
        result.metrics, profile=[seg, seg + 0.2 * COINCIDE_MM, seg]))
    apart = dataclasses.replace(result, metrics=dataclasses.replace(
        result.metrics, profile=[seg, seg + 1.0, seg]))
    for res, n, text in ((same, 1, "the profiles coincide (within 0.014 mm)"),
                         (apart, 3, "leaflet 2 (2 segments)")):
        fig = plot_profiles(res)
        labels = [c.get_label() for c in fig.axes[0].collections]
        assert len(labels) == n and text in labels[-1]
        plt.close(fig)
