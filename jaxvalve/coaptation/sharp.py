"""Sharp coaptation metrics of a closed valve (NumPy, host side): what is reported.

Conventions (see the package docstring for the definitions):
* u(p) = (p - origin) . axis is the axial coordinate (mm), growing toward the ventricle;
  "highest" means most aortic = smallest u.
* phi_ij(n) = g_c - d_ij(n) at node n of leaflet i, linearly interpolated on triangles;
  the zone of i w.r.t. j is phi_ij > 0; the zone of i is max_j phi_ij > 0 (i.e. the
  interpolated nodal minimum distance is < g_c).  Clipping is exact (marching triangles).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import MeshError, check_positive
from .central_zone import central_candidates, central_index, free_edge_closest
from .level_sets import chords, seg_fraction, tri_fraction, tri_moments
from .topology import check_frame, check_x, max_edge_length, perp_basis, topology
from .gaps import gap_field

__all__ = ["CoaptationResult", "PairCurves", "coaptation_metrics", "level_values",
           "pair_height_curves", "coaptation_profile", "zone_fractions"]


# ------------------------------------------------------------------------------ results
@dataclasses.dataclass(frozen=True)
class PairCurves:
    """Pair height curves H_ij(w) (mm) of leaflet pairs.

    pairs: (P, 2) leaflet ids (i < j).  direction: (P, 3) unit vector e of each pair's
    mid-plane (perpendicular to the axis, w = (p - origin) . e >= 0 toward the
    commissure).  w: (K,) sample positions (mm).  H: (P, K) = (H_i|j + H_j|i) / 2, mean
    of the two directed curves; H_directed: (P, 2, K) = [H_i|j, H_j|i].
    """

    pairs: np.ndarray
    direction: np.ndarray
    w: np.ndarray
    H: np.ndarray
    H_directed: np.ndarray


@dataclasses.dataclass(frozen=True)
class CoaptationResult:
    """Coaptation characteristics of a closed valve (lengths mm, areas mm^2).

    Per leaflet (L,): area (deformed cusp area), zone_area (deformed coaptation area),
    zone_area_flat (the same region on the flat template), free_edge_length (deformed),
    ncca = zone_area / area (-), h_avr = zone_area / free_edge_length (mm).
    Valve: ncca_valve, h_avr_valve = means over leaflets.
    Heights (mm): curves (`PairCurves`); h = max over pairs and w of H_ij(w), attained
    for pair h_pair_index at w = h_w; h_cc = mean over pairs of H_ij(w_cc), h_cc_pair (P,);
    h_c = axial extent of the three-leaflet zone (0 if empty), central_range = its
    (min u, max u) (NaN if empty); h_e = annulus_level - u(central_point), where
    central_point (3,) is the highest point of the three-leaflet zone or, if it is empty
    (h_e_from_free_edge True), the free-edge point nearest the axis.
    profile: per leaflet, (K_i, 2, 2) segments (mm, template frame) of the zone boundary,
    oriented with the zone on their left.  gap: (N, L) node-to-leaflet distances (mm,
    +inf beyond the search cutoff and for the node's own leaflet).
    Parameters: g_c, w_cc, annulus_level (mm).
    """

    g_c: float
    w_cc: float
    annulus_level: float
    area: np.ndarray
    zone_area: np.ndarray
    zone_area_flat: np.ndarray
    free_edge_length: np.ndarray
    ncca: np.ndarray
    h_avr: np.ndarray
    ncca_valve: float
    h_avr_valve: float
    curves: PairCurves
    h: float
    h_pair_index: int
    h_w: float
    h_cc: float
    h_cc_pair: np.ndarray
    h_c: float
    central_range: tuple
    h_e: float
    central_point: np.ndarray
    h_e_from_free_edge: bool
    profile: tuple
    gap: np.ndarray

    def as_dict(self, include_gap: bool = False) -> dict:
        """Plain floats / ints / lists (JSON-ready; NaN -> None).  `gap` only on request."""
        from ..io.jsonable import plain
        out = {}
        for f in dataclasses.fields(self):
            if f.name == "gap" and not include_gap:
                continue
            out[f.name] = plain(getattr(self, f.name))
        return out


# ------------------------------------------------------------------------------ pieces
def _tri_areas(p, tri):
    e1, e2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    if p.shape[1] == 2:
        return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def level_values(x, topo, g_c):
    """phi (N, L) = g_c - d (mm), distances clamped at the cutoff g_c + longest edge
    (exact wherever a triangle can reach the zone), own column -> g_c - cutoff; and the
    gap field (N, L) (inf beyond the cutoff)."""
    cutoff = (g_c + max_edge_length(x, topo.tri)) * (1 + 1e-9) + 1e-12
    gap = gap_field(x, topo.tri, topo.body, cutoff)
    return g_c - np.minimum(gap, cutoff), gap


def zone_fractions(phi, topo):
    """Per leaflet: sharp zone fraction (M_i,) of each triangle (zone = max_j phi_ij > 0)."""
    pmax = phi.max(axis=1)
    return tuple(tri_fraction(pmax[t], None, np) for t in topo.tris)


def _segments_on_template(ref, tri, pv):
    """Level-set segments (K, 2, 2) of the linear field pv (M, 3) > 0 on ref triangles."""
    inside = pv > 0
    cut = np.any(inside, axis=1) & ~np.all(inside, axis=1)
    tri, pv = tri[cut], pv[cut]
    r = ref[tri]                                              # (K, 3, 2)
    pts = []
    for k in range(3):
        a, b = k, (k + 1) % 3
        pa, pb = pv[:, a], pv[:, b]
        cross = (pa > 0) != (pb > 0)
        t = np.where(cross, pa / np.where(cross, pa - pb, 1.0), 0.0)
        pts.append((cross, r[:, a] + t[:, None] * (r[:, b] - r[:, a])))
    seg = np.zeros((tri.shape[0], 2, 2))
    filled = np.zeros(tri.shape[0], np.int64)
    for cross, p in pts:
        for slot in (0, 1):
            sel = cross & (filled == slot)
            seg[sel, slot] = p[sel]
            filled[sel] += 1
            cross = cross & ~sel
    # orient: zone (grad phi) on the left of the segment direction
    e1, e2 = r[:, 1] - r[:, 0], r[:, 2] - r[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    d1, d2 = pv[:, 1] - pv[:, 0], pv[:, 2] - pv[:, 0]
    gx = (d1 * e2[:, 1] - d2 * e1[:, 1]) / det
    gy = (d2 * e1[:, 0] - d1 * e2[:, 0]) / det
    v = seg[:, 1] - seg[:, 0]
    flip = v[:, 0] * gy - v[:, 1] * gx < 0
    seg[flip] = seg[flip][:, ::-1]
    scale = max(float(np.ptp(ref)), 1.0)
    return seg[np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) > 1e-12 * scale]


def coaptation_profile(ref, phi, topo):
    """Per leaflet, the zone boundary on the flat template: (K_i, 2, 2) segments (mm)."""
    pmax = phi.max(axis=1)
    return tuple(_segments_on_template(ref, t, pmax[t]) for t in topo.tris)


def _direction(x, topo, pair, phi, axis, origin, basis):
    """Unit direction e (3,) of the pair's mid-plane and the projected data of its two
    directed zones: list of (w (Z,3), u (Z,3), phi (Z,3)) over zone triangles."""
    m1, m2, data = np.zeros(2), np.zeros((2, 2)), []
    for a, b in (pair, pair[::-1]):
        t = topo.tris[a]
        pv = phi[:, b][t]
        f = tri_fraction(pv, None, np)
        q = (x[t] - origin) @ basis.T                          # (M, 3, 2)
        mean, M2 = tri_moments(q, np)
        wgt = f * _tri_areas(x, t)
        m1 += wgt @ mean
        m2 += np.einsum("m,mij->ij", wgt, M2)
        zone = np.any(pv > 0, axis=1)
        data.append((q[zone], ((x[t[zone]] - origin) @ axis), pv[zone]))
    e2 = _major_axis(m2)
    if e2 @ m1 < 0:
        e2 = -e2
    return e2 @ basis, [(q @ e2, u, p) for q, u, p in data]


def _major_axis(m2):
    th = 0.5 * math.atan2(2 * m2[0, 1], m2[0, 0] - m2[1, 1])
    return np.array([math.cos(th), math.sin(th)])


def _union_length(sample, lo, hi, K):
    """Total length (K,) of the union of intervals [lo, hi] grouped by sample id."""
    keep = hi > lo
    sample, lo, hi = sample[keep], lo[keep], hi[keep]
    if sample.size == 0:
        return np.zeros(K)
    span = 2.0 * (hi.max() - lo.min()) + 1.0
    order = np.lexsort((lo, sample))
    s, lo, hi = sample[order], lo[order], hi[order]
    off = s * span
    run = np.maximum.accumulate(hi + off)
    prev = np.concatenate([[-np.inf], run[:-1]]) - off
    return np.bincount(s, np.maximum(0.0, hi - np.maximum(lo, prev)), minlength=K)


def _directed_lengths(wv, uv, pv, samples):
    """H (K,) of one directed zone at sorted samples: union of chord parts with phi > 0."""
    K = samples.shape[0]
    if wv.shape[0] == 0:
        return np.zeros(K)
    a = np.searchsorted(samples, wv.min(axis=1), "left")
    b = np.searchsorted(samples, wv.max(axis=1), "right")
    cnt = np.maximum(b - a, 0)
    z = np.repeat(np.arange(wv.shape[0]), cnt)
    k = a[z] + np.arange(z.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    hit, u1, u2, p1, p2 = chords(wv[z], uv[z], pv[z], samples[k], np)
    first = p1 >= p2
    us, uo = np.where(first, u1, u2), np.where(first, u2, u1)
    ps, po = np.where(first, p1, p2), np.where(first, p2, p1)
    end = us + seg_fraction(ps, po, None, np) * (uo - us)
    lo, hi = np.minimum(us, end), np.maximum(us, end)
    return _union_length(k[hit], lo[hit], hi[hit], K)


def _breakpoints(wv, pv):
    """w of the clipped polygons' vertices (vertices and level crossings on edges)."""
    w1, p1 = np.roll(wv, -1, axis=1), np.roll(pv, -1, axis=1)
    cross = (pv > 0) != (p1 > 0)
    t = np.where(cross, pv / np.where(cross, pv - p1, 1.0), 0.0)
    return np.concatenate([wv.ravel(), (wv + t * (w1 - wv))[cross]])


def _pair_heights(x, topo, phi, axis, origin, w, n_w, at, exact_max):
    """Curves on w, values (P, len(at)) at the points `at`, and with exact_max the
    maximum of each pair's H over w, `at` and all breakpoints (w >= 0) and its w."""
    basis = perp_basis(axis)
    dirs, data = [], []
    for pair in topo.pairs:
        e, d = _direction(x, topo, pair, phi, axis, origin, basis)
        dirs.append(e)
        data.append(d)
    if w is None:
        wmax = max([float(np.max(wv)) for d in data for wv, _, _ in d if wv.size] + [0.0])
        w = np.linspace(0.0, wmax, int(n_w))
    w = np.asarray(w, dtype=np.float64).ravel()
    at = np.asarray(at, dtype=np.float64).ravel()
    P = len(topo.pairs)
    Hd, Hat = np.zeros((P, 2, w.size)), np.zeros((P, at.size))
    hmax, hw = np.zeros(P), np.zeros(P)
    for p, d in enumerate(data):
        samples = [w, at] + ([_breakpoints(wv, pv) for wv, _, pv in d] if exact_max else [])
        S = np.unique(np.concatenate(samples))
        HS = np.stack([_directed_lengths(wv, uv, pv, S) for wv, uv, pv in d])   # (2, |S|)
        Hd[p] = HS[:, np.searchsorted(S, w)]
        Hat[p] = HS[:, np.searchsorted(S, at)].mean(axis=0)
        if exact_max:
            Hm = np.where(S >= 0, HS.mean(axis=0), -np.inf)
            k = int(np.argmax(Hm))
            hmax[p], hw[p] = max(Hm[k], 0.0), S[k]
    curves = PairCurves(np.array(topo.pairs, dtype=np.int64).reshape(-1, 2),
                        np.array(dirs).reshape(-1, 3), w, Hd.mean(axis=1), Hd)
    return curves, Hat, hmax, hw


def pair_height_curves(x, topo, phi, axis, origin, w=None, n_w=201):
    """`PairCurves` (mm) on the grid w (default n_w points on [0, max zone w]); phi from
    `level_values`, topo from `topology.topology`, axis unit (3,), origin (3,)."""
    return _pair_heights(x, topo, phi, axis, origin, w, n_w, [], False)[0]


# ------------------------------------------------------------------------------ driver
def coaptation_metrics(x, triangles, body, ref, free_edge, *, axis, origin, annulus_level,
                       g_c=0.5, w_cc=5.0, w=None, n_w=201) -> CoaptationResult:
    """Sharp coaptation characteristics of a closed valve (see `CoaptationResult`).

    x (N, 3) mm deformed nodes; triangles (M, 3) int; body (N,) leaflet ids 0..L-1
    (L >= 2); ref (N, 2) template coordinates (mm); free_edge (N,) bool; axis (3,) valve
    axis aorta -> ventricle; origin (3,) a point on it; annulus_level: axial coordinate
    s0 (mm) of the annulus plane; g_c (mm) coaptation distance; w_cc (mm) the C-C
    distance; w (K,) sample positions for the pair curves (default n_w on [0, w_max]).
    """
    x = check_x(x)
    g_c = check_positive("g_c", g_c)
    w_cc = check_positive("w_cc", w_cc)
    axis, origin, s0 = check_frame(axis, origin, annulus_level)
    topo = topology(triangles, body, free_edge, x.shape[0])
    ref = np.asarray(ref, dtype=np.float64)
    if ref.shape != (x.shape[0], 2) or not np.all(np.isfinite(ref)):
        raise MeshError(f"ref must be finite with shape ({x.shape[0]}, 2); got {ref.shape}")
    phi, gap = level_values(x, topo, g_c)

    # areas
    fr = zone_fractions(phi, topo)
    area = np.array([_tri_areas(x, t).sum() for t in topo.tris])
    zone = np.array([(_tri_areas(x, t) * f).sum() for t, f in zip(topo.tris, fr)])
    zone_flat = np.array([(_tri_areas(ref, t) * f).sum() for t, f in zip(topo.tris, fr)])
    fel = np.array([np.linalg.norm(x[s[:, 1]] - x[s[:, 0]], axis=1).sum()
                    for s in topo.free])
    ncca, h_avr = zone / area, zone / fel

    # pair heights
    curves, Hat, hmax, hw = _pair_heights(x, topo, phi, axis, origin, w, n_w, [w_cc], True)
    kp = int(np.argmax(hmax))
    cc = Hat[:, 0]

    # central zone
    pts, wts = central_candidates(x, phi, central_index(topo), None, np)
    u = (pts - origin) @ axis
    inside = wts > 0
    if np.any(inside):
        ui = u[inside]
        crange = (float(ui.min()), float(ui.max()))
        h_c = crange[1] - crange[0]
        cpoint = pts[inside][int(np.argmin(ui))]
        from_fe = False
    else:
        crange, h_c, from_fe = (math.nan, math.nan), 0.0, True
        segs = np.concatenate(topo.free)
        c, r = free_edge_closest(x, segs, axis, origin, np)
        cpoint = c[int(np.argmin(r))]
    h_e = s0 - float((cpoint - origin) @ axis)

    return CoaptationResult(
        g_c=g_c, w_cc=w_cc, annulus_level=s0, area=area, zone_area=zone,
        zone_area_flat=zone_flat, free_edge_length=fel, ncca=ncca, h_avr=h_avr,
        ncca_valve=float(ncca.mean()), h_avr_valve=float(h_avr.mean()), curves=curves,
        h=float(hmax[kp]), h_pair_index=kp, h_w=float(hw[kp]), h_cc=float(cc.mean()),
        h_cc_pair=cc, h_c=float(h_c), central_range=crange, h_e=float(h_e),
        central_point=cpoint, h_e_from_free_edge=from_fe,
        profile=coaptation_profile(ref, phi, topo), gap=gap)
