"""Coaptation characteristics of a closed valve (definitions: docs/metrics.md).

Inputs: deformed nodes x (N, 3) mm of all leaflets, oriented triangles (M, 3), leaflet
ids body (N,) in 0..L-1, template coordinates ref (N, 2) mm, free-edge mask (N,), valve
axis (3,) from aorta to ventricle and a point `origin` on it, and the annulus level s0
(axial coordinate, mm).  u(p) = (p - origin) . axis is the axial coordinate.

Definitions (sharp = reported; `coaptation_metrics`):
* gap d_ij(n): distance (mm) from node n of leaflet i to the surface of leaflet j (min of
  point-triangle distances), interpolated linearly on i's triangles.  The zone of i is
  where min_j d_ij < g_c (default 0.5 mm), clipped exactly by that linear level set.
* zone area (deformed), NCCA_i = zone area / cusp area, h_avr_i = zone area / free-edge
  length (sum of boundary edges whose ends are both free-edge nodes); valve values are
  means over leaflets.
* pair (i, j), all i < j (for a valve, L = 3, every pair is adjacent): the zone of i
  w.r.t. j (d_ij < g_c) and of j w.r.t. i.  Mid-plane: contains the axis; its in-plane
  direction e (perpendicular to the axis) is the major axis of the second moment, about
  the axis, of the two directed zones projected on the plane normal to the axis (each
  zone triangle weighted by its area times its zone fraction); e is oriented so that the
  zones' first moment is along +e.  w = (p - origin) . e.  H_i|j(w) = total axial length
  (union) of the zone's part on the line {w} of the (w, u) plane; H_ij = (H_i|j + H_j|i)
  / 2, the mean of the two sides' lengths.
* h = max over pairs and w >= 0 of H_ij (evaluated at every breakpoint of the piecewise
  linear H and on the grid: exact when each directed zone projects one-to-one);
  h_cc = mean over pairs of H_ij(w_cc), w_cc = 5 mm.
* three-leaflet zone: points of leaflet i with d_ij < g_c and d_ik < g_c (j, k the two
  others; any two others if L > 3), clipped exactly by both linear level sets; h_c = its
  axial extent (max u - min u), 0 if empty (always for L = 2).  h_E = s0 - u(c), c the
  zone's highest (smallest u) point, or the free-edge point nearest the axis when the
  zone is empty.
* coaptation profile: the zone boundary (level set) drawn on the template `ref`.

Smooth versions (`smooth`): pure jax.numpy functions of x with a `SmoothPlan` (candidate
node-triangle pairs and index sets fixed outside, on the host), smoothing width eps (mm)
and temperature T (mm, default eps).  Distances are exact point-triangle distances
(`contact.geometry.point_triangle_distance`, hard min over candidates).  The indicator
1[d < g_c] becomes H_eps(g_c - d), a C2 step of compact support [-eps, eps] (biweight
CDF), integrated exactly over each triangle / chord with the linearly interpolated field;
max / min become log-sum-exp.  H_ij is a sum of chord lengths over triangles (equal to the
sharp union when the projection is one-to-one); h is a log-sum-exp over pairs and the
plan's w grid; h_c / h_E use weighted soft extremes of the central candidates
(`central_zone`).  Every smooth metric tends to the sharp one as eps, T -> 0.
"""
from .topology import annulus_level
from .gaps import candidate_pairs, gap_field
from .sharp import CoaptationResult, PairCurves, coaptation_metrics
from .smooth import (SmoothPlan, plan_valid, smooth_gap_field, smooth_h, smooth_h_avr,
                     smooth_h_c, smooth_h_cc, smooth_h_e, smooth_metrics, smooth_ncca,
                     smooth_pair_heights, smooth_plan, smooth_zone_area)

__all__ = [
    "annulus_level", "candidate_pairs", "gap_field",
    "CoaptationResult", "PairCurves", "coaptation_metrics",
    "SmoothPlan", "smooth_plan", "plan_valid", "smooth_metrics", "smooth_gap_field",
    "smooth_zone_area", "smooth_ncca", "smooth_h_avr", "smooth_pair_heights", "smooth_h",
    "smooth_h_cc", "smooth_h_c", "smooth_h_e",
]
