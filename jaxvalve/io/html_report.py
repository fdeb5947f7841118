"""A self-contained HTML report of a closed valve (``report.html``): opens offline.

One file, no network: the closed valve in 3D on a canvas that a person rotates with the
mouse (drag; wheel to zoom; buttons for the side view and the surgeon's view down the axis
from the aorta), each leaflet in its colour with its coaptation zone coloured by gap; the
convergence status first (a red banner where a closure did not converge or the valve has
no equilibrium at the load); the metrics with their units and meanings; the design
warnings; and the figures (the view from the aorta, the coaptation profiles, the pair
heights) embedded as PNG.  The 3D view is drawn by a small script in the page itself
(orthographic projection, painter's order, Lambert shading): no WebGL and no library.
When it has drawn, the page records the number of triangles in
``document.body.dataset.rendered`` and the canvas's place on the page (x, y, width,
height in CSS pixels) in ``dataset.canvas``; any script error is listed on the page and in
``dataset.errors`` (what the browser test reads).
"""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

__all__ = ["html_report", "write_html_report"]

#: the headline metrics: (key of `SimulationResult.summary`, label, unit, meaning)
METRICS = (
    ("h_E", "h_E", "mm", "effective height: top of the central coaptation zone above the "
                         "annulus plane, at the effective-height load"),
    ("h_CC", "h_C-C", "mm", "pair coaptation height at 5 mm from the axis, mean of the pairs"),
    ("h_avr", "h_avr", "mm", "coaptation zone area / deformed free-edge length"),
    ("NCCA_pct", "NCCA", "%", "coaptation zone area / cusp area"),
    ("h", "h", "mm", "largest pair coaptation height"),
    ("h_c", "h_c", "mm", "axial extent of the central zone (0: a central gap)"),
    ("coaptation_area", "coaptation area", "mm^2", "area of the three leaflets' zones"),
)


def _scene_data(result) -> dict:
    """Node positions (mm, rounded to 1e-3), triangles and face colours (RGB 0-255) of the
    closed valve, centred on its bounding box, and the frame of the view from the aorta."""
    from matplotlib import colors

    from .plots import COLOURS, _face_colours, _zone_faces, aortic_frame
    xs, tris, cols = [], [], []
    base = 0
    for i, (zone, gap) in enumerate(_zone_faces(result)):
        p, tri = result.leaflet(i, "closed")
        xs.append(np.asarray(p, float))
        tris.append(np.asarray(tri) + base)
        cols.append(_face_colours(COLOURS[i], zone, gap, result.metrics.g_c)[:, :3])
        base += len(p)
    x = np.concatenate(xs)
    _, e1, e2 = aortic_frame(result.valve.root)
    axis = np.asarray(result.valve.root.axis, float)
    centre = 0.5 * (x.min(axis=0) + x.max(axis=0))       # the view turns about it
    return {
        "x": np.round(x - centre, 3).ravel().tolist(),
        "t": np.concatenate(tris).astype(int).ravel().tolist(),
        "c": np.round(255 * np.concatenate(cols)).astype(int).ravel().tolist(),
        "e1": e1.tolist(), "e2": e2.tolist(), "axis": axis.tolist(),
        "legend": [colors.to_hex(c) for c in COLOURS],
    }


def _status(result) -> tuple[str, str]:
    """(css class, text) of the convergence banner."""
    lim = [s for s in result.solves if s.result == "limit_point"]
    if lim:
        return "bad", (f"LIMIT POINT: the valve has no equilibrium above "
                       f"{lim[0].limit_pressure:.3g} mmHg; the state and the metrics shown "
                       f"are those at {lim[0].limit_pressure:.3g} mmHg, not at "
                       f"{lim[-1].pressure:g} mmHg.")
    if not result.converged:
        bad = "; ".join(f"at {s.pressure:g} mmHg: {s.describe()}" for s in result.solves
                        if not s.converged)
        return "bad", (f"NOT CONVERGED ({bad}). The state and the metrics shown are of an "
                       "unconverged state, not of a closed valve.")
    worst = max(float(s.residual) for s in result.solves)
    return "good", (f"Converged: both closures reached a relative residual of "
                    f"{worst:.1e} or less (rtol {result.scene.rtol:g}).")


#: the figures the report embeds: (`plots.FIGURES` name, caption)
EMBEDDED = (("valve_aortic_view", "the closed valve seen from the aorta"),
            ("profiles", "coaptation profiles on the flat template"),
            ("pair_heights", "pair coaptation heights H_ij(w)"))


