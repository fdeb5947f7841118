"""Contact benchmark: the previous flat pair list against the dense chunked layout.

For each configuration, the time (ms per call, best of --repeat batches, after
compilation) of

* rebuild:  the broad phase (`build_neighbours`, capacities fixed as in a solve),
* energy:   `SmoothContact(one_sided=True).energy`,
* E+grad:   its value and gradient (what a force evaluation costs),

for the previous implementation (a frozen copy below: 27-cell x cell_capacity dense scan,
flat pair list, segment_min) and the current one, then the exponent b of a fit
t ~ M^b over each family of meshes (M = triangles).  Families:

* valve:   the benchmark valve (3 leaflets) at its placed (open) position, mesh sizes
           --valve-h; few pairs (the leaflets barely touch);
* sheets:  three wavy sheets 0.19 mm apart, triangles ~0.87 mm, --sheets n x n cells:
           every node is in contact, pairs grow like M (the worst case of a closed
           valve's coaptation zone);
* --state: a saved (N, 3) state of the valve at --state-h (e.g. a closed valve).

The cutoff is gap + skin = 0.2 + 1.0 mm, as in `equilibrium.solve`.

    python benchmarks/contact.py [--valve-h 1.3,0.87,0.6] [--sheets 24,34,48]
                                 [--state x_closed.npy --state-h 0.87] [--repeat 5]
"""
from __future__ import annotations

import argparse
import functools
import itertools
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxvalve import contact as C  # noqa: E402
from jaxvalve.contact.geometry import point_triangle_distance  # noqa: E402

CUTOFF = 1.2  # mm: SmoothContact().gap + equilibrium.DEFAULT_SKIN


# --------------------------------------------------- previous implementation (frozen)
_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)


@functools.partial(jax.jit, static_argnames=("capacity", "cell_capacity"))
def old_build(x, triangles, body, cutoff, capacity, cell_capacity):
    """The previous broad phase: each node scans 27 cells x cell_capacity slots; flat
    (capacity, 2) pair list sorted by (node, body), group ids."""
    n, m = x.shape[0], triangles.shape[0]
    K, itype = int(cell_capacity), jnp.int64
    xt = x[triangles]
    centre = jnp.mean(xt, axis=1)
    radius = jnp.max(jnp.linalg.norm(xt - centre[:, None], axis=-1), axis=1)
    tbody = body[triangles[:, 0]]
    h = cutoff + jnp.max(radius)
    lo = jnp.min(x, axis=0) - 1.5 * h
    dims = jnp.floor((jnp.max(x, axis=0) - lo) / h).astype(itype) + 3

    def cell(p):
        return jnp.floor((p - lo) / h).astype(itype)

    def linear(ijk):
        return ijk[..., 0] + dims[0] * (ijk[..., 1] + dims[1] * ijk[..., 2])

    tcell = linear(cell(centre))
    order = jnp.argsort(tcell)
    sorted_cells = tcell[order]
    ncells = linear(cell(x)[:, None, :] + jnp.asarray(_OFFSETS, dtype=itype))
    start = jnp.searchsorted(sorted_cells, ncells, side="left")
    stop = jnp.searchsorted(sorted_cells, ncells, side="right")
    occ = (stop - start).astype(jnp.int32)
    k = jnp.arange(K)
    tri = order[jnp.clip(start[..., None] + k, 0, m - 1)].astype(jnp.int32)
    diff = x[:, None, None, :] - centre[tri]
    reach = cutoff + radius[tri]
    ok = ((k < occ[..., None]) & (jnp.sum(diff * diff, axis=-1) < reach * reach)
          & (body[:, None, None] != tbody[tri])).reshape(-1)
    node = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None, None], tri.shape)
    pos = jnp.cumsum(ok) - 1
    count = jnp.sum(ok)
    dest = jnp.where(ok, pos, capacity)
    pn = jnp.full((capacity,), n, jnp.int32).at[dest].set(node.reshape(-1), mode="drop")
    pt = jnp.full((capacity,), m, jnp.int32).at[dest].set(tri.reshape(-1), mode="drop")
    valid = pn < n
    nb = jnp.max(body).astype(itype) + 1
    key = jnp.where(valid, pn.astype(itype) * nb + tbody[jnp.clip(pt, 0, m - 1)],
                    jnp.iinfo(itype).max)
    perm = jnp.argsort(key, stable=True)
    key, pn, pt, valid = key[perm], pn[perm], pt[perm], valid[perm]
    new = jnp.concatenate([jnp.ones((1,), bool), key[1:] != key[:-1]])
    group = jnp.where(valid, (jnp.cumsum(new) - 1).astype(jnp.int32), capacity - 1)
    overflow = (count > capacity) | (jnp.max(occ) > K)
    return dict(pairs=jnp.stack([pn, pt], 1), group=group, valid=valid, count=count,
                max_cell=jnp.max(occ), overflow=overflow)


