"""The notebooks run top to bottom (coarse mesh h = 1.5 mm, two models) and their results are physical."""
import json
import os
from pathlib import Path

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


def run_notebook(path, env):
    """Execute the code cells of a notebook in one namespace; return the namespace."""
    nb = json.loads(Path(path).read_text())
    ns = {"__name__": "__notebook__"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        for cell in nb["cells"]:
            if cell["cell_type"] == "code":
                exec(compile("".join(cell["source"]), f"{path.name}", "exec"), ns)
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        import matplotlib.pyplot as plt
        plt.close("all")
    return ns


@pytest.fixture(scope="module")
def nb02():
    """Coarse (h = 2.5 mm) and at 3 mmHg: coarse meshes do not close at 80 mmHg (README,
    Known limits); two iterations toward h = 8 mm.  The valve and solver settings of
    tests/test_optimize.py's evaluator: in the CI this file runs right after that one, in
    its worker (tests/conftest.py, SAME_WORKER), and notebook 02 runs first here, on the
    programs compiled there, which are released after it."""
    ns = run_notebook(NOTEBOOKS / "02_optimisation.ipynb",
                      {"JAXVALVE_NB_H": "2.5", "JAXVALVE_NB_PRESSURE": "3",
                       "JAXVALVE_NB_TARGETS": "h_c>=4,h=8", "JAXVALVE_NB_MAXITER": "2"})
    yield ns
    import jax
    jax.clear_caches()


def test_notebook02_descends_toward_the_target(nb02):
    res = nb02["res"]
    assert not res.failed and len(res.records) == 3
    f = [r["objective"] for r in res.records]
    assert f[2] < f[1] < f[0]                                   # Armijo: strict decrease
    start, end = res.records[0], res.records[-1]
    # the run moves the smooth maximal height toward its target (8 mm)
    assert abs(end["m:h"] - 8.0) < abs(start["m:h"] - 8.0)
    # every record's metrics and parameters are finite, and the parameters stay in bounds
    for r in res.records:
        assert all(np.isfinite(v) for k, v in r.items() if isinstance(v, float))
        assert 8.0 <= r["r"] <= 16.0 and 2.0 <= r["a"] <= 14.0 and 8.0 <= r["b"] <= 22.0


def test_notebook02_exact_metrics_before_and_after(nb02):
    before, after, res = nb02["before"], nb02["after"], nb02["res"]
    assert before.converged and after.converged
    t = after.valve.leaflet.template
    np.testing.assert_allclose([t.r, t.a, t.b], res.rab, rtol=0, atol=1e-12)
    # the mapped mesh is the final template: its area is the template's area
    pts, tri = after.leaflet(0, "template")
    e1, e2 = pts[tri[:, 1]] - pts[tri[:, 0]], pts[tri[:, 2]] - pts[tri[:, 0]]
    area = 0.5 * np.abs(np.cross(e1, e2)[:, 2]).sum()
    assert area == pytest.approx(t.area, rel=2e-2)              # polygonal arc: below 2 %
    # the exact heights of the closed states agree with the smooth ones to ~ the smoothing
    for r, ev in ((before, nb02["ev_start"]), (after, res.evaluation)):
        s = r.summary()
        for k in ("h", "h_c"):
            assert abs(s[k] - ev.metrics[k]) < 0.5, (k, s[k], ev.metrics[k])
    # the same state and closed load as the evaluation (no re-solve at the closing load)
    np.testing.assert_array_equal(after.x, np.asarray(res.evaluation.states["closed"][1].x))


def test_notebook02_figures(nb02):
    # objective, metrics in mm, metrics in %, template
    axes = nb02["fig_trajectory"].axes
    assert len(axes) == 4 and "mm" in axes[1].get_ylabel() and "%" in axes[2].get_ylabel()
    assert len(nb02["fig_profiles"].axes) == 2
    for ax in nb02["fig_profiles"].axes:
        # one profile per leaflet, or one line where the three coincide (said in its label)
        labels = [c.get_label() for c in ax.collections]
        assert len(labels) == 3 or (len(labels) == 1 and "coincide" in labels[0]), labels


def test_notebook02_stiffness_sensitivity(nb02):
    sens, stiff, res = nb02["sens"], nb02["stiffness"], nb02["res"]
    assert all(np.isfinite(v) for d in sens.values() for v in d.values())
    # the adjoint slope d/dE has the sign of the secant between 0.5 E and 2 E, where the
    # secant is clearly non-zero
    assert stiff[0.5].converged and stiff[2.0].converged
    E0 = float(nb02["E0"])
    for k in ("h", "h_c"):
        secant = (stiff[2.0].metrics[k] - stiff[0.5].metrics[k]) / (1.5 * E0)
        if abs(secant) > 1e-2:
            assert np.sign(sens[k]["E"]) == np.sign(secant), (k, sens[k]["E"], secant)
    assert res.evaluation.metrics["h"] == pytest.approx(nb02["after"].summary()["h"], abs=0.5)


@pytest.fixture(scope="module")
def nb01():
    return run_notebook(NOTEBOOKS / "01_benchmark_closure.ipynb",
                        {"JAXVALVE_NB_H": "1.5", "JAXVALVE_NB_MODELS": "stvk,neo-hookean"})


def test_notebook01_closes_and_measures(nb01):
    res = nb01["res"]
    assert res.converged
    assert all(s.residual < res.scene.rtol for s in res.solves)
    s = res.summary()
    # the closed valve coapts: a central zone, heights below the template height, NCCA in (0, 1)
    assert s["h_c"] > 0 and 0 < s["NCCA_pct"] < 100
    assert 0 < s["h_CC"] <= s["h"] + 1e-9
    assert s["h"] < res.valve.leaflet.template.height
    # h_E: the central coaptation point lies between the annulus and the template's reach
    assert 0 < s["h_E"] < res.valve.leaflet.template.height


def test_notebook01_models_agree_within_paper_spread(nb01):
    results = nb01["results"]
    assert set(results) == {"stvk", "neo-hookean"}
    assert all(r.converged for r in results.values())
    # the same valve, two laws with the same small-strain modulus: close coaptation
    a, b = (results[m].summary() for m in ("stvk", "neo-hookean"))
    assert abs(a["h_E"] - b["h_E"]) < 1.0
    assert abs(a["NCCA_pct"] - b["NCCA_pct"]) < 6.0
    assert nb01["res"].summary()["h_E"] == pytest.approx(a["h_E"], abs=1e-9)


def test_notebook01_figures(nb01):
    for name in ("fig_valve", "fig_aorta", "fig_profiles", "fig_heights"):
        fig = nb01[name]
        assert len(fig.axes) >= 1
        assert np.all(np.isfinite(fig.get_size_inches()))


@pytest.mark.parametrize("name", ["01_benchmark_closure.ipynb", "02_optimisation.ipynb"])
def test_committed_notebooks_carry_their_outputs(name):
    """`notebooks/execute.py` wrote the outputs: every code cell ran, in order, once,
    without an error, and the figures are embedded as PNG (readable without running)."""
    nb = json.loads((NOTEBOOKS / name).read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert [c["execution_count"] for c in code] == list(range(1, len(code) + 1))
    outputs = [o for c in code for o in c["outputs"]]
    assert not [o for o in outputs if o["output_type"] == "error"]
    pngs = [o for o in outputs if "image/png" in o.get("data", {})]
    figure_cells = [c for c in code if "plot_" in "".join(c["source"])
                    or "figure(" in "".join(c["source"])]
    assert figure_cells and len(pngs) >= len(figure_cells)
    text = "".join("".join(o.get("text", "")) for o in outputs)
    assert "jaxvalve" in text and "Traceback" not in text
