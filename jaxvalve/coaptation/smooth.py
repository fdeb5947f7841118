"""Smooth (differentiable, jit-able) coaptation metrics for gradient-based optimisation.

Build a `SmoothPlan` once on the host (`smooth_plan`, NumPy: candidate node-triangle pairs,
per-leaflet index sets, the w grid), then evaluate any metric as a pure jax.numpy function
of the positions x (N, 3) mm:  ``smooth_metrics(x, plan, eps, temperature)``.

Smoothing (eps, T in mm; T defaults to eps):
* distances: exact point-triangle distances (`contact.geometry.point_triangle_distance`),
  hard minimum over the candidate triangles of each other leaflet (C1 across shared
  edges), clamped at plan.clamp = g_c + eps_max + longest edge + skin, which is exact for
  every triangle that can reach the soft zone;
* zone indicator: H_eps(phi) = S(phi / eps), S the C2 biweight step (0 below -eps, 1 above
  +eps), integrated exactly over each triangle (areas, mid-plane moments) or chord (H);
* max / min: log-sum-exp with temperature T; h over the plan's w grid and the pairs;
  the extremes of the central zone are weighted soft maxima over its candidate points
  (`central_zone`), normalised by the total weight W so they lie within the candidates' range.

Sharp limit (eps, T -> 0): zone areas, NCCA, h_avr, H_ij(w) and h_cc tend to the sharp
values (O(eps^2) for areas where the level set is regular); h tends to the maximum of the
sharp H over the grid plan.w (+ at most T log(P K)); h_c and h_E to the sharp values
(errors O(eps) + O(T log W)).  H is the sum of chord lengths over triangles (the sharp one
is the union): they agree when each directed zone projects one-to-one onto its mid-plane.
For h_E the central point is blended with the free-edge fallback by
lambda(W) = smoothstep(min(W, 1)), W the total candidate weight (>= 1 when the sharp
three-leaflet zone is non-empty).

The plan stays valid while no node moves more than skin / 2 from plan.x0 (`plan_valid`)
and eps <= eps_max.  Python-level checks (eps, temperature > 0, eps <= eps_max) run when
they are concrete numbers; traced inputs are not checked (a NaN anywhere in x makes
every output NaN).
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np
import jax
import jax.numpy as jnp

from ..contact.geometry import point_triangle_distance
from ..errors import ParameterError, check_positive
from .central_zone import central_candidates, central_index, free_edge_closest
from .level_sets import chords, seg_fraction, tri_fraction, tri_moments
from .topology import check_frame, check_x, max_edge_length, perp_basis, topology
from .gaps import candidate_pairs

__all__ = ["SmoothPlan", "smooth_plan", "plan_valid", "smooth_metrics", "smooth_gap_field",
           "smooth_zone_area", "smooth_ncca", "smooth_h_avr", "smooth_pair_heights",
           "smooth_h", "smooth_h_cc", "smooth_h_c", "smooth_h_e"]

_DATA = ["x0", "tri", "tbody", "dz_tri", "dz_col", "dz_id", "central", "free", "free_leaf",
         "cand_node", "cand_tri", "cand_slot", "w", "axis", "origin", "basis",
         "annulus_level", "g_c", "w_cc", "clamp"]


@functools.partial(jax.tree_util.register_dataclass, data_fields=_DATA,
                   meta_fields=["n_nodes", "n_leaflets", "pairs", "triples", "eps_max", "skin",
                                "w_band"])
@dataclasses.dataclass(frozen=True)
class SmoothPlan:
    """Static data of the smooth metrics (a pytree; index arrays are int32 leaves).

    x0 (N, 3) build positions (mm); tri (M, 3) with leaflet tbody (M,).  Directed zones
    d = 0..2P-1 ((i, j) then (j, i) for each pair): triangles dz_tri (Z, 3) of the first
    leaflet, the other leaflet dz_col (Z,) and the zone id dz_id (Z,).  central: flat
    candidate index arrays of the three-leaflet zone (`central_zone.central_index`).  free
    (F, 2) free-edge segments of leaflet free_leaf (F,).  Candidate rows cand_node,
    cand_tri, cand_slot (= node * L + leaflet of the triangle; padding slot N * L).  w (K,)
    grid of the pair curves; axis, origin, basis (2, 3) of the plane normal to the axis;
    annulus_level, g_c, w_cc, clamp (mm).  Static (meta): n_nodes, n_leaflets, pairs,
    triples (tuples of leaflet ids), eps_max, skin (mm, Python floats); w_band: the most
    grid lines of w one triangle can span while the plan is valid (0: w is not
    increasing, every line meets every triangle in the computation).
    """

    x0: jax.Array
    tri: jax.Array
    tbody: jax.Array
    dz_tri: jax.Array
    dz_col: jax.Array
    dz_id: jax.Array
    central: tuple
    free: jax.Array
    free_leaf: jax.Array
    cand_node: jax.Array
    cand_tri: jax.Array
    cand_slot: jax.Array
    w: jax.Array
    axis: jax.Array
    origin: jax.Array
    basis: jax.Array
    annulus_level: jax.Array
    g_c: jax.Array
    w_cc: jax.Array
    clamp: jax.Array
    n_nodes: int
    n_leaflets: int
    pairs: tuple
    triples: tuple
    eps_max: float
    skin: float
    w_band: int = 0


def smooth_plan(x0, triangles, body, free_edge, *, axis, origin, annulus_level, g_c=0.5,
                w_cc=5.0, eps_max=0.1, skin=0.5, w=None, n_w=64, capacity=None,
                w_band=None) -> SmoothPlan:
    """Build the `SmoothPlan` at positions x0 (N, 3) mm (host side, NumPy).

    eps_max (mm): largest smoothing width to be used; skin (mm): allowed motion (nodes may
    move up to skin / 2); w (K,) grid of the pair curves, default n_w points on
    [0, max distance of a node from the axis + skin]; capacity: length of the padded
    candidate arrays (default: the count rounded up to 1024); w_band: the lines of w met
    per triangle (default: the most a triangle can span while the plan is valid; not used
    when w is not increasing, where every line meets every triangle).  Plans
    of equal capacity and w_band share compiled metric functions; a capacity below the
    count or a w_band below that bound raises `ParameterError`."""
    x0 = check_x(x0, name="x0")
    g_c = check_positive("g_c", g_c)
    w_cc = check_positive("w_cc", w_cc)
    eps_max = check_positive("eps_max", eps_max)
    skin = check_positive("skin", skin)
    a, o, s0 = check_frame(axis, origin, annulus_level)
    topo = topology(triangles, body, free_edge, x0.shape[0])
    n, L = x0.shape[0], topo.n_leaflets
    longest = max_edge_length(x0, topo.tri)
    clamp = g_c + eps_max + longest + skin
    rows, cols = candidate_pairs(x0, topo.tri, topo.body, clamp + 2.0 * skin)
    slot = rows * L + topo.tbody[cols]
    cap = max(1024, -(-rows.size // 1024) * 1024) if capacity is None else int(capacity)
    if cap < rows.size:
        raise ParameterError(f"capacity must be >= the {rows.size} candidate pairs of this "
                             f"plan; got {cap}")
    pad = cap - rows.size
    rows = np.concatenate([rows, np.zeros(pad, np.int64)])
    cols = np.concatenate([cols, np.zeros(pad, np.int64)])
    slot = np.concatenate([slot, np.full(pad, n * L, np.int64)])
    if w is None:
        v = x0 - o
        r = np.linalg.norm(v - (v @ a)[:, None] * a, axis=1)
        w = np.linspace(0.0, float(r.max()) + skin, int(n_w))
    w = np.asarray(w, dtype=np.float64)
    if w.ndim != 1 or w.size == 0 or not np.all(np.isfinite(w)):
        raise ParameterError(f"w must be a non-empty 1D array of finite positions (mm); "
                             f"got shape {w.shape}")
    # a triangle's extent in w is below its longest edge, below longest + skin while the
    # plan is valid (nodes within skin / 2 of x0): it spans at most `band` lines of w
    dw = np.diff(w)
    band = 0
    if w.size > 1 and np.all(dw > 0):
        band = int(min(w.size, np.floor((longest + skin) / dw.min()) + 2))
        if w_band is not None:
            if not (isinstance(w_band, (int, np.integer)) and band <= w_band):
                raise ParameterError(f"w_band must be an integer >= {band} (the grid lines "
                                     f"a triangle of this plan can span); got {w_band!r}")
            band = int(min(w.size, w_band))
    dirs = [d for i, j in topo.pairs for d in ((i, j), (j, i))]
    dz_tri = np.concatenate([topo.tris[i] for i, _ in dirs] + [np.zeros((0, 3), np.int64)])
    dz_col = np.concatenate([np.full(len(topo.tris[i]), j) for i, j in dirs] + [[]])
    dz_id = np.concatenate([np.full(len(topo.tris[i]), d) for d, (i, _) in enumerate(dirs)]
                           + [[]])
    free = np.concatenate(topo.free)
    free_leaf = np.concatenate([np.full(f.shape[0], k) for k, f in enumerate(topo.free)])
    i32 = lambda v: jnp.asarray(v, dtype=jnp.int32)  # noqa: E731
    f64 = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
    return SmoothPlan(
        x0=f64(x0), tri=i32(topo.tri), tbody=i32(topo.tbody), dz_tri=i32(dz_tri),
        dz_col=i32(dz_col), dz_id=i32(dz_id),
        central=tuple(i32(v) for v in central_index(topo)), free=i32(free),
        free_leaf=i32(free_leaf), cand_node=i32(rows), cand_tri=i32(cols),
        cand_slot=i32(slot), w=f64(w), axis=f64(a), origin=f64(o),
        basis=f64(perp_basis(a)), annulus_level=f64(s0), g_c=f64(g_c), w_cc=f64(w_cc),
        clamp=f64(clamp), n_nodes=n, n_leaflets=L, pairs=topo.pairs,
        triples=topo.triples, eps_max=eps_max, skin=skin, w_band=band)


def plan_valid(plan: SmoothPlan, x) -> bool:
    """Host check: True while every node is within skin / 2 of its build position."""
    d = np.linalg.norm(np.asarray(x) - np.asarray(plan.x0), axis=1)
    return bool(np.max(d) < 0.5 * float(plan.skin))


def _check_eps(plan, eps, temperature):
    for name, v in (("eps", eps), ("temperature", temperature)):
        if isinstance(v, (int, float, np.number, np.ndarray)):
            val = check_positive(name, v)
            if name == "eps" and val > float(plan.eps_max) * (1 + 1e-12):
                raise ParameterError(f"eps must be in (0, eps_max = {float(plan.eps_max)}] "
                                     f"mm for this plan; got {val} (rebuild the plan with "
                                     "a larger eps_max)")
    return eps if temperature is None else temperature


def _nan_through(fn):
    """Make every output NaN when x holds a NaN (the safe norms and masks below would
    otherwise turn a NaN node into a finite area or chord)."""
    @functools.wraps(fn)
    def wrapped(x, plan, *args, **kw):
        out = fn(x, plan, *args, **kw)
        bad = jnp.any(jnp.isnan(x))
        return jax.tree_util.tree_map(lambda v: jnp.where(bad, jnp.nan, v), out)
    return wrapped


# ------------------------------------------------------------------------------ fields
def _norm(v):
    q = jnp.sum(v * v, axis=-1)
    return jnp.where(q > 0, jnp.sqrt(jnp.where(q > 0, q, 1.0)), 0.0)


def _areas(x, t):
    """Areas (...) mm^2 of triangles t (..., 3) (0 for degenerate ones)."""
    xt = x[t]
    return 0.5 * _norm(jnp.cross(xt[..., 1, :] - xt[..., 0, :], xt[..., 2, :] - xt[..., 0, :]))


@_nan_through
def smooth_gap_field(x, plan: SmoothPlan):
    """Distances (N, L) mm from each node to each leaflet, clamped at plan.clamp (own
    leaflet and nodes without candidates -> clamp).  Differentiable in x (`_gap_field`)."""
    return _gap_field(x, plan)


def _gap_field(x, plan):
    """`smooth_gap_field` without the NaN check (its callers make it).

    The minimum over the candidates is found without derivatives; the distance is then
    recomputed, with them, for the nearest candidate of each (node, leaflet) only: the
    same values and (where the nearest triangle is unique) the same gradient as a
    differentiated minimum, with a backward pass over N L pairs instead of every
    candidate (330 000 at h = 0.88 mm)."""
    n, L = plan.n_nodes, plan.n_leaflets
    S, C = n * L + 1, plan.cand_node.shape[0]

    def dist(rows, xx):
        t = plan.tri[plan.cand_tri[rows]]
        return jax.vmap(point_triangle_distance)(xx[plan.cand_node[rows]], xx[t[:, 0]],
                                                 xx[t[:, 1]], xx[t[:, 2]])[0]

    d = dist(jnp.arange(C), jax.lax.stop_gradient(x))
    dmin = jax.ops.segment_min(d, plan.cand_slot, num_segments=S)
    first = jax.ops.segment_min(jnp.where(d <= dmin[plan.cand_slot], jnp.arange(C), C),
                                plan.cand_slot, num_segments=S)[: n * L]
    found = first < C
    g = jnp.where(found, dist(jnp.where(found, first, 0), x), jnp.inf)
    return jnp.minimum(g.reshape(n, L), plan.clamp)


def _phi(x, plan):
    return plan.g_c - _gap_field(x, plan)


def _zone(x, plan, phi, eps):
    """Cusp areas (L,), zone areas (L,) mm^2 and free-edge lengths (L,) mm."""
    L = plan.n_leaflets
    pmax = jnp.max(phi, axis=1)
    A = _areas(x, plan.tri)
    f = tri_fraction(pmax[plan.tri], eps, jnp)
    seg = _norm(x[plan.free[:, 1]] - x[plan.free[:, 0]])
    return (jax.ops.segment_sum(A, plan.tbody, num_segments=L),
            jax.ops.segment_sum(A * f, plan.tbody, num_segments=L),
            jax.ops.segment_sum(seg, plan.free_leaf, num_segments=L))


@_nan_through
def smooth_zone_area(x, plan: SmoothPlan, eps):
    """Soft coaptation area (L,) mm^2 of each leaflet (deformed)."""
    _check_eps(plan, eps, None)
    return _zone(x, plan, _phi(x, plan), eps)[1]


@_nan_through
def smooth_ncca(x, plan: SmoothPlan, eps):
    """(NCCA per leaflet (L,), valve mean ()) - dimensionless."""
    _check_eps(plan, eps, None)
    area, zone, _ = _zone(x, plan, _phi(x, plan), eps)
    return zone / area, jnp.mean(zone / area)


@_nan_through
def smooth_h_avr(x, plan: SmoothPlan, eps):
    """(h_avr per leaflet (L,), valve mean ()) in mm."""
    _check_eps(plan, eps, None)
    _, zone, fel = _zone(x, plan, _phi(x, plan), eps)
    return zone / fel, jnp.mean(zone / fel)


# ------------------------------------------------------------------------------ heights
def _major_axis(m2):
    """Unit major axes (P, 2) of symmetric 2x2 moments m2 (P, 2, 2)."""
    a, b = m2[:, 0, 0] - m2[:, 1, 1], 2.0 * m2[:, 0, 1]
    ok = (a != 0) | (b != 0)
    th = 0.5 * jnp.arctan2(jnp.where(ok, b, 0.0), jnp.where(ok, a, 1.0))
    return jnp.stack([jnp.cos(th), jnp.sin(th)], axis=-1)


def _directed(x, plan, phi, eps):
    """Projected data of the directed-zone triangles: w, u, phi, each (Z, 3)."""
    D = 2 * len(plan.pairs)
    t = plan.dz_tri
    pv = phi[t, plan.dz_col[:, None]]
    rel = x[t] - plan.origin
    q = rel @ plan.basis.T                                         # (Z, 3, 2)
    mean, M2 = tri_moments(q, jnp)
    wgt = tri_fraction(pv, eps, jnp) * _areas(x, t)                # (Z,)
    m1 = jax.ops.segment_sum(wgt[:, None] * mean, plan.dz_id, num_segments=D)
    m2 = jax.ops.segment_sum(wgt[:, None, None] * M2, plan.dz_id, num_segments=D)
    m1 = m1.reshape(-1, 2, 2).sum(axis=1)                          # (P, 2)
    e2 = _major_axis(m2.reshape(-1, 2, 2, 2).sum(axis=1))         # (P, 2)
    e2 = jnp.where(jnp.sum(e2 * m1, axis=-1, keepdims=True) < 0, -e2, e2)
    e = e2[plan.dz_id // 2]                                        # (Z, 2)
    return jnp.einsum("zki,zi->zk", q, e), rel @ plan.axis, pv


def _heights(x, plan, phi, eps, w, directed=None):
    """H (P, K) mm at positions w (K,): mean of the two directed chord sums.
    directed: `_directed`'s output when the caller has it."""
    if not plan.pairs:
        return jnp.zeros((0, w.shape[0]))
    wv, uv, pv = _directed(x, plan, phi, eps) if directed is None else directed
    hit, u1, u2, p1, p2 = chords(wv, uv, pv, w[:, None], jnp)     # (K, Z)
    c = jnp.where(hit, jnp.abs(u2 - u1) * seg_fraction(p1, p2, eps, jnp), 0.0)
    H = jax.ops.segment_sum(c.T, plan.dz_id, num_segments=2 * len(plan.pairs))
    return H.reshape(-1, 2, w.shape[0]).mean(axis=1)


