"""The barrier's pair lists inside jit (`jaxvalve.contact.pairs`) against a brute force on
the host, their overflow flag and growth, and the chunked barrier forces
(`jaxvalve.contact.barrier.forces`) against autodiff of the pair energies."""
import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.contact import pairs as pair_lists
from jaxvalve.contact.barrier import BarrierContact, collision_weights, forces
from jaxvalve.contact.geometry import point_triangle_distance_np
from jaxvalve.errors import ParameterError
from jaxvalve.geometry.mesh import unique_edges
from sheets import combine, grid_sheet

CUTOFF = 0.45


def _bodies(seed=0, n=6, L=3.0):
    """Two crumpled sheets 0.25 mm apart and a third folded over the first: pairs of
    different bodies and of one body (the fold) within the cutoff."""
    rng = np.random.default_rng(seed)
    sheets = []
    for k in range(2):
        p, t = grid_sheet(n, L, z=0.25 * k, jitter=0.15, rng=rng, flip=bool(k))
        p[:, 2] += 0.08 * np.sin(1.3 * p[:, 0] + k) * np.cos(0.9 * p[:, 1])
        sheets.append((p, t))
    x, tri, body = combine(*sheets)
    # the template: each sheet flat, far apart (the self-contact gap is measured there)
    ref = x.copy()
    ref[:, 2] = 0.0
    ref[body == 1, 0] += 10.0
    return x, tri, body, ref


def _seg_seg_np(a0, a1, b0, b1):
    """Distance between two segments by dense sampling then refinement (reference)."""
    s = np.linspace(0, 1, 201)
    P = a0 + s[:, None] * (a1 - a0)
    Q = b0 + s[:, None] * (b1 - b0)
    d = np.linalg.norm(P[:, None] - Q[None], axis=-1)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    from scipy.optimize import minimize
    f = lambda st: np.sum((a0 + st[0] * (a1 - a0) - b0 - st[1] * (b1 - b0)) ** 2)
    r = minimize(f, [s[i], s[j]], bounds=[(0, 1), (0, 1)], method="L-BFGS-B",
                 options=dict(ftol=1e-15, gtol=1e-12))
    return np.sqrt(r.fun)


def _brute(x, tri, body, ref, cutoff, gap):
    """Every point-triangle and edge-edge pair within cutoff, by loops: no shared node,
    and of one body only where their template balls are gap apart."""
    edges, _ = unique_edges(tri)
    ball = lambda rows: (ref[rows].mean(0), np.max(np.linalg.norm(ref[rows] - ref[rows].mean(0), axis=1)))
    pt, ee = set(), set()
    for p in range(len(x)):
        for t in tri:
            if p in t:
                continue
            if body[p] == body[t[0]]:
                c, r = ball(t)
                if np.linalg.norm(ref[p] - c) < gap + r:
                    continue
            d = float(point_triangle_distance_np(x[p][None], *(x[t][k][None] for k in range(3)))[0])
            if d < cutoff:
                pt.add((p,) + tuple(t))
    for e, f in itertools.combinations(range(len(edges)), 2):
        a, b = edges[e], edges[f]
        if set(a) & set(b):
            continue
        if body[a[0]] == body[b[0]]:
            (ca, ra), (cb, rb) = ball(a), ball(b)
            if np.linalg.norm(ca - cb) < gap + ra + rb:
                continue
        # quick reject by bounding boxes, then the reference distance
        if np.min(np.linalg.norm(x[a][:, None] - x[b][None], axis=-1)) > cutoff + 1.0:
            continue
        if _seg_seg_np(*x[a], *x[b]) < cutoff:
            ee.add(frozenset((tuple(a), tuple(b))))
    return pt, ee


def _listed(pl):
    n_pt, n_ee = int(pl.n_pt), int(pl.n_ee)
    pt = {tuple(r) for r in np.asarray(pl.pt)[:n_pt].tolist()}
    ee = {frozenset((tuple(r[:2]), tuple(r[2:]))) for r in np.asarray(pl.ee)[:n_ee].tolist()}
    return pt, ee, n_pt, n_ee


def _canon_pt(pt, tri):
    """Point-triangle rows keyed by (p, sorted triangle) (the list keeps the mesh's order)."""
    return {(r[0],) + tuple(sorted(r[1:])) for r in pt}


