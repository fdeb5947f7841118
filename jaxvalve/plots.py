"""Figures of a `jaxvalve.simulation.SimulationResult` (matplotlib, imported lazily).

Each function draws into ``ax`` when given (``plot_valve`` needs a 3D axes) and otherwise
makes a new pyplot figure (the Agg backend is chosen when there is no display).  Each
returns the matplotlib `Figure`.  Lengths in mm.
"""
from __future__ import annotations

import os
import sys

import numpy as np

__all__ = ["plot_valve", "plot_profiles", "plot_pair_heights", "profile_distance"]

COLOURS = ("tab:blue", "tab:orange", "tab:green")
# distinct styles, so that the (often identical) curves of a symmetric valve stay visible
STYLES = (dict(linestyle="-", linewidth=3.0), dict(linestyle="--", linewidth=2.0),
          dict(linestyle=":", linewidth=1.5))


def _pyplot():
    import matplotlib
    headless = sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if headless and "MPLBACKEND" not in os.environ and "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _axes(ax, **kw):
    if ax is None:
        fig = _pyplot().figure(figsize=(7, 6))
        ax = fig.add_subplot(**kw)
    return ax.figure, ax


def _status(result, load=1):
    """Title suffix naming a load's outcome unless it converged (load 0: the effective-
    height load, 1: the closing load): a figure never shows an unconverged state as if
    it were one; a state closed by the barrier fallback says so."""
    r = result.solves[load]
    if r.converged:
        return (f"\nclosed by {r.path} (the fallback: {r.fallback.split(':')[0]})"
                if r.fallback else "")
    if r.result == "limit_point":
        return (f"\nLIMIT POINT: no equilibrium above {r.limit_pressure:.3g} mmHg; "
                f"shown at {r.limit_pressure:.3g} mmHg")
    return f"\nNOT CONVERGED: {r.describe()}"


def plot_valve(result, ax=None, state="closed"):
    """The three leaflets in 3D (mm) in ``state`` ('closed', 'effective', 'placed' or
    'template'), with the suturing paths in black."""
    fig, ax = _axes(ax, projection="3d")
    allp = []
    for i in range(3):
        p, tri = result.leaflet(i, state)
        ax.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], triangles=tri, color=COLOURS[i],
                        edgecolor=(0, 0, 0, 0.25), linewidth=0.2, alpha=0.9)
        allp.append(p)
    if state != "template":
        for path in result.valve.root.paths:
            q = np.asarray(path)
            ax.plot(q[:, 0], q[:, 1], q[:, 2], color="k", linewidth=1.0)
    allp = np.concatenate(allp)
    span = np.ptp(allp, axis=0)
    ax.set_box_aspect(np.maximum(span, 1e-3 * span.max()))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    load = {"closed": f", P = {result.scene.pressure:g} mmHg",
            "effective": f", P = {result.scene.he_pressure:g} mmHg"}.get(state, "")
    status = {"closed": _status(result, 1), "effective": _status(result, 0)}.get(state, "")
    ax.set_title(f"valve ({state}{load}){status}")
    return fig


#: profiles of the three leaflets closer than this (mm, `profile_distance`) are drawn as one
COINCIDE_MM = 0.05


def profile_distance(profiles) -> float:
    """The largest distance (mm, template coordinates) from a segment end of one leaflet's
    coaptation profile to the nearest segment end of another's, over all pairs (both
    ways): 0 for identical profiles; inf where one profile is empty and another is not."""
    from scipy.spatial import cKDTree
    pts = [np.asarray(p, float).reshape(-1, 2) for p in profiles]
    if all(len(p) == 0 for p in pts):
        return 0.0
    if any(len(p) == 0 for p in pts):
        return float("inf")
    return max(float(cKDTree(pts[j]).query(pts[i])[0].max())
               for i in range(len(pts)) for j in range(len(pts)) if i != j)


def plot_profiles(result, ax=None):
    """Coaptation profiles on the flat template: its outline (grey) and each leaflet's
    zone boundary (gap = g_c) at the closing load, in template coordinates (mm)."""
    from matplotlib.collections import LineCollection

    fig, ax = _axes(ax)
    lm = result.valve.leaflet
    pts = np.asarray(lm.points)
    for idx in (lm.sutured, lm.free):
        ax.plot(pts[idx, 0], pts[idx, 1], color="0.5", linewidth=1.0)
    profiles = [np.asarray(seg).reshape(-1, 2, 2) for seg in result.metrics.profile]
    apart = profile_distance(profiles)
    if apart <= COINCIDE_MM:         # one line, and the figure says so
        ax.add_collection(LineCollection(profiles[0], colors="k", linewidths=2.0,
                                         label=f"leaflets 0, 1, 2: the profiles coincide "
                                               f"(within {max(apart, 0.0):.2g} mm)"))
    else:
        for i, seg in enumerate(profiles):
            st = STYLES[i % 3]
            ax.add_collection(LineCollection(seg, colors=COLOURS[i],
                                             linewidths=st["linewidth"],
                                             linestyles=st["linestyle"],
                                             label=f"leaflet {i} ({len(seg)} segments)"))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("template x (mm)")
    ax.set_ylabel("template y (mm)")
    ax.set_title(f"coaptation profiles (gap < {result.metrics.g_c:g} mm, "
                 f"P = {result.scene.pressure:g} mmHg){_status(result)}")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3, fontsize="small")
    return fig


def plot_pair_heights(result, ax=None):
    """Pair height curves H_ij(w) (mm) at the closing load, one per leaflet pair, with the
    C-C line at w = w_cc (5 mm)."""
    fig, ax = _axes(ax)
    m = result.metrics
    c = m.curves
    for p, (i, j) in enumerate(np.asarray(c.pairs)):
        ax.plot(c.w, c.H[p], color=COLOURS[p % 3], label=f"leaflets {i}-{j}", **STYLES[p % 3])
    ax.axvline(m.w_cc, color="k", linestyle="--", linewidth=1.0,
               label=f"C-C: w = {m.w_cc:g} mm (h_CC = {m.h_cc:.2f} mm)")
    ax.set_xlabel("w: distance from the axis in the pair's mid-plane (mm)")
    ax.set_ylabel("pair coaptation height H_ij(w) (mm)")
    ax.set_title(f"pair heights (P = {result.scene.pressure:g} mmHg, h = {m.h:.2f} mm)"
                 f"{_status(result)}")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.legend(loc="best", fontsize="small")
    return fig
