"""Tests for jaxvalve.coaptation: sharp metrics with known answers, invariances, mesh
refinement, and the smooth versions (limit eps -> 0, gradients vs finite differences).

Frame: axis (0, 0, -1), origin 0, so the axial coordinate is u = -z; annulus level 10 mm.
Hand-built sheets are "extruded" along the axis, with template coordinates (s, u).
"""
import json
import math

import numpy as np
import pytest
import jax
import jax.numpy as jnp

from jaxvalve.contact.geometry import point_triangle_distance_np
from jaxvalve.errors import MeshError, ParameterError
from jaxvalve.coaptation import (annulus_level, coaptation_metrics, gap_field,
                                 smooth_gap_field, smooth_h, smooth_h_avr, smooth_h_c,
                                 smooth_h_cc, smooth_h_e, smooth_metrics, smooth_ncca,
                                 smooth_pair_heights, smooth_plan, smooth_zone_area)
from jaxvalve.coaptation.smooth import plan_valid

KW = dict(axis=(0.0, 0.0, -1.0), origin=(0.0, 0.0, 0.0), annulus_level=10.0)
G_C = 0.5
EPS = (0.1, 0.03, 0.01, 0.003)


# ------------------------------------------------------------------ mesh builders
def grid(P, R):
    """Structured sheet from grid points P (n, m, 3), template coords R (n, m, 2)."""
    n, m = P.shape[:2]
    idx = np.arange(n * m).reshape(n, m)
    t = []
    for i in range(n - 1):
        for j in range(m - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            t += [[a, b, c], [a, c, d]] if (i + j) % 2 == 0 else [[a, b, d], [b, c, d]]
    return P.reshape(-1, 3), np.array(t), R.reshape(-1, 2)


def leaflet(P, R, free_u):
    x, t, r = grid(P, R)
    return x, t, r, np.isclose(-x[:, 2], free_u)


def combine(leaflets):
    """[(x, t, ref, free)] per leaflet (each may be a list of parts) -> valve arrays."""
    xs, ts, bs, rs, fs, off = [], [], [], [], [], 0
    for k, parts in enumerate(leaflets):
        for x, t, r, f in (parts if isinstance(parts, list) else [parts]):
            xs.append(x)
            ts.append(t + off)
            bs.append(np.full(len(x), k))
            rs.append(r)
            fs.append(f)
            off += len(x)
    return (np.concatenate(xs), np.concatenate(ts), np.concatenate(bs),
            np.concatenate(rs), np.concatenate(fs))


def flat_sheet(ws, us, y):
    """Sheet in the plane y (mm), x in ws, u in us; free edge = the row u = min(us)."""
    W, U = np.meshgrid(ws, us, indexing="ij")
    return leaflet(np.stack([W, np.full_like(W, y), -U], -1), np.stack([W, U], -1), us.min())


def parallel_pair(delta, us_a=None, us_b=None, ws=None):
    """A at y = +delta/2 (u in [0, 6]), B at y = -delta/2 (u in [-2, 4]); x in [2, 8]."""
    ws = np.linspace(2.0, 8.0, 7) if ws is None else ws
    us_a = np.array([0, 1, 2, 3, 4, 4.4, 5, 6.0]) if us_a is None else us_a
    us_b = np.array([-2, -1, -0.4, 0, 1, 2, 3, 4.0]) if us_b is None else us_b
    return combine([flat_sheet(ws, us_a, delta / 2), flat_sheet(ws, us_b, -delta / 2)])


TILT_A, TILT_B = 0.1, 0.1     # B: y = -(a + b u): its gap to A grows linearly with u
U_A = (G_C * math.sqrt(1 + TILT_B**2) - TILT_A) / TILT_B   # zone of A: u < U_A
U_B = (G_C - TILT_A) / TILT_B                               # zone of B: u < U_B


def tilted_pair(nu_a=7, nu_b=7, nw=6):
    ws = np.linspace(2.0, 8.0, nw + 1)
    A = flat_sheet(ws, np.linspace(0.0, 6.0, nu_a), 0.0)
    W, U = np.meshgrid(ws, np.linspace(0.0, 6.0, nu_b), indexing="ij")
    P = np.stack([W, -(TILT_A + TILT_B * U), -U], -1)
    B = leaflet(P, np.stack([W, U * math.sqrt(1 + TILT_B**2)], -1), 0.0)
    return combine([A, B])


def v_leaflet(k, delta, wing, us, nw, rho=0.0):
    """Leaflet k of a Y (Mercedes star) with arms at 90, 210, 330 degrees: a V of two
    wings parallel to the arms bounding sector k, offset by delta/2 into the sector (so
    facing wings of neighbours are delta apart and the three V tips form an equilateral
    triangle of side delta around the axis).  rho > 0 cuts the tip off (a central gap)."""
    th1, th2 = np.radians(90 + 120 * k), np.radians(210 + 120 * k)
    bis = 0.5 * (th1 + th2)
    tip = delta / math.sqrt(3) * np.array([math.cos(bis), math.sin(bis)])
    d1 = np.array([math.cos(th1), math.sin(th1)])
    d2 = np.array([math.cos(th2), math.sin(th2)])
    if rho == 0:      # one strip, template coordinate s < 0 along d1, s > 0 along d2
        s = np.linspace(-wing, wing, 2 * nw + 1)
        strips = [(tip + np.where(s[:, None] < 0, -s[:, None] * d1, s[:, None] * d2), s)]
    else:             # two strips starting rho from the tip
        s = np.linspace(rho, wing, nw + 1)
        strips = [(tip + s[::-1, None] * d1, -s[::-1]), (tip + s[:, None] * d2, s)]
    parts = []
    for xy, sc in strips:
        S, U = np.meshgrid(sc, us, indexing="ij")
        P = np.concatenate([np.repeat(xy[:, None], len(us), 1), -U[..., None]], -1)
        parts.append(leaflet(P, np.stack([S, U], -1), us.min()))
    return parts


US0 = np.array([0, 0.6, 1, 2, 3, 4.5, 6.0])   # leaflet 0 starts 1 mm above the others
US12 = np.array([1, 2, 3, 4.5, 6.0])


def ystar(delta=0.3, rho=(0.0, 0.0, 0.0), nw=6):
    return combine([v_leaflet(0, delta, 8.0, US0, nw, rho[0]),
                    v_leaflet(1, delta, 8.0, US12, nw, rho[1]),
                    v_leaflet(2, delta, 8.0, US12, nw, rho[2])])


def metrics(cfg, **kw):
    x, t, b, r, f = cfg
    return coaptation_metrics(x, t, b, r, f, **{**KW, **kw})


# ------------------------------------------------------------------ sharp: known answers
def test_parallel_sheets_known_zone_and_heights():
    # overlap u in [0, 4]; each sheet's zone runs sqrt(g_c^2 - delta^2) = 0.4 mm past the
    # other's edge (A: to u = 4.4; B: to u = -0.4): 6 mm x 4.4 mm each
    res = metrics(parallel_pair(0.3))
    np.testing.assert_allclose(res.zone_area, [26.4, 26.4], rtol=1e-12)
    np.testing.assert_allclose(res.zone_area_flat, [26.4, 26.4], rtol=1e-12)
    np.testing.assert_allclose(res.area, [36.0, 36.0], rtol=1e-12)
    np.testing.assert_allclose(res.free_edge_length, [6.0, 6.0], rtol=1e-12)
    np.testing.assert_allclose(res.ncca, [26.4 / 36] * 2, rtol=1e-12)
    np.testing.assert_allclose(res.h_avr, [4.4, 4.4], rtol=1e-12)
    assert res.ncca_valve == pytest.approx(26.4 / 36) and res.h_avr_valve == pytest.approx(4.4)
    c = res.curves
    np.testing.assert_allclose(np.abs(c.direction[0]), [1, 0, 0], atol=1e-12)
    inside = (c.w > 2 + 1e-9) & (c.w < 8 - 1e-9)
    np.testing.assert_allclose(c.H[0, inside], 4.4, rtol=1e-12)
    np.testing.assert_allclose(c.H_directed[0, :, inside], 4.4, rtol=1e-12)
    assert np.all(c.H[0, (c.w < 2 - 1e-9) | (c.w > 8 + 1e-9)] == 0)
    assert res.h == pytest.approx(4.4, rel=1e-12) and res.h_cc == pytest.approx(4.4, rel=1e-12)
    assert res.h_c == 0 and res.h_e_from_free_edge
    # profile: A's zone boundary is the template line u = 4.4, B's u = -0.4 (6 mm each),
    # oriented with the zone on the left
    for prof, u_line, zone_side in zip(res.profile, (4.4, -0.4), (-1, 1)):
        np.testing.assert_allclose(prof[:, :, 1], u_line, atol=1e-12)
        d = prof[:, 1] - prof[:, 0]
        assert np.sum(np.linalg.norm(d, axis=1)) == pytest.approx(6.0)
        assert np.all(np.sign(d[:, 0]) == zone_side)   # left normal (-d_u, d_s) -> zone


def test_far_sheets_have_no_coaptation():
    res = metrics(parallel_pair(1.0))
    assert np.all(res.zone_area == 0) and np.all(res.ncca == 0) and np.all(res.h_avr == 0)
    assert np.all(res.curves.H == 0) and res.h == 0 and res.h_cc == 0 and res.h_c == 0
    assert all(p.shape == (0, 2, 2) for p in res.profile)
    assert np.all(res.gap[np.isfinite(res.gap)] >= 1.0 - 1e-12)


def test_tilted_sheets_linear_gap_is_clipped_exactly():
    res = metrics(tilted_pair())
    sec = math.sqrt(1 + TILT_B**2)
    np.testing.assert_allclose(res.zone_area, [6 * U_A, 6 * U_B * sec], rtol=1e-12)
    np.testing.assert_allclose(res.area, [36.0, 36.0 * sec], rtol=1e-12)
    np.testing.assert_allclose(res.h_avr, [U_A, U_B * sec], rtol=1e-12)
    c = res.curves
    inside = (c.w > 2.2) & (c.w < 7.8)
    np.testing.assert_allclose(c.H_directed[0, 0, inside], U_A, rtol=1e-12)
    np.testing.assert_allclose(c.H_directed[0, 1, inside], U_B, rtol=1e-12)
    assert res.h == pytest.approx((U_A + U_B) / 2, rel=1e-12)
    assert res.h_cc == pytest.approx((U_A + U_B) / 2, rel=1e-12)
    # no three-leaflet zone for L = 2: h_E from the free-edge point nearest the axis,
    # A's corner (2, 0, 0) at u = 0
    assert res.h_c == 0 and res.h_e_from_free_edge
    np.testing.assert_allclose(res.central_point, [2, 0, 0], atol=1e-12)
    assert res.h_e == pytest.approx(10.0)
    np.testing.assert_allclose(res.profile[0][:, :, 1], U_A, atol=1e-12)


def test_mesh_refinement():
    # linear distance field: the clipped area is exact on any mesh
    for nu in (4, 7, 10, 19):
        res = metrics(tilted_pair(nu_a=nu, nu_b=nu + 2, nw=3))
        np.testing.assert_allclose(res.zone_area, [6 * U_A, 6 * U_B * 1.004987562112089],
                                   rtol=1e-12)
    # nonlinear field past the other sheet's edge (d = sqrt(delta^2 + s^2)): converges
    err = []
    for n in (7, 13, 25, 49):
        ws = np.linspace(2.0, 8.0, 3)
        cfg = parallel_pair(0.3, np.linspace(0, 6, n), np.linspace(-2, 4, n), ws)
        err.append(abs(metrics(cfg).zone_area[0] - 26.4))
    assert all(e2 < e1 / 2.5 for e1, e2 in zip(err, err[1:])), err
    assert err[-1] < 0.01


def test_ystar_central_zone():
    res = metrics(ystar())
    # leaflet 0 reaches 1 mm above the others; near the tips its points stay within g_c of
    # both other leaflets down to u = 1 - sqrt(g_c^2 - delta^2) = 0.6; all end at u = 6
    assert not res.h_e_from_free_edge
    assert res.central_range == pytest.approx((0.6, 6.0), abs=1e-12)
    assert res.h_c == pytest.approx(5.4, abs=1e-12)
    assert res.h_e == pytest.approx(10.0 - 0.6, abs=1e-12)
    np.testing.assert_allclose(res.zone_area, [16 * 5.4, 16 * 5.0, 16 * 5.0], rtol=1e-12)
    # pairs (0,1), (0,2): (5.4 + 5.0) / 2; pair (1,2): 5.0 (wings of 8 mm reach w = 5)
    np.testing.assert_allclose(res.h_cc_pair, [5.2, 5.2, 5.0], rtol=1e-12)
    assert res.h == pytest.approx(5.2, rel=1e-12)
    dirs = np.degrees(np.arctan2(res.curves.direction[:, 1], res.curves.direction[:, 0]))
    np.testing.assert_allclose(np.mod(dirs, 360), [210, 90, 330], atol=0.5)


def test_central_gap_falls_back_to_free_edge():
    # tips cut off: no point is within g_c of both other leaflets; leaflet 0's cut is the
    # smallest, so its free-edge corner at radius rho0 (u = 0) is nearest the axis
    res = metrics(ystar(rho=(0.8, 1.0, 1.0)))
    assert res.h_c == 0 and res.h_e_from_free_edge and math.isnan(res.central_range[0])
    assert res.h_e == pytest.approx(10.0)
    assert res.h_cc == pytest.approx((5.2 + 5.2 + 5.0) / 3, rel=1e-12)


def _rotation(rng):
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def _summary(res):
    return np.r_[res.zone_area, res.area, res.ncca, res.h_avr, res.h, res.h_cc, res.h_c,
                 res.h_e, res.curves.H.ravel()]


@pytest.mark.parametrize("cfg", [tilted_pair(), ystar()], ids=["tilted", "ystar"])
def test_rigid_motion_invariance(cfg):
    x, t, b, r, f = cfg
    w = np.linspace(0.0, 9.0, 31)
    ref = metrics(cfg, w=w)
    rng = np.random.default_rng(0)
    R, c = _rotation(rng), rng.uniform(-5, 5, 3)
    moved = coaptation_metrics(x @ R.T + c, t, b, r, f, axis=R @ np.array(KW["axis"]),
                               origin=R @ np.array(KW["origin"]) + c,
                               annulus_level=KW["annulus_level"], w=w)
    np.testing.assert_allclose(_summary(moved), _summary(ref), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(moved.curves.direction, ref.curves.direction @ R.T,
                               atol=1e-9)
    for p1, p2 in zip(moved.profile, ref.profile):
        _same_polyline(p1, p2)


def _same_polyline(s1, s2, tol=1e-9):
    """Segment sets (K, 2, 2) covering the same curve (a boundary through a node may be
    split differently when rounding puts the node on either side)."""
    def length(s):
        return np.linalg.norm(s[:, 1] - s[:, 0], axis=1).sum()

    def dist(p, s):     # distance of points p (P, 2) to the segments s
        a, d = s[:, 0], s[:, 1] - s[:, 0]
        t = np.clip(np.einsum("pkj,kj->pk", p[:, None] - a, d)
                    / np.maximum(np.sum(d * d, 1), 1e-300), 0, 1)
        return np.min(np.linalg.norm(p[:, None] - a - t[..., None] * d, axis=-1), axis=1)

    assert abs(length(s1) - length(s2)) < tol
    if len(s1) == 0 or len(s2) == 0:
        assert len(s1) == len(s2)
        return
    for a, b in ((s1, s2), (s2, s1)):
        for f in (0.0, 0.3, 1.0):
            assert np.all(dist(a[:, 0] + f * (a[:, 1] - a[:, 0]), b) < tol)


def test_relabelling_invariance():
    x, t, b, r, f = ystar()
    perm = np.array([2, 0, 1])            # leaflet k becomes perm[k]
    res = metrics((x, t, b, r, f))
    new = metrics((x, t, perm[b], r, f))
    inv = np.argsort(perm)
    np.testing.assert_allclose(new.zone_area, res.zone_area[inv], rtol=1e-12)
    np.testing.assert_allclose(new.h_avr, res.h_avr[inv], rtol=1e-12)
    for name in ("ncca_valve", "h_avr_valve", "h", "h_cc", "h_c", "h_e"):
        assert getattr(new, name) == pytest.approx(getattr(res, name), rel=1e-12), name
    np.testing.assert_allclose(np.sort(new.h_cc_pair), np.sort(res.h_cc_pair), rtol=1e-12)


def test_gap_field_matches_brute_force():
    x, t, b, _, _ = ystar()
    rng = np.random.default_rng(1)
    x = x + 0.05 * rng.standard_normal(x.shape)
    exact = gap_field(x, t, b)
    tb = b[t[:, 0]]
    for j in range(3):
        tj = t[tb == j]
        verts = (np.tile(x[tj[:, k]], (len(x), 1)) for k in range(3))
        d = point_triangle_distance_np(np.repeat(x, len(tj), 0), *verts)
        ref = d.reshape(len(x), len(tj)).min(axis=1)
        ref[b == j] = np.inf
        np.testing.assert_allclose(exact[:, j], ref, rtol=1e-12)
    cut = gap_field(x, t, b, cutoff=0.7)
    np.testing.assert_array_equal(np.isinf(cut), ~(exact < 0.7))
    np.testing.assert_allclose(cut[exact < 0.7], exact[exact < 0.7], rtol=1e-12)


def test_annulus_level_and_result_dict():
    x, t, b, r, f = ystar()
    sutured = np.isclose(np.abs(r[:, 0]), 8.0)           # outer wing ends
    assert annulus_level(x, sutured, b, KW["axis"], KW["origin"]) == pytest.approx(6.0)
    d = metrics(ystar(rho=(0.8, 1.0, 1.0))).as_dict()
    text = json.dumps(d)                                  # plain types only
    assert d["central_range"] == [None, None] and "gap" not in d
    assert json.loads(text)["curves"]["pairs"] == [[0, 1], [0, 2], [1, 2]]
    assert len(metrics(ystar()).as_dict(include_gap=True)["gap"]) == len(x)


def test_bad_inputs():
    x, t, b, r, f = tilted_pair()
    ok = dict(KW)
    with pytest.raises(MeshError, match=r"x must have shape"):
        coaptation_metrics(x[:, :2], t, b, r, f, **ok)
    xn = x.copy()
    xn[3, 1] = np.nan
    with pytest.raises(MeshError, match="non-finite"):
        coaptation_metrics(xn, t, b, r, f, **ok)
    with pytest.raises(ParameterError, match="g_c"):
        coaptation_metrics(x, t, b, r, f, g_c=0.0, **ok)
    with pytest.raises(ParameterError, match="w_cc"):
        coaptation_metrics(x, t, b, r, f, w_cc=-1.0, **ok)
    with pytest.raises(ParameterError, match="axis"):
        coaptation_metrics(x, t, b, r, f, **{**ok, "axis": (0, 0, 0)})
    with pytest.raises(ParameterError, match="annulus_level"):
        coaptation_metrics(x, t, b, r, f, **{**ok, "annulus_level": np.nan})
    with pytest.raises(MeshError, match="L >= 2"):
        coaptation_metrics(x, t, np.zeros_like(b), r, f, **ok)
    bad = b.copy()
    bad[t[0, 0]] = 1 - bad[t[0, 0]]
    with pytest.raises(MeshError, match="different leaflets"):
        coaptation_metrics(x, t, bad, r, f, **ok)
    with pytest.raises(MeshError, match="free-edge"):
        coaptation_metrics(x, t, b, r, np.zeros_like(f), **ok)
    with pytest.raises(MeshError, match="ref"):
        coaptation_metrics(x, t, b, r[:, :1], f, **ok)
    with pytest.raises(MeshError, match="indices"):
        coaptation_metrics(x, t + len(x), b, r, f, **ok)


# ------------------------------------------------------------------ smooth versions
_metrics = jax.jit(smooth_metrics)
SCALARS = ("ncca_valve", "h_avr_valve", "h", "h_cc", "h_c", "h_e")


def _scalars(x, plan, eps):
    m = smooth_metrics(x, plan, eps)
    return jnp.stack([m[k] for k in SCALARS] + list(m["zone_area"]))


def _sharp_values(res, plan, cfg):
    """Sharp references: h is the max of the sharp H over the plan's grid."""
    from jaxvalve.coaptation.sharp import level_values, pair_height_curves
    from jaxvalve.coaptation.topology import topology
    x, t, b, _, f = cfg
    topo = topology(t, b, f, len(x))
    phi, _ = level_values(x, topo, G_C)
    H = pair_height_curves(x, topo, phi, np.array(KW["axis"]), np.array(KW["origin"]),
                           w=np.asarray(plan.w)).H
    return np.r_[res.ncca_valve, res.h_avr_valve, H.max(), res.h_cc, res.h_c, res.h_e,
                 res.zone_area], H


@pytest.mark.parametrize("cfg", [tilted_pair(), ystar()], ids=["tilted", "ystar"])
def test_smooth_tends_to_sharp(cfg):
    """Errors shrink monotonically as eps -> 0 and end below tolerances set by the
    smoothing.  Areas: the soft zone differs from the sharp one in a band of width ~eps
    along its boundary; the first-order terms cancel (symmetric kernel) except where the
    boundary runs through nodes (here: the Y's row u = 0.6), leaving ~eps * (boundary
    length 2 mm) * O(0.1) / (area 86 mm^2) ~ 1e-5..1e-4 relative at eps = 3e-3 (tol 5e-4).
    Heights: log-sum-exp maxima exceed the max by at most T log(#candidates) =
    0.003 * ln(~2000) = 0.023 mm, and the soft central zone reaches ~eps / |grad phi| ~
    1.25 eps beyond the sharp one (tol 0.05 mm; h_cc and H have no soft max: 0.02 mm)."""
    x, t, b, r, f = cfg
    res = metrics(cfg)
    plan = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37))
    sharp, H = _sharp_values(res, plan, cfg)
    far = np.asarray(plan.w) >= 1.0     # H near w = 0 may overlap itself (sum vs union)
    errs = []
    for eps in EPS:
        m = _metrics(x, plan, eps)
        v = np.r_[[float(m[k]) for k in SCALARS], np.asarray(m["zone_area"])]
        e = np.abs(v - sharp)
        e[:2] /= np.abs(sharp[:2]) + 1e-300
        e[6:] /= sharp[6:]
        errs.append(np.r_[e, np.max(np.abs(np.asarray(m["H"]) - H)[:, far])])
    errs = np.array(errs)
    assert np.all(np.diff(errs, axis=0) <= 1e-12), errs
    tol = np.r_[5e-4, 5e-4, 0.05, 0.02, 0.05, 0.05, [5e-4] * (len(sharp) - 6), 0.02]
    assert np.all(errs[-1] <= tol), (errs[-1], tol)