def test_in_jit_lists_equal_the_brute_force():
    x, tri, body, ref = _bodies()
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x, self_gap=0.4)
    lists, caps = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), CUTOFF, 0.0, 0.0)
    pt, ee, n_pt, n_ee = _listed(lists.cand)
    assert len(pt) == n_pt and len(ee) == n_ee            # no row listed twice
    want_pt, want_ee = _brute(x, tri, body, ref, CUTOFF, 0.4)
    assert len(want_pt) > 20 and len(want_ee) > 20
    assert _canon_pt(pt, tri) == _canon_pt(want_pt, tri)
    assert ee == want_ee


def test_self_pairs_follow_the_template_gap():
    """A sheet folded onto itself: pairs of one body are listed where their template balls
    lie self_gap apart, never between template neighbours."""
    p, t = grid_sheet(8, 4.0)
    ref = p.copy()
    x = p.copy()
    fold = x[:, 0] > 2.0                              # fold the right half over the left
    x[fold, 0] = 4.0 - x[fold, 0]
    x[fold, 2] = 0.3
    body = np.zeros(len(x), np.int64)
    topo = pair_lists.contact_topology(t, body, np.zeros(len(x), bool), x, self_gap=1.2)
    lists, _ = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), CUTOFF, 0.0, 0.0)
    pt, ee, n_pt, n_ee = _listed(lists.cand)
    want_pt, want_ee = _brute(x, t, body, ref, CUTOFF, 1.2)
    assert n_pt > 10 and _canon_pt(pt, t) == _canon_pt(want_pt, t) and ee == want_ee


def test_overflow_is_flagged_and_allocate_grows_the_capacities():
    x, tri, body, ref = _bodies()
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x, self_gap=0.4)
    small = pair_lists.Capacities(pt=16, ee=16, raw_pt=64, raw_ee=64, scan_pt=256,
                                  scan_ee=256, act_pt=16, act_ee=16, table=16384)
    lists = pair_lists.start(topo, jnp.asarray(ref), jnp.asarray(x), small, CUTOFF, 0.0, 0.0)
    assert pair_lists.overflowed(lists, small)
    with pytest.raises(Exception, match="overflowed their capacities"):
        pair_lists.check_overflow(lists, small)
    grown, caps = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), CUTOFF, 0.0,
                                      0.0, caps=small)
    assert not pair_lists.overflowed(grown, caps) and caps.pt > small.pt
    full, _ = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), CUTOFF, 0.0, 0.0)
    assert _listed(grown.cand)[:2] == _listed(full.cand)[:2]


def test_min_distance_is_the_smallest_pair_distance():
    x, tri, body, ref = _bodies()
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x, self_gap=0.4)
    d = pair_lists.min_distance(topo, jnp.asarray(ref), x, cutoff=CUTOFF)
    up = body == 1
    lo = ~up
    brute = min(float(point_triangle_distance_np(x[p][None], *(x[t][k][None] for k in range(3)))[0])
                for p in np.flatnonzero(up) for t in tri[np.all(lo[tri], axis=1)])
    assert 0 < d <= brute + 1e-12


def test_chunked_forces_equal_autodiff_and_obey_newtons_third_law():
    """`barrier.forces` (hand-written gradients, a chunk of rows at a time) against
    jax.grad of the typed closed forms over the same list; the forces of a rigid-motion
    invariant energy sum to zero and carry no torque."""
    x, tri, body, ref = _bodies()
    law = BarrierContact(dhat=0.3)
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x, self_gap=0.4)
    lists, _ = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), 0.3, 0.0, 0.0)
    w = collision_weights(jnp.asarray(ref), topo.triangles, topo.tri_edge, int(topo.n_edges))
    X = jnp.asarray(x)
    E, g, dmin, stiff = forces(law, X, lists.act, w)
    assert int(lists.act.n_pt) > 10 and int(lists.act.n_ee) > 10
    from jaxvalve.contact.barrier import pair_weights
    act = lists.act
    pt_w, ee_w, eps = pair_weights(*w, act.pt[:, 0], act.ee_id)
    pt_w = jnp.where(act.pt_valid, pt_w, 0.0)
    ee_w = jnp.where(act.ee_valid, ee_w, 0.0)
    keep = lambda r, ok: jnp.where(ok[:, None], r, r[:1])
    E2, g2 = jax.value_and_grad(lambda y: law.energy_pairs(
        y, keep(act.pt, act.pt_valid), pt_w, keep(act.ee, act.ee_valid), ee_w, eps))(X)
    scale = float(jnp.abs(g2).sum())
    assert scale > 0
    np.testing.assert_allclose(float(E), float(E2), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g2), atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(g).sum(0), 0.0, atol=1e-12 * scale)
    torque = np.cross(x - x.mean(0), np.asarray(g)).sum(0)
    np.testing.assert_allclose(torque, 0.0, atol=1e-10 * scale)
    # dmin: each listed node's smallest pair distance, never below the true one
    assert float(jnp.min(dmin)) > 0 and np.isfinite(float(jnp.min(dmin)))


