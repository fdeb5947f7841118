"""Draw docs/figures/metrics.png: the coaptation metrics on one closed valve.

    python docs/figures/make_metrics_figure.py [--h 1.5]

The benchmark valve (StVK, E = 1 MPa) closed at 80 mmHg on a mesh of size h: the view
from the aorta with each zone coloured by its gap, the coaptation profiles on the flat
template, and the pair heights H_ij(w) with h and h_C-C marked.  The figure's title gives
the metrics of that closure (and says if it did not converge).
"""
from __future__ import annotations

import argparse
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    args = ap.parse_args(argv)
    from matplotlib.figure import Figure

    from jaxvalve import Scene, simulate
    from jaxvalve.io.plots import plot_aortic_view, plot_pair_heights, plot_profiles

    res = simulate(Scene(h=args.h), throw=False)
    s = res.summary()
    fig = Figure(figsize=(20, 6.2))
    for k, fn in enumerate((plot_aortic_view, plot_profiles, plot_pair_heights)):
        fn(res, ax=fig.add_subplot(1, 3, k + 1))
    ax = fig.axes[-1]
    m = res.metrics
    ax.axhline(m.h, color="0.4", linestyle=":", linewidth=1.0, label=f"h = {m.h:.2f} mm")
    ax.legend(loc="best", fontsize="small")
    state = "" if res.converged else " (NOT CONVERGED)"
    fig.suptitle(f"benchmark valve, StVK, h = {args.h:g} mm{state}: h_E {s['h_E']:.2f} mm, "
                 f"h_C-C {s['h_CC']:.2f} mm, h_avr {s['h_avr']:.2f} mm, NCCA "
                 f"{s['NCCA_pct']:.1f} %, h {s['h']:.2f} mm, h_c {s['h_c']:.2f} mm")
    out = HERE / "metrics.png"
    fig.savefig(out, dpi=80, bbox_inches="tight")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
