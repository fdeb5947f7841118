"""Figures of a `jaxvalve.simulation.SimulationResult` (matplotlib, imported lazily).

Each function draws into ``ax`` when given (``plot_valve`` needs a 3D axes) and otherwise
makes a new pyplot figure (the Agg backend is chosen when there is no display).  Each
returns the matplotlib `Figure`.  Lengths in mm.
"""
from __future__ import annotations

import os
import sys

import numpy as np

__all__ = ["plot_valve", "plot_aortic_view", "plot_profiles", "plot_pair_heights",
           "profile_distance", "aortic_frame", "FIGURES", "figure_pngs"]

#: colour map of the gap (mm) inside the coaptation zone, 0 (touching) to g_c
GAP_CMAP = "plasma"

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
    it were one."""
    r = result.solves[load]
    if r.converged:
        return ""
    if r.result == "limit_point":
        return (f"\nLIMIT POINT: no equilibrium above {r.limit_pressure:.3g} mmHg; "
                f"shown at {r.limit_pressure:.3g} mmHg")
    return f"\nNOT CONVERGED: {r.describe()}"


def _zone_faces(result):
    """Per leaflet: (triangles in the coaptation zone (bool (m,)), their gap (m,) mm), at
    the closing load; a triangle is in the zone when its three nodes are (gap < g_c)."""
    from .report import nodal_gap
    m = result.metrics
    gap, _ = nodal_gap(m, np.asarray(result.x), result.valve.triangles)
    out = []
    for i in range(3):
        _, tri = result.leaflet(i, "closed")
        g = gap[result.valve.leaflet_slice(i)][tri]
        out.append((np.all(g < m.g_c, axis=1), g.mean(axis=1)))
    return out


def _face_colours(base, zone, gap, g_c):
    """RGBA (m, 4): the leaflet's colour, and the gap's colour (`GAP_CMAP`, 0..g_c) on the
    zone's triangles."""
    from matplotlib import colormaps, colors
    fc = np.tile(colors.to_rgba(base, 0.9), (len(zone), 1))
    fc[zone] = colormaps[GAP_CMAP](np.clip(gap[zone] / g_c, 0.0, 1.0))
    return fc


def _gap_colourbar(fig, ax, g_c):
    from matplotlib import cm, colors
    sm = cm.ScalarMappable(norm=colors.Normalize(0.0, g_c), cmap=GAP_CMAP)
    cb = fig.colorbar(sm, ax=ax, shrink=0.6, pad=0.08)
    cb.set_label(f"gap in the coaptation zone (mm; zone: gap < g_c = {g_c:g})")


def plot_valve(result, ax=None, state="closed"):
    """The three leaflets in 3D (mm) in ``state`` ('closed', 'effective', 'placed' or
    'template'), with the suturing paths in black; in the closed state each leaflet's
    coaptation zone is coloured by its gap (colour bar)."""
    fig, ax = _axes(ax, projection="3d")
    allp = []
    zones = _zone_faces(result) if state == "closed" else None
    for i in range(3):
        p, tri = result.leaflet(i, state)
        surf = ax.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], triangles=tri, color=COLOURS[i],
                               edgecolor=(0, 0, 0, 0.25), linewidth=0.2, alpha=0.9)
        if zones is not None:
            surf.set_facecolor(_face_colours(COLOURS[i], *zones[i], result.metrics.g_c))
        allp.append(p)
    if zones is not None:
        _gap_colourbar(fig, ax, result.metrics.g_c)
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


def aortic_frame(root):
    """(origin (3,), e1 (3,), e2 (3,)): the surgeon's view down the valve axis from the
    aorta.  e1 points from the axis to commissure 0, e2 = e1 x axis; seen so, the
    commissures, ordered counter-clockwise from the aorta, turn counter-clockwise."""
    axis = np.asarray(root.axis, float)
    origin = np.asarray(root.origin, float)
    c0 = np.asarray(root.commissures[0], float) - origin
    e1 = c0 - (c0 @ axis) * axis
    e1 = e1 / np.linalg.norm(e1)
    return origin, e1, np.cross(e1, axis)


def plot_aortic_view(result, ax=None):
    """The closed valve seen from the aorta down its axis (the surgeon's view, mm): each
    leaflet in its colour with its coaptation zone coloured by gap, nearer surfaces drawn
    over farther ones, the suturing paths in black, the commissures marked, and the
    centre of the valve; the title gives h_c, or says that there is a central gap."""
    from matplotlib.collections import PolyCollection

    fig, ax = _axes(ax)
    root, m = result.valve.root, result.metrics
    origin, e1, e2 = aortic_frame(root)
    axis = np.asarray(root.axis, float)
    polys, colours, depth = [], [], []
    for i, (zone, gap) in enumerate(_zone_faces(result)):
        p, tri = result.leaflet(i, "closed")
        q = p - origin
        uv = np.stack([q @ e1, q @ e2], axis=-1)
        polys.append(uv[tri])
        colours.append(_face_colours(COLOURS[i], zone, gap, m.g_c))
        depth.append((q @ axis)[tri].mean(axis=1))    # along the axis, away from the viewer
    polys, colours, depth = (np.concatenate(v) for v in (polys, colours, depth))
    order = np.argsort(-depth)                          # farthest first
    ax.add_collection(PolyCollection(polys[order], facecolors=colours[order],
                                     edgecolors=(0, 0, 0, 0.15), linewidths=0.2))
    for path in root.paths:
        q = np.asarray(path) - origin
        ax.plot(q @ e1, q @ e2, color="k", linewidth=1.0)
    for k, c in enumerate(np.asarray(root.commissures)):
        q = c - origin
        ax.plot(q @ e1, q @ e2, "k^", markersize=8)
        ax.annotate(f"C{k}", (q @ e1, q @ e2), textcoords="offset points", xytext=(6, 6))
    ax.plot(0.0, 0.0, "k+", markersize=12, label="valve axis")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("towards commissure C0 (mm)")
    ax.set_ylabel("perpendicular, in the annulus plane (mm)")
    ax.legend(loc="lower right", fontsize="small")
    _gap_colourbar(fig, ax, m.g_c)
    centre = (f"central coaptation h_c = {m.h_c:.2f} mm" if m.h_c > 0
              else "CENTRAL GAP: no point meets both other leaflets")
    ax.set_title(f"seen from the aorta (P = {result.scene.pressure:g} mmHg): {centre}"
                 f"{_status(result)}")
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


#: the figures of a simulation's outputs: name -> (drawing function, subplot keywords)
FIGURES = {"valve": (plot_valve, {"projection": "3d"}),
           "valve_aortic_view": (plot_aortic_view, {}),
           "profiles": (plot_profiles, {}),
           "pair_heights": (plot_pair_heights, {})}


def figure_pngs(result, names=tuple(FIGURES), dpi: int = 120) -> dict:
    """{name: PNG bytes} of the named `FIGURES`, each drawn once on its own `Figure` (no
    pyplot state); the files of `io.report.write_outputs` and the images embedded in the
    HTML report are these bytes."""
    import io

    from matplotlib.figure import Figure

    out = {}
    for name in names:
        fn, kw = FIGURES[name]
        fig = Figure(figsize=(7, 6))
        fn(result, ax=fig.add_subplot(**kw))
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
        out[name] = buf.getvalue()
    return out