def html_report(result, pngs: dict | None = None) -> str:
    """The report of a `SimulationResult` as one HTML document (str).  pngs: the
    figures already drawn (`plots.figure_pngs`, as `write_outputs` passes them); those
    missing are drawn here."""
    from .. import __version__
    from .plots import figure_pngs

    pngs = dict(pngs or {})
    missing = [n for n, _ in EMBEDDED if n not in pngs]
    if missing:
        pngs.update(figure_pngs(result, missing))

    cls, status = _status(result)
    s = result.summary()
    rows = "\n".join(
        f"<tr><td>{html.escape(label)}</td><td class='num'>{s[k]:.2f}</td>"
        f"<td>{html.escape(unit)}</td><td>{html.escape(text)}</td></tr>"
        for k, label, unit, text in METRICS)
    solves = "\n".join(
        f"<tr><td>{sv.pressure:g} mmHg</td><td>{html.escape(sv.describe())}</td></tr>"
        for sv in result.solves)
    warns = "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings)
    sc = result.scene
    scene = (f"template r = {sc.r:g} mm, a = {sc.a:g} mm, b = {sc.b:g} mm, alpha = "
             f"{sc.alpha:g} deg; mesh h = {sc.h:g} mm; {sc.model}; closing load "
             f"{sc.pressure:g} mmHg, effective-height load {sc.he_pressure:g} mmHg; "
             f"coaptation distance g_c = {result.metrics.g_c:g} mm")
    figs = "".join(
        f"<figure><img alt='{html.escape(alt)}' src='data:image/png;base64,"
        f"{base64.b64encode(pngs[name]).decode('ascii')}'>"
        f"<figcaption>{html.escape(alt)}</figcaption></figure>"
        for name, alt in EMBEDDED)
    data = json.dumps(_scene_data(result), separators=(",", ":"))
    return _PAGE.format(version=html.escape(__version__), cls=cls,
                        status=html.escape(status), rows=rows, solves=solves,
                        warns=(f"<h2>Warnings</h2><ul>{warns}</ul>" if warns else ""),
                        scene=html.escape(scene), figs=figs, data=data,
                        g_c=f"{result.metrics.g_c:g}")