def test_smooth_gradients_match_finite_differences():
    x, t, b, r, f = ystar()
    rng = np.random.default_rng(2)
    x = x + 0.02 * rng.standard_normal(x.shape)       # break symmetric ties
    plan = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37))
    eps = 0.05
    J = np.asarray(jax.jit(jax.jacrev(_scalars))(x, plan, eps))
    assert np.all(np.isfinite(J)) and np.all(np.abs(J).sum(axis=(1, 2)) > 0)

    def fwd(x):                                      # reuses the compiled _metrics
        m = _metrics(x, plan, eps)
        return np.r_[[float(m[k]) for k in SCALARS], np.asarray(m["zone_area"])]

    h = 1e-6
    for _ in range(2):
        v = rng.standard_normal(x.shape)
        fd = (fwd(x + h * v) - fwd(x - h * v)) / (2 * h)
        np.testing.assert_allclose(np.einsum("kij,ij->k", J, v), fd, rtol=1e-5, atol=1e-7)


def test_smooth_individual_functions_and_plan():
    x, t, b, r, f = tilted_pair()
    plan = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37))
    eps = 0.01

    def each(x, plan, eps):
        return dict(zone_area=smooth_zone_area(x, plan, eps),
                    ncca=smooth_ncca(x, plan, eps)[0], ncca_valve=smooth_ncca(x, plan, eps)[1],
                    h_avr_valve=smooth_h_avr(x, plan, eps)[1],
                    H=smooth_pair_heights(x, plan, eps), h=smooth_h(x, plan, eps),
                    h_cc=smooth_h_cc(x, plan, eps), h_c=smooth_h_c(x, plan, eps),
                    h_e=smooth_h_e(x, plan, eps), gap=smooth_gap_field(x, plan))

    got = jax.jit(each)(x, plan, eps)
    ref = _metrics(x, plan, eps)
    for k in got:
        if k != "gap":
            np.testing.assert_allclose(got[k], ref[k], rtol=1e-12, atol=1e-12, err_msg=k)
    exact = gap_field(x, t, b)
    near = exact < float(plan.clamp)
    np.testing.assert_allclose(np.asarray(got["gap"])[near], exact[near], rtol=1e-12)
    assert np.all(np.asarray(got["gap"])[~near] == pytest.approx(float(plan.clamp)))
    assert plan_valid(plan, x + [0.2, 0, 0]) and not plan_valid(plan, x + [0.3, 0, 0])
    with pytest.raises(ParameterError, match="eps"):
        smooth_h(x, plan, 0.0)
    with pytest.raises(ParameterError, match="eps_max"):
        smooth_metrics(x, plan, 0.2)
    with pytest.raises(ParameterError, match="temperature"):
        smooth_h_c(x, plan, 0.01, temperature=-1.0)
    with pytest.raises(MeshError, match="non-finite"):
        smooth_plan(np.full_like(x, np.nan), t, b, f, **KW)
    with pytest.raises(ParameterError, match="skin"):
        smooth_plan(x, t, b, f, **KW, skin=0.0)


