"""Outputs of a simulation: ``metrics.json``, one ``.vtu`` per leaflet and PNG figures.

`metrics_json(result)` is the JSON-ready record of a `jaxvalve.simulation.SimulationResult`
(NaN / inf written as null); `write_outputs(result, out_dir)` writes the files.  Units: mm,
mm^2, mmHg, MPa, degrees, seconds; NCCA as a fraction (``summary.NCCA_pct`` in %).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import RootFileError
from .jsonable import plain
from ..geometry.mesh import cauchy_green_np, signed_areas_np

__all__ = ["metrics_json", "write_outputs", "principal_stretches", "nodal_average",
           "nodal_gap", "UNITS"]

UNITS = {"length": "mm", "area": "mm^2", "pressure": "mmHg", "modulus": "MPa",
         "angle": "degrees", "time": "s", "ncca": "fraction (summary.NCCA_pct: %)"}


def metrics_json(result) -> dict:
    """Everything about ``result`` as plain JSON data (no NaN / inf: those are null).

    Keys: jaxvalve_version, units, converged, residual (the worse relative residual of
    the two solves), summary (h_E, h_CC, h_avr, NCCA_pct, h, h_c, coaptation_area),
    metrics (closing load) and metrics_he (effective-height load; its h_e is h_E), both
    `CoaptationResult.as_dict()` with per-leaflet lists, pair curves w / H and profiles;
    model, scene (all parameters), solves (per load: pressure, result, converged, steps,
    residual, wall_s, compile_s, solve_s, limit_pressure, status), timings (s) and mesh
    sizes; warnings (`SimulationResult.warnings`: design findings, e.g. surplus tissue);
    limit_pressure (mmHg): where the valve passed a limit point, the highest
    pressure with an equilibrium, whose state the metrics describe (else null).
    """
    from .. import __version__

    scene, valve = result.scene, result.valve
    solves = []
    for name, s in zip(("effective_height", "closing"), result.solves):
        solves.append({"load": name, **s.as_dict(), "status": s.describe()})
    timings = dict(result.timings)
    timings["compile"] = sum(s.compile_s for s in result.solves)
    timings["solve"] = sum(s.solve_s for s in result.solves)
    n_tri = int(len(valve.leaflet.triangles))
    n_nodes = int(valve.leaflet.n_nodes)
    out = {
        "jaxvalve_version": __version__,
        "units": UNITS,
        "converged": bool(result.converged),
        "limit_pressure": next((s.limit_pressure for s in result.solves
                                if s.limit_pressure is not None), None),
        "residual": max(float(s.residual) for s in result.solves),
        "summary": result.summary(),
        "warnings": list(result.warnings),
        "model": scene.model,
        "scene": scene.as_dict(),
        "solves": solves,
        "timings": timings,
        "mesh": {"leaflets": 3, "triangles_per_leaflet": n_tri,
                 "nodes_per_leaflet": n_nodes, "triangles": 3 * n_tri, "nodes": 3 * n_nodes},
        "metrics": result.metrics.as_dict(),
        "metrics_he": result.metrics_he.as_dict(),
    }
    return plain(out)


# ------------------------------------------------------------------------- point data
def principal_stretches(x, triangles, ref) -> np.ndarray:
    """Principal in-plane stretches (M, 2), descending, of each triangle: sqrt(eig(C)),
    C = F^T F, F (3, 2) the affine map from the template triangle ``ref`` (N, 2) mm to
    ``x`` (N, 3) or (N, 2) mm.  Equal to 1 in the template (and any rigid) state."""
    ev = np.linalg.eigvalsh(cauchy_green_np(x, triangles, ref))                                 # ascending
    return np.sqrt(np.clip(ev, 0.0, None))[:, ::-1]


def nodal_average(values, triangles, n_nodes, weights=None) -> np.ndarray:
    """Average (n_nodes, ...) of per-triangle ``values`` (M, ...) over the triangles at
    each node, weighted by ``weights`` (M,) (default 1)."""
    values = np.asarray(values, dtype=np.float64)
    t = np.asarray(triangles)
    w = np.ones(len(t)) if weights is None else np.asarray(weights, dtype=np.float64)
    acc = np.zeros((n_nodes,) + values.shape[1:])
    wsum = np.zeros(n_nodes)
    for k in range(3):
        np.add.at(acc, t[:, k], w.reshape((-1,) + (1,) * (values.ndim - 1)) * values)
        np.add.at(wsum, t[:, k], w)
    return acc / np.where(wsum > 0, wsum, 1.0).reshape((-1,) + (1,) * (values.ndim - 1))


def nodal_gap(metrics, x, triangles):
    """Distance (N,) mm of each node to the nearest other leaflet, from ``metrics.gap``
    (N, L).  Distances beyond the coaptation search cutoff (g_c + the longest edge of x,
    as in `jaxvalve.coaptation.sharp.level_values`) are +inf there; they are clipped to
    that cutoff here, so a value equal to the cutoff means "at least this far".
    Returns (gap (N,), cutoff)."""
    from ..coaptation.topology import max_edge_length

    cutoff = (metrics.g_c + max_edge_length(np.asarray(x), np.asarray(triangles))) \
        * (1 + 1e-9) + 1e-12
    return np.minimum(np.min(metrics.gap, axis=1), cutoff), float(cutoff)


def leaflet_data(result, i):
    """(points (n, 3), triangles (m, 3), point_data, cell_data) of leaflet i, closed."""
    valve, m = result.valve, result.metrics
    sl = valve.leaflet_slice(i)
    x = np.asarray(result.x)
    gap, _ = nodal_gap(m, x, valve.triangles)
    pts, tri = result.leaflet(i, "closed")
    tpl = np.asarray(valve.leaflet.points, dtype=np.float64)
    lam = principal_stretches(pts, tri, tpl)
    point_data = {
        "displacement": pts - np.asarray(valve.x_start)[sl],
        "gap": gap[sl],
        "zone": (gap[sl] < m.g_c).astype(np.uint8),
        "principal_stretches": nodal_average(lam, tri, len(pts), np.abs(signed_areas_np(tpl, tri))),
        "template": tpl,
        # the solve's status on every node: meshio's VTU writer drops field data, and a
        # viewer shows point data beside the state it describes
        "converged": np.full(len(pts), int(result.converged), np.uint8),
        "residual": np.full(len(pts), max(float(s.residual) for s in result.solves)),
    }
    return pts, tri, point_data, {"principal_stretches": lam}


# ------------------------------------------------------------------------------- files
def write_outputs(result, out_dir, figures: bool = True) -> list[Path]:
    """Write into ``out_dir`` (created): ``metrics.json`` (`metrics_json`), ``leaflet_{i}.vtu``
    (closed state, mm) with point data displacement (n, 3) = x - x_start, gap (n,) to the
    nearest other leaflet (clipped at the search cutoff, see `nodal_gap`), zone (n,) uint8
    = gap < g_c, principal_stretches (n, 2) (reference-area-weighted nodal mean, also per
    triangle as cell data), template (n, 2) coordinates, and the solve's status on every
    node: converged (n,) uint8 (1 where every closure converged) and residual (n,) (the
    worse relative residual of the closures, as in metrics.json); with ``figures`` also
    ``valve.png`` (side view), ``valve_aortic_view.png`` (down the axis from the aorta),
    ``profiles.png`` and ``pair_heights.png``, and ``report.html`` (`jaxvalve.io.html_report`:
    one self-contained page, the valve in 3D, the metrics and the status).  Returns the
    paths."""
    from .files import write_surface

    out = Path(out_dir)
    paths = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        p = out / "metrics.json"
        p.write_text(json.dumps(metrics_json(result), indent=1, allow_nan=False) + "\n",
                     encoding="utf-8")
        paths.append(p)
        for i in range(3):
            pts, tri, pd, cd = leaflet_data(result, i)
            paths.append(write_surface(out / f"leaflet_{i}.vtu", pts, tri, point_data=pd,
                                       cell_data=cd))
        if figures:
            from .html_report import write_html_report
            from .plots import figure_pngs
            pngs = figure_pngs(result)          # drawn once: the files and the report
            for name, data in pngs.items():
                paths.append(out / f"{name}.png")
                paths[-1].write_bytes(data)
            paths.append(write_html_report(result, out / "report.html", pngs=pngs))
    except OSError as e:
        raise RootFileError(f"cannot write the outputs to '{out}': {e}") from None
    return paths