def write_html_report(result, path, pngs: dict | None = None) -> Path:
    """Write `html_report` to ``path`` (UTF-8); returns the path."""
    p = Path(path)
    p.write_text(html_report(result, pngs), encoding="utf-8")
    return p


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>jaxvalve report</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 70em; color: #222; }}
.banner {{ padding: 0.8em 1em; border-radius: 4px; font-weight: bold; }}
.good {{ background: #e3f4e3; border: 1px solid #4a4; }}
.bad {{ background: #fde2e2; border: 2px solid #c00; color: #900; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 0.25em 0.7em; text-align: left; }}
td.num {{ text-align: right; font-variant-numeric: tabular-nums; }}
#view {{ border: 1px solid #aaa; cursor: grab; background: #fff; }}
figure {{ display: inline-block; margin: 0.5em; }} figure img {{ max-width: 32em; }}
#errors {{ color: #c00; }}
</style></head>
<body>
<h1>jaxvalve: closed valve</h1>
<p class="banner {cls}" id="status">{status}</p>
<p>{scene}</p>
<h2>Coaptation</h2>
<table><tr><th>metric</th><th>value</th><th>unit</th><th>meaning</th></tr>
{rows}
</table>
<h2>Solves</h2>
<table>{solves}</table>
{warns}
<h2>The closed valve in 3D</h2>
<p>Drag to rotate, wheel to zoom.
<button id="side">side view</button> <button id="top">from the aorta</button>
Leaflets in blue, orange and green; the coaptation zone (gap &lt; g_c = {g_c} mm) coloured
by its gap, from dark (touching) to yellow (g_c).</p>
<canvas id="view" width="720" height="560"></canvas>
<ul id="errors"></ul>
<h2>Figures</h2>
{figs}
<p><small>jaxvalve {version}</small></p>
<script id="valve-data" type="application/json">{data}</script>
<script>
(function () {{
  var errs = [];
  function fail(msg) {{
    errs.push(msg);
    document.body.dataset.errors = errs.join(" | ");
    var li = document.createElement("li"); li.textContent = msg;
    document.getElementById("errors").appendChild(li);
  }}
  window.addEventListener("error", function (e) {{ fail(String(e.message)); }});
  try {{
    var D = JSON.parse(document.getElementById("valve-data").textContent);
    var X = D.x, T = D.t, C = D.c, nt = T.length / 3, nn = X.length / 3;
    var canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
    var e1 = D.e1, e2 = D.e2, ax = D.axis;
    // camera basis: right r, up u, towards the viewer f (orthonormal rows)
    function basis(yaw, pitch) {{
      // start: looking from the side, the aorta (-axis) up
      var up = [-ax[0], -ax[1], -ax[2]];
      var cy = Math.cos(yaw), sy = Math.sin(yaw);
      var h = [cy * e1[0] + sy * e2[0], cy * e1[1] + sy * e2[1], cy * e1[2] + sy * e2[2]];
      var r = [-sy * e1[0] + cy * e2[0], -sy * e1[1] + cy * e2[1], -sy * e1[2] + cy * e2[2]];
      var cp = Math.cos(pitch), sp = Math.sin(pitch);
      var f = [cp * h[0] + sp * up[0], cp * h[1] + sp * up[1], cp * h[2] + sp * up[2]];
      var u = [cp * up[0] - sp * h[0], cp * up[1] - sp * h[1], cp * up[2] - sp * h[2]];
      return [r, u, f];
    }}
    var yaw = 0.5, pitch = 0.35, zoom = 1.0, span = 0;
    for (var i = 0; i < nn; i++) {{
      span = Math.max(span, Math.hypot(X[3 * i], X[3 * i + 1], X[3 * i + 2]));
    }}
    var P = new Float64Array(3 * nn), order = new Array(nt), depth = new Float64Array(nt);
    function draw() {{
      var B = basis(yaw, pitch), s = zoom * 0.45 * Math.min(canvas.width, canvas.height) / span;
      var cx = canvas.width / 2, cy = canvas.height / 2;
      for (var i = 0; i < nn; i++) {{
        var x = X[3 * i], y = X[3 * i + 1], z = X[3 * i + 2];
        P[3 * i] = B[0][0] * x + B[0][1] * y + B[0][2] * z;
        P[3 * i + 1] = B[1][0] * x + B[1][1] * y + B[1][2] * z;
        P[3 * i + 2] = B[2][0] * x + B[2][1] * y + B[2][2] * z;
      }}
      for (var k = 0; k < nt; k++) {{
        order[k] = k;
        depth[k] = P[3 * T[3 * k] + 2] + P[3 * T[3 * k + 1] + 2] + P[3 * T[3 * k + 2] + 2];
      }}
      order.sort(function (a, b) {{ return depth[a] - depth[b]; }});   // far first
      ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, canvas.width, canvas.height);
      ctx.lineWidth = 0.3; ctx.strokeStyle = "rgba(0,0,0,0.15)";
      for (var j = 0; j < nt; j++) {{
        var k = order[j], a = 3 * T[3 * k], b = 3 * T[3 * k + 1], c = 3 * T[3 * k + 2];
        var ux = P[b] - P[a], uy = P[b + 1] - P[a + 1], uz = P[b + 2] - P[a + 2];
        var vx = P[c] - P[a], vy = P[c + 1] - P[a + 1], vz = P[c + 2] - P[a + 2];
        var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
        var lam = 0.35 + 0.65 * Math.abs(nz) / (Math.hypot(nx, ny, nz) || 1);
        ctx.fillStyle = "rgb(" + Math.round(C[3 * k] * lam) + "," +
          Math.round(C[3 * k + 1] * lam) + "," + Math.round(C[3 * k + 2] * lam) + ")";
        ctx.beginPath();
        ctx.moveTo(cx + s * P[a], cy - s * P[a + 1]);
        ctx.lineTo(cx + s * P[b], cy - s * P[b + 1]);
        ctx.lineTo(cx + s * P[c], cy - s * P[c + 1]);
        ctx.closePath(); ctx.fill(); ctx.stroke();
      }}
      var rect = canvas.getBoundingClientRect();
      document.body.dataset.canvas = [rect.left + window.scrollX, rect.top + window.scrollY,
                                      rect.width, rect.height].map(Math.round).join(",");
      document.body.dataset.rendered = String(nt);
    }}
    var drag = null;
    canvas.addEventListener("mousedown", function (e) {{ drag = [e.clientX, e.clientY]; }});
    window.addEventListener("mouseup", function () {{ drag = null; }});
    window.addEventListener("mousemove", function (e) {{
      if (!drag) return;
      yaw -= 0.01 * (e.clientX - drag[0]);
      pitch = Math.max(-1.57, Math.min(1.57, pitch + 0.01 * (e.clientY - drag[1])));
      drag = [e.clientX, e.clientY]; draw();
    }});
    canvas.addEventListener("wheel", function (e) {{
      e.preventDefault(); zoom *= Math.exp(-0.001 * e.deltaY); draw();
    }}, {{ passive: false }});
    document.getElementById("side").onclick = function () {{ yaw = 0.5; pitch = 0.35; draw(); }};
    document.getElementById("top").onclick = function () {{   // as valve_aortic_view.png
      yaw = -1.5707963; pitch = 1.5707963; draw();
    }};
    draw();
  }} catch (e) {{
    fail(String(e && e.message || e));
  }}
}})();
</script>
</body></html>
"""