def _grid_heights(x, plan, phi, eps, directed=None):
    """H (P, K) mm on the plan's grid plan.w, as `_heights`, but each triangle meets only
    the plan.w_band lines from the first at or above its smallest w (the others miss
    it): Z x w_band chords instead of Z x K.  NaN if a triangle spans more lines (the
    plan is used beyond its validity)."""
    K = plan.w.shape[0]
    if not plan.pairs or plan.w_band == 0:
        return _heights(x, plan, phi, eps, plan.w, directed)
    wv, uv, pv = _directed(x, plan, phi, eps) if directed is None else directed
    wq = jax.lax.stop_gradient(wv)
    k0 = jnp.searchsorted(plan.w, jnp.min(wq, axis=1), side="left")          # (Z,)
    span = jnp.searchsorted(plan.w, jnp.max(wq, axis=1), side="right") - k0
    k = k0[:, None] + jnp.arange(plan.w_band)                                # (Z, B)
    ok = k < K
    k = jnp.where(ok, k, K - 1)
    hit, u1, u2, p1, p2 = chords(wv[:, None, :], uv[:, None, :], pv[:, None, :],
                                 plan.w[k], jnp)
    c = jnp.where(hit & ok, jnp.abs(u2 - u1) * seg_fraction(p1, p2, eps, jnp), 0.0)
    D = 2 * len(plan.pairs)
    H = jnp.zeros((D, K), c.dtype).at[jnp.broadcast_to(plan.dz_id[:, None], k.shape), k].add(c)
    H = jnp.where(jnp.any(span > plan.w_band), jnp.nan, H)
    return H.reshape(-1, 2, K).mean(axis=1)