def test_under_vmap_every_member_takes_a_refresh_that_one_member_needs():
    """A batch refreshes its pair lists when any member needs it, and every member takes
    the refreshed lists (built at its own state); alone, a member that has moved less
    than the skin allows keeps its lists."""
    x, tri, body, ref = _bodies()
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x, self_gap=0.4)
    dhat, skin, margin = 0.3, 0.4, 0.1              # rebuilt after 0.15 mm, re-selected after 0.05
    _, caps = pair_lists.allocate(topo, jnp.asarray(ref), jnp.asarray(x), dhat + skin, 0.0, 0.0)
    X = jnp.asarray(x)
    start = jax.vmap(lambda y: pair_lists.start(topo, jnp.asarray(ref), y, caps, dhat, skin,
                                                margin))
    lists = start(jnp.stack([X, X]))
    still = X.at[:, 2].add(0.01)                    # member 0: moved 0.01 mm, needs nothing
    moved = X.at[3, 2].add(0.2)                     # member 1: one node moved 0.2 mm
    update = lambda l, y: pair_lists.update(l, topo, jnp.asarray(ref), y, caps)
    new = jax.vmap(update)(lists, jnp.stack([still, moved]))
    np.testing.assert_array_equal(np.asarray(new.cand.x_build), np.stack([still, moved]))
    np.testing.assert_array_equal(np.asarray(new.act.x_build), np.stack([still, moved]))
    fresh = pair_lists.start(topo, jnp.asarray(ref), still, caps, dhat, skin, margin)
    member0 = jax.tree_util.tree_map(lambda a: a[0], new)
    assert _listed(member0.cand)[:2] == _listed(fresh.cand)[:2]
    assert _listed(member0.act)[:2] == _listed(fresh.act)[:2]
    alone = update(jax.tree_util.tree_map(lambda a: a[0], lists), still)
    np.testing.assert_array_equal(np.asarray(alone.cand.x_build), x)
    np.testing.assert_array_equal(np.asarray(alone.act.x_build), x)


@pytest.mark.parametrize("cell", [0.6, 1.5])
def test_capacities_for_a_mesh_hold_two_coapted_sheets(cell):
    """Two sheets pressed 0.05 mm apart over their whole area, as coapted leaflets are:
    the capacities `Capacities.for_mesh` sizes from the mesh's edge length and the lists'
    cutoffs hold every pair (no overflow) at a fine and a coarse mesh, and grow per node
    as the edges shorten."""
    n = int(round(9.0 / cell))
    rng = np.random.default_rng(1)
    a = grid_sheet(n, 9.0, jitter=0.1, rng=rng)
    b = grid_sheet(n, 9.0, z=0.05, origin=(0.3 * cell, 0.4 * cell), jitter=0.1, rng=rng,
                   flip=True)
    x, tri, body = combine(a, b)
    ref = x.copy()
    ref[body == 1, 0] += 20.0
    topo = pair_lists.contact_topology(tri, body, np.zeros(len(x), bool), x)
    assert topo.edge_len == pytest.approx(cell * (2 + np.sqrt(2)) / 3, rel=0.1)
    caps = pair_lists.Capacities.for_mesh(topo, 0.2, 1.0, 0.2)
    lists = pair_lists.start(topo, jnp.asarray(ref), jnp.asarray(x), caps, 0.2, 1.0, 0.2)
    assert int(lists.act.n_pt) > len(x) // 2           # the sheets are in contact
    assert not pair_lists.overflowed(lists, caps)
    per_node = caps.pt / len(x)
    coarse = pair_lists.Capacities.for_mesh(
        dataclasses.replace(topo, edge_len=2 * topo.edge_len), 0.2, 1.0, 0.2)
    assert coarse.pt / len(x) < 0.7 * per_node


def test_a_topology_of_coincident_nodes_is_refused_naming_x0():
    """Edges of zero mean length give the pair lists no scale: a clear error, before any
    list is built."""
    p, t = grid_sheet(3, 1.0)
    with pytest.raises(ParameterError, match="x0 gives the mesh's edges a mean length"):
        pair_lists.contact_topology(t, np.zeros(len(p), np.int64), np.zeros(len(p), bool),
                                    np.zeros_like(p))
