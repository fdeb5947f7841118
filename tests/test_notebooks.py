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
    for name in ("fig_valve", "fig_profiles", "fig_heights"):
        fig = nb01[name]
        assert len(fig.axes) >= 1
        assert np.all(np.isfinite(fig.get_size_inches()))