@_nan_through
def smooth_pair_heights(x, plan: SmoothPlan, eps, w=None):
    """Soft pair height curves H (P, K) mm on w (default plan.w), pairs plan.pairs."""
    _check_eps(plan, eps, None)
    if w is None:
        return _grid_heights(x, plan, _phi(x, plan), eps)
    return _heights(x, plan, _phi(x, plan), eps, jnp.asarray(w))


def _lse_max(v, T):
    return T * jax.nn.logsumexp(v / T)


@_nan_through
def smooth_h(x, plan: SmoothPlan, eps, temperature=None):
    """Soft maximal coaptation height h (mm): T logsumexp(H / T) over pairs and plan.w."""
    T = _check_eps(plan, eps, temperature)
    return _lse_max(_grid_heights(x, plan, _phi(x, plan), eps), T)


@_nan_through
def smooth_h_cc(x, plan: SmoothPlan, eps):
    """Soft h_C-C (mm): mean over pairs of H_ij(w_cc)."""
    _check_eps(plan, eps, None)
    return jnp.mean(_heights(x, plan, _phi(x, plan), eps, plan.w_cc[None]))


def _central(x, plan, phi, eps, T):
    """(soft min u, soft max u, total weight W) of the three-leaflet zone (mm, mm, -)."""
    if not plan.triples:
        z = jnp.zeros(())
        return z, z, z
    pts, wts = central_candidates(x, phi, plan.central, eps, jnp)
    u = (pts - plan.origin) @ plan.axis
    W = jnp.sum(wts)
    ok = W > 0
    b = jnp.where(ok, wts, 1.0)
    logW = jnp.log(jnp.sum(b))
    ubar = jnp.sum(b * jnp.where(b > 0, u, 0.0)) / jnp.sum(b)
    u = jnp.where(b > 0, u, ubar)          # zero-weight candidates may lie anywhere
    umax = T * (jax.nn.logsumexp(u / T, b=b) - logW)
    umin = -T * (jax.nn.logsumexp(-u / T, b=b) - logW)
    return jnp.where(ok, umin, 0.0), jnp.where(ok, umax, 0.0), W


