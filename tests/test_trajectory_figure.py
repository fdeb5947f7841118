"""The optimiser's figure: one panel per unit, integer iteration ticks, labelled targets."""
import numpy as np

from jaxvalve.io.plots import _pyplot
from optimize.targets import parse_target
from optimize.trajectory import figure


def test_the_optimisation_figure_has_a_panel_per_unit_and_integer_iterations():
    records = [dict(iteration=k, objective=4.0 / (k + 1), r=12.0, a=7.1 - 0.1 * k, b=15.0,
                    **{"m:h_c": 3.0 + k, "m:h_E": 19.0, "m:NCCA_pct": 50.0 - k,
                       "m:area": 400.0}) for k in range(3)]
    targets = (parse_target("h_c>=4"), parse_target("NCCA<=49"))
    plt = _pyplot()
    fig = figure(records, 160.0, targets, plt)
    try:
        obj, mm, pct, tpl = fig.axes
        assert "mm" in mm.get_ylabel() and "%" in pct.get_ylabel()
        mm_labels = [t.get_text() for t in mm.get_legend().get_texts()]
        pct_labels = [t.get_text() for t in pct.get_legend().get_texts()]
        assert mm_labels == ["h_c", "target h_c >= 4 mm", "h_E"]
        assert pct_labels == ["NCCA_pct", "target NCCA_pct <= 49 %"]
        for ax in (obj, mm, pct):
            ticks = ax.get_xticks()
            assert np.all(ticks == np.round(ticks)) and ax.get_xlabel() == "iteration"
        assert tpl.get_title() == "template"
    finally:
        plt.close(fig)