def test_banded_grid_heights_equal_every_line_against_every_triangle():
    """`_grid_heights` meets each triangle with plan.w_band lines only; on the Y star
    its curves and their gradient equal those of all K lines against all triangles
    (`_heights`), a plan used beyond its validity gives NaN instead of missing chords,
    and a NaN node, wherever it is, makes every metric NaN."""
    from jaxvalve.coaptation.smooth import _grid_heights, _heights, _lse_max, _phi
    x, t, b, r, f = ystar()
    x = x + 0.02 * np.random.default_rng(5).standard_normal(x.shape)
    plan = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37))
    assert 2 <= plan.w_band < 37
    eps = 0.05

    def dense(x, plan, phi, eps):
        return _heights(x, plan, phi, eps, plan.w)

    # jitted (plan is a pytree with static fields: one program per plan layout); op by op
    # these gradients took most of a minute on a 2-core VM
    curves = jax.jit(lambda fn, x, plan: fn(x, plan, _phi(x, plan), eps), static_argnums=0)
    grad_h = jax.jit(jax.grad(lambda x, fn: _lse_max(fn(x, plan, _phi(x, plan), eps), eps)),
                     static_argnums=1)
    np.testing.assert_allclose(curves(_grid_heights, x, plan), curves(dense, x, plan),
                               rtol=0, atol=1e-13)
    g_band, g_all = grad_h(x, _grid_heights), grad_h(x, dense)
    assert np.max(np.abs(g_all)) > 0
    np.testing.assert_allclose(g_band, g_all, rtol=0, atol=1e-13)
    roomy = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37),
                        w_band=plan.w_band + 5)     # shared programs: a fixed, larger band
    assert roomy.w_band == plan.w_band + 5
    np.testing.assert_allclose(curves(_grid_heights, x, roomy), curves(dense, x, plan),
                               rtol=0, atol=1e-13)
    with pytest.raises(ParameterError, match="w_band"):
        smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37), w_band=plan.w_band - 1)
    wide = smooth_plan(x, t, b, f, **KW, w=np.linspace(-40.0, 40.0, 321))
    o = np.asarray(KW["origin"], float)
    stretched = o + 4.0 * (np.asarray(x, float) - o)   # triangles 4x wider: beyond the plan
    assert not np.isnan(curves(_grid_heights, x, wide)).any()
    assert np.all(np.isnan(curves(_grid_heights, stretched, wide)))
    gap = jax.jit(lambda x: smooth_gap_field(x, plan))
    soft_h = jax.jit(lambda x: smooth_h(x, plan, eps))
    for node in (0, 3, len(x) // 2):          # a NaN node far from, or in, the zones
        bad = np.asarray(x, float).copy()
        bad[node, 0] = np.nan
        assert np.all(np.isnan(np.asarray(gap(bad))))
        m = _metrics(bad, plan, eps)
        assert all(np.all(np.isnan(np.asarray(v))) for v in m.values()), node
        assert np.isnan(float(soft_h(bad)))


def _triangle_index(T):
    """`central_index` layout for T triangles of leaflet 0 (nodes 3t..3t+2), triple (0; 1, 2),
    with no node or edge candidates."""
    e = np.zeros((0,), np.int64)
    tris = np.arange(3 * T, dtype=np.int64).reshape(T, 3)
    return (e, e, e, np.zeros((0, 2), np.int64), e, e, tris, np.ones(T, np.int64),
            np.full(T, 2, np.int64))


@pytest.mark.parametrize("sharp", [False, True])
def test_central_candidates_drop_coinciding_level_lines(sharp):
    # phi_k = c phi_j on a triangle: the two level lines coincide (or the zones are
    # disjoint), so there is no interior intersection point.  cv = fx x fy is then only
    # rounding error, and cv / sum(cv) once gave weights up to 0.89 and derivatives
    # ~1e18-1e20 (compiled code contracts a*b - c*d into FMAs, so even fx x fx != 0).
    from jaxvalve.coaptation.central_zone import central_candidates

    rng = np.random.default_rng(1)
    T = 64
    f = rng.uniform(-0.08, 0.08, size=3 * T)
    c = np.repeat(rng.choice([1.0, 0.7, -2.0, 3.1], size=T), 3)
    phi = np.stack([f, f, c * f], axis=1)
    x = rng.normal(size=(3 * T, 3))
    idx = _triangle_index(T)
    if sharp:
        _, w = central_candidates(x, phi, idx, None, np)
        assert np.all(w == 0)
        return

    def total(phi):
        p, w = central_candidates(jnp.asarray(x), phi, idx, 0.1, jnp)
        return jnp.sum(p * jnp.arange(1.0, 4.0)) + jnp.sum(w)

    _, w = jax.jit(lambda phi: central_candidates(jnp.asarray(x), phi, idx, 0.1, jnp))(phi)
    assert np.all(np.asarray(w) == 0)
    g = np.asarray(jax.jit(jax.grad(total))(jnp.asarray(phi)))
    with jax.disable_jit():
        g_op = np.asarray(jax.grad(total)(jnp.asarray(phi)))
    assert np.all(g == 0) and np.all(g_op == 0)
    # a generic pair of fields keeps its interior points, compiled as op by op
    phi2 = phi.copy()
    phi2[:, 2] = rng.uniform(-0.08, 0.08, size=3 * T)
    p2, w2 = jax.jit(lambda phi: central_candidates(jnp.asarray(x), phi, idx, 0.1, jnp))(phi2)
    with jax.disable_jit():
        p2_op, w2_op = central_candidates(jnp.asarray(x), jnp.asarray(phi2), idx, 0.1, jnp)
    assert np.count_nonzero(np.asarray(w2)) > 0
    np.testing.assert_allclose(np.asarray(w2), np.asarray(w2_op), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(p2), np.asarray(p2_op), rtol=1e-9, atol=1e-9)


def test_central_candidates_gradient_is_finite_where_step_values_tie():
    """Far from a leaflet the gap is clamped, so phi takes one value at every node of a
    triangle and its three step values tie.  The weights' gradient there is finite and
    the same at XLA's LLVM optimisation levels 0 and 3 (with max - min reductions it was
    NaN at level 0 on 15-25 entries of this case, and on 24 of the smooth h_E's gradient
    on the h = 2.5 mm benchmark valve)."""
    from jaxvalve.coaptation.central_zone import central_candidates, _spread3

    x, t, b, r, f = ystar()
    plan = smooth_plan(x, t, b, f, **KW, w=np.linspace(0.0, 9.0, 37))
    rng = np.random.default_rng(0)
    phi = rng.uniform(-0.3, 0.3, (x.shape[0], 3))
    phi[rng.random(phi.shape) < 0.5] = plan.g_c - plan.clamp
    phi = jnp.asarray(phi)

    def weights(p):
        return jnp.sum(central_candidates(jnp.asarray(x), p, plan.central, 0.1, jnp)[1][:10])

    grads = [np.asarray(jax.jit(jax.grad(weights)).lower(phi).compile(
        compiler_options={"xla_backend_optimization_level": lvl})(phi)) for lvl in (0, 3)]
    assert np.all(np.isfinite(grads[0])) and np.abs(grads[0]).sum() > 0
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-12, atol=1e-14)
    v = rng.uniform(-1, 1, (50, 3))
    np.testing.assert_allclose(_spread3(v, np), v.max(-1) - v.min(-1), rtol=0, atol=4e-16)