@_nan_through
def smooth_h_c(x, plan: SmoothPlan, eps, temperature=None):
    """Soft central coaptation height h_c (mm): soft axial extent of the three-leaflet
    zone (0 when its total candidate weight is 0, and always for L = 2)."""
    T = _check_eps(plan, eps, temperature)
    umin, umax, _ = _central(x, plan, _phi(x, plan), eps, T)
    return umax - umin


def _h_e(x, plan, central, T):
    umin, _, W = central
    c, r = free_edge_closest(x, plan.free, plan.axis, plan.origin, jnp)
    p = jax.nn.softmax(-r / T)
    u_fe = p @ ((c - plan.origin) @ plan.axis)
    s = jnp.clip(W, 0.0, 1.0)
    lam = s * s * (3.0 - 2.0 * s)
    return plan.annulus_level - (lam * umin + (1.0 - lam) * u_fe)


@_nan_through
def smooth_h_e(x, plan: SmoothPlan, eps, temperature=None):
    """Soft effective height h_E (mm): annulus_level - soft-min u of the three-leaflet
    zone, blended with the free-edge point nearest the axis when that zone vanishes."""
    T = _check_eps(plan, eps, temperature)
    return _h_e(x, plan, _central(x, plan, _phi(x, plan), eps, T), T)


@_nan_through
def smooth_metrics(x, plan: SmoothPlan, eps, temperature=None) -> dict:
    """All smooth metrics at once (one gap-field evaluation); jit-able.

    Returns a dict of jnp arrays: area, zone_area, free_edge_length, ncca, h_avr (L,);
    ncca_valve, h_avr_valve, h, h_cc, h_c, h_e (); H (P, K) on plan.w."""
    T = _check_eps(plan, eps, temperature)
    phi = _phi(x, plan)
    area, zone, fel = _zone(x, plan, phi, eps)
    directed = _directed(x, plan, phi, eps) if plan.pairs else None
    H = _grid_heights(x, plan, phi, eps, directed)
    h_cc = jnp.mean(_heights(x, plan, phi, eps, plan.w_cc[None], directed))
    central = _central(x, plan, phi, eps, T)
    return dict(area=area, zone_area=zone, free_edge_length=fel, ncca=zone / area,
                h_avr=zone / fel, ncca_valve=jnp.mean(zone / area),
                h_avr_valve=jnp.mean(zone / fel), H=H, h=_lse_max(H, T),
                h_cc=h_cc, h_c=central[1] - central[0],
                h_e=_h_e(x, plan, central, T))