def old_build_checked(x, triangles, body, cutoff):
    """(capacity, cell_capacity) the previous checked builder ends with."""
    cap, cc = C.default_capacity(len(x)), 32
    for _ in range(12):
        lst = old_build(x, triangles, body, cutoff, cap, cc)
        if not bool(lst["overflow"]):
            return cap, cc
        if int(lst["count"]) > cap:
            cap = 1 << (max(2 * cap, int(lst["count"])) - 1).bit_length()
        if int(lst["max_cell"]) > cc:
            cc = 1 << (max(2 * cc, int(lst["max_cell"])) - 1).bit_length()
    raise RuntimeError("old list overflow")


def old_energy(c, x, triangles, lst, node_area):
    """The previous SmoothContact.energy (one-sided): vmap'ed distances, segment_min."""
    n, m = x.shape[0], triangles.shape[0]
    cap = lst["pairs"].shape[0]
    seg = dict(segment_ids=lst["group"], num_segments=cap, indices_are_sorted=True)
    i = jnp.clip(lst["pairs"][:, 0], 0, n - 1)
    t = triangles[jnp.clip(lst["pairs"][:, 1], 0, m - 1)]
    p, a, b, cc = x[i], x[t[:, 0]], x[t[:, 1]], x[t[:, 2]]
    d, q, bary = jax.vmap(point_triangle_distance)(p, a, b, cc)
    d = jnp.where(lst["valid"], d, jnp.inf)
    over = jnp.all(bary > 0, axis=-1)
    side = jnp.where(over & (jnp.sum((p - q) * jnp.cross(b - a, cc - a), axis=-1) < 0),
                     -1.0, 1.0)
    dmin = jax.ops.segment_min(d, **seg)
    near = lst["valid"] & (d <= dmin[lst["group"]])
    side = jax.ops.segment_max(jnp.where(near, side, -1.0), **seg)
    dmin = jnp.minimum(jnp.where(jnp.isfinite(dmin), side * dmin, c.gap), c.gap)
    node = jax.ops.segment_max(jnp.where(lst["valid"], lst["pairs"][:, 0], 0), **seg)
    return 0.5 * jnp.sum(node_area[jnp.clip(node, 0, n - 1)] * c.potential(dmin))


# ---------------------------------------------------------------------- configurations
def valve(h, state=None):
    from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
    from jaxvalve.geometry.root import benchmark_root
    from jaxvalve.geometry.template import Template
    from jaxvalve.valve import build_valve

    tpl = Template(12, 6.7, 15)
    v = build_valve(benchmark_root(tpl.sutured_length), mesh_leaflet(tpl, h))
    x = v.x_placed if state is None else np.load(state)
    return np.asarray(x, float), np.asarray(v.triangles, np.int32), v.body.astype(np.int32)


