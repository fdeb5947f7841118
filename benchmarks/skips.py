"""What each scene skips, timed with and without the skip, and the broad phase's scaling.

    nice -n 15 .venv/bin/python benchmarks/skips.py [--h 1.5,0.88]
        [--scaling-h 2,1.5,1,0.7,0.5,0.4] [--repeat 7] [--cache DIR]
        [--out benchmarks/results/skips.txt]

Closes the benchmark valve (StVK, bending on, smooth one-sided soft-min contact: the
default `Scene`, 3 then 80 mmHg) at each --h and, at the closed 80 mmHg state, times
(median of --repeat batches, after compilation, float64) each skip against a variant that
does not skip (written here, not in the library):

* reference once:    `assembly.prepare` (Dm^-1, areas, cotangents, spring directions,
                     hinge weights) once per solve, against inside every force evaluation;
* linear springs:    `MassSpring.linear(E)` (E2 = E3 = None: psi = E eps^2 / 2), against
                     the piecewise law (3.3) with E1 = E2 = E3 = E;
* isotropic:         mass-spring without cross-fibre moduli (no mixing traced), against
                     E1_cf = E1 (eq. 2.4 mixing with equal moduli);
* no bending:        `Scene(bending=0)` (`bending_law()` None: no hinges traced), against
                     `Bending(0.0)` (hinges evaluated with a zero modulus);
* stretch check:     StVK's admissibility (no check: constant True), against Gent's
                     stretch-limit check (I1 + 1/I2 - 3 < Jm on every triangle);
* other leaflets:    the Verlet list of (node, other leaflet) pairs, against every
                     (node, triangle) pair within the cutoff including the node's own
                     leaflet: broad phase and nearest-triangle pass;
* cutoff region:     the Verlet candidates (cutoff g0 + skin, `Valve.skin`), against every pair
                     of different leaflets (cutoff past the valve's size; only where a
                     leaflet has <= MAX_GROUP triangles), soft-min contact E+grad from its
                     definition (`smooth.soft_energy_reference`) and broad phase;
* pruned pairs:      the soft-min contact on the pruned list (`soft_pairs`), against the
                     definition over all Verlet candidates;
* no contact at P=0: the settle (P = 0, from the harmonic start) without contact, against
                     with contact (force evaluation at the start).

Each row says what is timed, both times (ms per call), their ratio, both compile times
(s), and the largest relative difference of the values (energy and forces) where the two
variants compute the same thing.

Broad phase scaling: the Verlet build (`contact.build_neighbours`, capacities as
`build_neighbours_checked` sets them) on the benchmark valve at each --scaling-h, with the
solve's cutoff g0 + skin, skin = `Valve.skin` (the median edge, at most 1 mm), in two
states: the closed state of the finest --h interpolated onto that mesh through the
template coordinates (the coaptation zone as in a closed valve), and the placement (the
leaflets apart); and, for comparison, the closed state with the fixed 1 mm skin the solve
used before (cutoff 1.2 mm).  The exponent b of t ~ M^b (M = triangles) is fitted by least
squares on log-log, over all sizes and over those with h <= 1 mm (where the skin follows
the mesh).

--cache DIR keeps the closed states (closed_h*.npy) between runs.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from contact import CUTOFF  # noqa: E402  (benchmarks/contact.py: gap + skin, mm)

GAP = 0.2  # mm: SmoothContact().gap
STATES = ("closed", "placed", "closed, 1 mm skin")

import jaxvalve  # noqa: E402
from jaxvalve.mechanics import assembly
from jaxvalve.solvers import equilibrium  # noqa: E402
from jaxvalve.mechanics import materials as M  # noqa: E402
from jaxvalve.mechanics.bending import Bending  # noqa: E402
from jaxvalve.contact import build_neighbours, build_neighbours_checked  # noqa: E402
from jaxvalve.contact.neighbours import MAX_GROUP  # noqa: E402
from jaxvalve.contact.smooth import nearest_triangles, soft_energy_reference  # noqa: E402
from jaxvalve.geometry.mesh import right_cauchy_green  # noqa: E402
from jaxvalve.scene import Scene  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402


# ------------------------------------------------------------------------------ timing
def _compile(f, args):
    jax.clear_caches()   # a fresh compilation, not a cache hit of an earlier row
    t0 = time.perf_counter()
    comp = jax.jit(f).lower(*args).compile()
    return comp, time.perf_counter() - t0


def _batch(comp, args, number):
    t0 = time.perf_counter()
    for _ in range(number):
        r = comp(*args)
    jax.block_until_ready(r)
    return (time.perf_counter() - t0) / number


def _number(comp, args, min_s):
    jax.block_until_ready(comp(*args))
    return max(1, min(200, int(min_s / max(_batch(comp, args, 1), 1e-6))))


def timed(f, *args, repeat=7, min_s=0.05):
    """(compile s, median ms per call, value): f jitted, compiled once, then called in
    batches of at least min_s seconds."""
    comp, c = _compile(f, args)
    out = jax.block_until_ready(comp(*args))
    number = _number(comp, args, min_s)
    ts = [_batch(comp, args, number) for _ in range(repeat)]
    return c, 1e3 * float(np.median(ts)), out


def compare(without, with_, repeat=7, min_s=0.05):
    """Each of (f, args) timed as `timed`, their batches interleaved (A, B, A, B, ...) so
    that the load of this shared machine falls on both alike."""
    (fa, aa), (fb, ab) = without, with_
    ca, sa = _compile(fa, aa)
    cb, sb = _compile(fb, ab)
    oa, ob = jax.block_until_ready(ca(*aa)), jax.block_until_ready(cb(*ab))
    na, nb = _number(ca, aa, min_s), _number(cb, ab, min_s)
    ta, tb = [], []
    for _ in range(repeat):
        ta.append(_batch(ca, aa, na))
        tb.append(_batch(cb, ab, nb))
    return ((sa, 1e3 * float(np.median(ta)), oa), (sb, 1e3 * float(np.median(tb)), ob))


def rel_diff(a, b):
    """Largest relative difference of two pytrees of arrays (each leaf by its max)."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    d = 0.0
    for u, v in zip(la, lb):
        u, v = np.asarray(u, float), np.asarray(v, float)
        d = max(d, float(np.max(np.abs(u - v)) / max(np.max(np.abs(v)), 1e-300)))
    return d


# ------------------------------------------------------------------------------ setup
def closed_state(scene, cache):
    path = os.path.join(cache, f"closed_h{scene.h:g}.npy") if cache else None
    if path and os.path.exists(path):
        return build_scene_valve(scene), np.load(path)
    res = jaxvalve.simulate(scene)
    if path:
        os.makedirs(cache, exist_ok=True)
        np.save(path, res.x)
    return res.valve, res.x


def as_f64(tree):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), tree)


class Rows:
    def __init__(self):
        self.rows = []

    def add(self, skip, what, h, without, with_, agree=None, note=""):
        self.rows.append(dict(skip=skip, what=what, h=h, c0=without[0], t0=without[1],
                              c1=with_[0], t1=with_[1], agree=agree, note=note))
        r = self.rows[-1]
        print(self.format(r), flush=True)

    @staticmethod
    def header():
        return (f"{'skip':19s} {'timed':26s} {'h mm':>4s} | {'without ms':>10s} "
                f"{'with ms':>9s} {'ratio':>6s} | {'compile s w/o':>13s} {'with':>5s} | "
                f"{'rel diff':>8s}  note")

    @staticmethod
    def format(r):
        agree = "-" if r["agree"] is None else f"{r['agree']:.0e}"
        return (f"{r['skip']:19s} {r['what']:26s} {r['h']:4g} | {r['t0']:10.3f} "
                f"{r['t1']:9.3f} {r['t0'] / r['t1']:6.2f} | {r['c0']:13.2f} {r['c1']:5.2f} | "
                f"{agree:>8s}  {r['note']}")


def all_pairs_list(x, tri, body):
    """(node, triangle) candidates within the cutoff of every leaflet INCLUDING the node's own:
    the triangles are given copies of the nodes (body 3), so each node of bodies 0-2 has
    one group holding every triangle in range.  Returns (x_ext, tri_ext, body_ext)."""
    n = x.shape[0]
    x_ext = np.concatenate([x, x])
    body_ext = np.concatenate([body, np.full(n, 3, body.dtype)])
    return x_ext, tri + n, body_ext