def sheets(n, size=0.87, spacing=0.19, seed=0):
    """Three wavy n x n-cell sheets, `spacing` apart, facing alternately."""
    rng = np.random.default_rng(seed)
    L = size * n
    g = np.linspace(0.0, L, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    xs, ts, bs = [], [], []
    for k in range(3):
        z = k * spacing + 0.3 * np.sin(2 * np.pi * X / 6.0) * np.cos(2 * np.pi * Y / 7.0)
        p = np.stack([X.ravel(), Y.ravel(), z.ravel()], 1)
        p += 0.02 * rng.standard_normal(p.shape)
        t = []
        for i in range(n):
            for j in range(n):
                a = i * (n + 1) + j
                b = a + n + 1
                t += [[a, b, b + 1], [a, b + 1, a + 1]] if k != 1 else [[a, b + 1, b],
                                                                       [a, a + 1, b + 1]]
        xs.append(p)
        ts.append(np.array(t) + k * len(p))
        bs.append(np.full(len(p), k))
    return np.concatenate(xs), np.concatenate(ts).astype(np.int32), np.concatenate(bs)


# ---------------------------------------------------------------------------- timing
def best_ms(f, *args, repeat=5, number=None):
    jax.block_until_ready(f(*args))
    if number is None:
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        number = max(1, min(50, int(0.05 / max(time.perf_counter() - t0, 1e-6))))
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            r = f(*args)
        jax.block_until_ready(r)
        best = min(best, (time.perf_counter() - t0) / number)
    return 1e3 * best


def run(name, x, tri, body, repeat, old_max):
    law = C.SmoothContact(one_sided=True)
    xj, tj, bj = jnp.asarray(x), jnp.asarray(tri), jnp.asarray(body)
    area = C.node_areas(xj, tj)
    row = dict(name=name, M=len(tri), N=len(x))
    nb = C.build_neighbours_checked(xj, tj, bj, CUTOFF)
    row.update(pairs=int(nb.n_pairs), slots=int(nb.count))
    build = jax.jit(lambda y: C.build_neighbours(
        y, tj, bj, CUTOFF, nb.capacity, nb.scan_capacity, n_bodies=nb.n_bodies,
        grid_size=nb.grid_size))
    energy = jax.jit(lambda y, lst: law.energy(y, tj, lst, area))
    vg = jax.jit(jax.value_and_grad(lambda y, lst: law.energy(y, tj, lst, area)))
    row["new"] = (best_ms(build, xj, repeat=repeat), best_ms(energy, xj, nb, repeat=repeat),
                  best_ms(vg, xj, nb, repeat=repeat))
    row["old"] = None
    if len(tri) <= old_max:
        cap, cc = old_build_checked(xj, tj, bj, CUTOFF)
        lst = old_build(xj, tj, bj, CUTOFF, cap, cc)
        e_new, e_old = float(energy(xj, nb)), float(old_energy(law, xj, tj, lst, area))
        assert abs(e_new - e_old) <= 1e-12 * max(abs(e_old), 1e-300), (e_new, e_old)
        obuild = jax.jit(lambda y: old_build(y, tj, bj, CUTOFF, cap, cc))
        oenergy = jax.jit(lambda y, lst: old_energy(law, y, tj, lst, area))
        ovg = jax.jit(jax.value_and_grad(lambda y, lst: old_energy(law, y, tj, lst, area)))
        row["old"] = (best_ms(obuild, xj, repeat=min(repeat, 3), number=2),
                      best_ms(oenergy, xj, lst, repeat=repeat),
                      best_ms(ovg, xj, lst, repeat=repeat))
    return row


def fmt(v):
    return "-" if v is None else (f"{v:8.3f}" if v < 100 else f"{v:8.1f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--valve-h", default="1.3,0.87,0.6", help="valve mesh sizes (mm)")
    ap.add_argument("--sheets", default="24,34,48", help="cells per side of the sheets")
    ap.add_argument("--state", default=None, help="(N, 3) .npy state of the valve")
    ap.add_argument("--state-h", type=float, default=0.87, help="mesh size of --state")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--old-max", type=int, default=16000,
                    help="skip the previous implementation above this many triangles")
    a = ap.parse_args(argv)
    fams = {"valve": [("valve h=%g open" % h, valve(h)) for h in
                      map(float, filter(None, a.valve_h.split(",")))],
            "sheets": [("sheets %dx%d" % (n, n), sheets(n)) for n in
                       map(int, filter(None, a.sheets.split(",")))]}
    if a.state:
        fams["state"] = [("valve h=%g state" % a.state_h, valve(a.state_h, a.state))]
    print(f"cutoff {CUTOFF} mm, SmoothContact(one_sided=True), float64, "
          f"{jax.devices()[0].platform}; ms per call (best of {a.repeat})")
    head = (f"{'configuration':22s} {'tris':>6s} {'pairs':>6s} | {'old rebuild':>11s} "
            f"{'new':>8s} {'x':>5s} | {'old energy':>10s} {'new':>8s} {'x':>5s} | "
            f"{'old E+grad':>10s} {'new':>8s} {'x':>5s}")
    print(head)
    print("-" * len(head))
    results = {}
    for fam, cfgs in fams.items():
        for name, (x, tri, body) in cfgs:
            r = run(name, x, tri, body, a.repeat, a.old_max)
            results.setdefault(fam, []).append(r)
            cols = []
            for k in range(3):
                o, nw = (None if r["old"] is None else r["old"][k]), r["new"][k]
                cols.append(f"{fmt(o):>{11 if k == 0 else 10}s} {fmt(nw)} "
                            f"{'-' if o is None else f'{o / nw:5.0f}':>5s}")
            print(f"{name:22s} {r['M']:6d} {r['pairs']:6d} | " + " | ".join(cols), flush=True)
    print()
    print("fitted exponent b of t ~ M^b (per family, >= 3 sizes):")
    for fam, rows in results.items():
        if len(rows) < 3:
            continue
        M = np.log([r["M"] for r in rows])
        line = [f"  {fam:7s}"]
        for who in ("old", "new"):
            for k, what in enumerate(("rebuild", "energy", "E+grad")):
                ts = [r[who][k] if r[who] else None for r in rows]
                if any(t is None for t in ts):
                    line.append(f"{who} {what} -")
                    continue
                line.append(f"{who} {what} {np.polyfit(M, np.log(ts), 1)[0]:.2f}")
        print(", ".join(line))
    print("pairs grow like M^%.2f (sheets) / M^%.2f (valve)" % tuple(
        np.polyfit(np.log([r["M"] for r in results[f]]), np.log([r["pairs"] for r in
                   results[f]]), 1)[0] if len(results.get(f, [])) >= 2 else float("nan")
        for f in ("sheets", "valve")))


if __name__ == "__main__":
    main()