def skips_at(h, rows, repeat, cache):
    scene = Scene(h=h)
    valve, x = closed_state(scene, cache)
    prob = valve.problem
    x = jnp.asarray(x, jnp.float64)
    tri = prob.triangles
    law = scene.contact_law()
    bend = scene.bending_law()
    base_params = as_f64(valve.params(scene.material(), scene.pressure, law,
                                      bending=bend))
    ref = assembly.prepare(prob, base_params)
    pairs = equilibrium.init_pairs(law, prob, x, valve.skin)
    cut = GAP + valve.skin    # the solve's broad-phase cutoff (mm)
    T = dict(repeat=repeat)
    print(f"-- h = {h} mm: {len(tri)} triangles, {prob.n_nodes} nodes; Verlet candidates "
          f"{int(pairs.base.n_pairs)}, pruned pairs {int(pairs.n)}", flush=True)

    def force_with(y, p, r, nb):
        return assembly.residual(y, prob, p, r, nb)

    def force_without(y, p, nb):
        return assembly.residual(y, prob, p, assembly.prepare(prob, p), nb)

    def add(skip, what, without, with_, agree=True, note=""):
        wo, w = compare(without, with_, **T)
        rows.add(skip, what, h, wo, w, rel_diff(wo[2], w[2]) if agree else None, note)

    # 1. reference geometry once per solve
    add("reference once", "force evaluation (StVK)", (force_without, (x, base_params, pairs)),
        (force_with, (x, base_params, ref, pairs)))
    ms_params = as_f64(base_params.replace(material=M.MassSpring.linear(1.0)))
    ms_ref = assembly.prepare(prob, ms_params)
    add("reference once", "force evaluation (springs)", (force_without, (x, ms_params, pairs)),
        (force_with, (x, ms_params, ms_ref, pairs)))

    # 2./3. material skips: elastic E+grad and the whole force evaluation
    def elastic(y, p, r):
        return jax.value_and_grad(assembly.elastic_energy)(y, prob, p, r)

    def material_rows(skip, mat_with, mat_without):
        pw, pwo = (as_f64(base_params.replace(material=m)) for m in (mat_with, mat_without))
        rw, rwo = assembly.prepare(prob, pw), assembly.prepare(prob, pwo)
        add(skip, "elastic E+grad", (elastic, (x, pwo, rwo)), (elastic, (x, pw, rw)))
        add(skip, "force evaluation", (force_with, (x, pwo, rwo, pairs)),
            (force_with, (x, pw, rw, pairs)))

    material_rows("linear springs", M.MassSpring.linear(1.0), M.MassSpring(1.0, 1.0, 1.0))
    material_rows("isotropic", M.MassSpring.linear(1.0), M.MassSpring.linear(1.0, 1.0))

    # 4. bending only when asked for
    def cons(y, p, r):
        return jax.value_and_grad(assembly.conservative_energy)(y, prob, p, r, None)

    pw = base_params.replace(bending=None, contact=None)
    pwo = as_f64(base_params.replace(bending=Bending(0.0), contact=None))
    rw, rwo = assembly.prepare(prob, pw), assembly.prepare(prob, pwo)
    add("no bending", "elastic+bending E+grad", (cons, (x, pwo, rwo)), (cons, (x, pw, rw)))
    pw, pwo = base_params.replace(bending=None), as_f64(base_params.replace(bending=Bending(0.0)))
    rw, rwo = assembly.prepare(prob, pw), assembly.prepare(prob, pwo)
    add("no bending", "force evaluation", (force_with, (x, pwo, rwo, pairs)),
        (force_with, (x, pw, rw, pairs)))

    # 5. the stretch-limit check only for Gent
    gent = M.Gent(mu=1.0 / 3.0, Jm=2.3)

    def check_with(y, p, r):
        return assembly.stretch_admissible(y, prob, p, r)

    def check_without(y, p, r):
        return jnp.all(gent.stretch_ok(right_cauchy_green(y, tri, r.Dm_inv)))

    add("stretch check", "admissibility per step", (check_without, (x, base_params, ref)),
        (check_with, (x, base_params, ref)), note="StVK: constant True, no Gent check")

    # 6. contact between different leaflets only
    body = np.asarray(prob.body)
    base = pairs.base
    x_np, tri_np = np.asarray(x), np.asarray(tri)
    xe, te, be = all_pairs_list(x_np, tri_np, body)
    self_nb = build_neighbours_checked(xe, te, be, cut)

    def build(y, t, b, nb, cutoff=cut):
        return build_neighbours(y, t, b, cutoff, nb.capacity, nb.scan_capacity,
                                n_bodies=nb.n_bodies, grid_size=nb.grid_size)

    tj, bj, tej, bej = (jnp.asarray(a) for a in (tri_np, body, te, be))
    xej = jnp.asarray(xe)
    note = f"pairs {int(base.n_pairs)} vs {int(self_nb.n_pairs)} with own leaflet"
    add("other leaflets", "broad phase (Verlet build)",
        (lambda y: build(y, tej, bej, self_nb), (xej,)), (lambda y: build(y, tj, bj, base), (x,)),
        agree=False, note=note)
    add("other leaflets", "nearest-triangle pass",
        (lambda y, nb: nearest_triangles(y, tej, nb, True)[3], (xej, self_nb)),
        (lambda y, nb: nearest_triangles(y, tj, nb, True)[3], (x, base)), agree=False, note=note)

    # 7. candidate region (cutoff) against every pair of different leaflets
    area = ref.node_area
    per_leaflet = len(tri_np) // 3

    def soft_def(y, nb):
        return jax.value_and_grad(
            lambda z: soft_energy_reference(law, z, tj, nb, area))(y)

    if per_leaflet <= MAX_GROUP:
        span = 2.0 * float(np.linalg.norm(x_np.max(0) - x_np.min(0)))
        everything = build_neighbours_checked(x, tj, bj, span)
        note = f"pairs {int(base.n_pairs)} vs {int(everything.n_pairs)} (all)"
        add("cutoff region", "broad phase", (lambda y: build(y, tj, bj, everything, span), (x,)),
            (lambda y: build(y, tj, bj, base), (x,)), agree=False, note=note)
        add("cutoff region", "contact E+grad (definition)", (soft_def, (x, everything)),
            (soft_def, (x, base)), note=note)
    else:
        print(f"   (cutoff region: skipped at h = {h}: a leaflet has {per_leaflet} > "
              f"MAX_GROUP = {MAX_GROUP} triangles, so the all-pairs list cannot be built)")

    # 8. pruned soft-min pairs against every Verlet candidate
    def soft_pruned(y, nb):
        return jax.value_and_grad(lambda z: law.energy(z, tj, nb, area))(y)

    add("pruned pairs", "contact E+grad", (soft_def, (x, base)), (soft_pruned, (x, pairs)),
        note=f"pairs {int(pairs.n)} vs {int(base.n_pairs)}")

    # 9. no contact in the settle at P = 0 (from the harmonic start)
    x0 = jnp.asarray(valve.x_start, jnp.float64)
    p0 = base_params.replace(pressure=jnp.asarray(0.0))
    pairs0 = equilibrium.init_pairs(law, prob, x0)
    add("no contact at P=0", "force evaluation at start", (force_with, (x0, p0, ref, pairs0)),
        (lambda y, p, r: assembly.residual(y, prob, p, r, None),
         (x0, p0.replace(contact=None), ref)),
        note=f"{int(pairs0.base.n_pairs)} candidates at the start")


# ------------------------------------------------------------------------------ scaling
def interpolate_state(v_from, x_from, v_to):
    """The state x_from (on v_from's mesh) carried to v_to's nodes by linear interpolation
    in the template plane, leaflet by leaflet (nearest node outside the coarse hull)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    out = []
    for i in range(3):
        s_f, s_t = v_from.leaflet_slice(i), v_to.leaflet_slice(i)
        p_f, p_t = np.asarray(v_from.ref)[s_f], np.asarray(v_to.ref)[s_t]
        y = np.asarray(x_from)[s_f]
        lin = LinearNDInterpolator(p_f, y)(p_t)
        near = NearestNDInterpolator(p_f, y)(p_t)
        out.append(np.where(np.isfinite(lin), lin, near))
    return np.concatenate(out)


def scaling(hs, v_closed, x_closed, repeat):
    rows = []
    for h in hs:
        v = build_scene_valve(Scene(h=h))
        tri, body = jnp.asarray(v.triangles), jnp.asarray(v.body)
        row = dict(h=h, M=len(v.triangles), N=v.problem.n_nodes)
        xc = jnp.asarray(interpolate_state(v_closed, x_closed, v), jnp.float64)
        row["skin"] = v.skin
        for state, x, cutoff in (("closed", xc, GAP + v.skin), ("placed", v.x_placed, GAP + v.skin),
                                 ("closed, 1 mm skin", xc, CUTOFF)):
            x = jnp.asarray(x, jnp.float64)
            nb = build_neighbours_checked(x, tri, body, cutoff)
            c, ms, _ = timed(lambda y: build_neighbours(
                y, tri, body, cutoff, nb.capacity, nb.scan_capacity, n_bodies=nb.n_bodies,
                grid_size=nb.grid_size), x, repeat=repeat, min_s=0.1)
            row[state] = (ms, int(nb.n_pairs), c, int(nb.n_scan))
        rows.append(row)
        print(f"   h={h:4g}: {row['M']:6d} triangles, " + ", ".join(
            f"{s} {row[s][0]:.3f} ms ({row[s][1]} pairs, {row[s][3]} scan slots)"
            for s in STATES), flush=True)
    return rows, exponents(rows), exponents([r for r in rows if r["h"] <= 1.0])


def exponents(rows):
    """{state: (b of t ~ M^b, b of pairs ~ M^b)} by least squares on log-log (NaN for fewer
    than 3 sizes)."""
    if len(rows) < 3:
        return {s: (float("nan"), float("nan")) for s in STATES}
    logM = np.log([r["M"] for r in rows])
    return {s: (float(np.polyfit(logM, np.log([r[s][0] for r in rows]), 1)[0]),
                float(np.polyfit(logM, np.log([max(r[s][1], 1) for r in rows]), 1)[0]))
            for s in STATES}


# ------------------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", default="1.5,0.88", help="mesh sizes of the skips table (mm)")
    ap.add_argument("--scaling-h", default="2,1.5,1,0.7,0.5,0.4",
                    help="mesh sizes of the broad-phase scaling (mm), >= 4")
    ap.add_argument("--repeat", type=int, default=7, help="timed batches (median)")
    ap.add_argument("--cache", default=None, help="directory keeping the closed states")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                  "results", "skips.txt"))
    a = ap.parse_args(argv)
    hs = [float(v) for v in a.h.split(",") if v]
    shs = [float(v) for v in a.scaling_h.split(",") if v]
    if len(shs) < 4:
        ap.error("--scaling-h needs at least 4 mesh sizes")
    t_all = time.perf_counter()
    lines = [f"benchmarks/skips.py {' '.join(argv if argv is not None else sys.argv[1:])}",
             f"{jax.devices()[0].platform}, {os.cpu_count()} CPU cores, float64, "
             f"median of {a.repeat} batches after compilation; closed benchmark valve "
             "(StVK, bending, soft-min one-sided contact) at 80 mmHg", ""]
    print("\n".join(lines))
    print(Rows.header())
    rows = Rows()
    for h in hs:
        skips_at(h, rows, a.repeat, a.cache)
    table = [Rows.header(), "-" * len(Rows.header())] + [Rows.format(r) for r in rows.rows]

    h_ref = min(hs)
    v_ref, x_ref = closed_state(Scene(h=h_ref), a.cache)
    print("\nbroad phase (Verlet build) against mesh size:")
    srows, fit, fit_fine = scaling(shs, v_ref, x_ref, a.repeat)
    sc = [f"broad phase: Verlet build, median ms; closed = the h = {h_ref:g} mm closed "
          "state interpolated onto each mesh, placed = the placement, both with the solve's "
          f"cutoff g0 + skin (skin = Valve.skin: median edge, at most 1 mm); closed, 1 mm "
          f"skin = the fixed cutoff {CUTOFF} mm used before",
          f"{'h mm':>5s} {'skin':>5s} {'tris/leaf':>9s} {'tris':>6s} | "
          + " | ".join(f"{s:>17s} {'pairs':>7s} {'scan':>8s}" for s in STATES)]
    for r in srows:
        sc.append(f"{r['h']:5g} {r['skin']:5.2f} {r['M'] // 3:9d} {r['M']:6d} | " + " | ".join(
            f"{r[s][0]:14.3f} ms {r[s][1]:7d} {r[s][3]:8d}" for s in STATES))
    for label, f in (("all sizes", fit), ("h <= 1 mm", fit_fine)):
        sc.append(f"fitted exponent b of t ~ M^b, {label}: " + ", ".join(
            f"{s} {f[s][0]:.2f} (pairs M^{f[s][1]:.2f})" for s in STATES))
    r0, r1 = srows[-2], srows[-1]
    sc.append("between the two finest meshes: " + ", ".join(
        f"{s} {np.log(r1[s][0] / r0[s][0]) / np.log(r1['M'] / r0['M']):.2f}" for s in STATES))
    out = lines + table + [""] + sc + ["", f"total wall {time.perf_counter() - t_all:.0f} s"]
    print("\n" + "\n".join(sc))
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as fh:
        fh.write("\n".join(out) + "\n")
    print(f"wrote {a.out}")
    return rows.rows, srows, fit


if __name__ == "__main__":
    main()
