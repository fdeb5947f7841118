"""Soft-min contact on the closed benchmark valve: every Verlet candidate vs the pruned list.

    python benchmarks/soft_contact.py [--h 0.88] [--repeat 5]

Closes the benchmark valve (StVK, 3 then 80 mmHg, `jaxvalve.simulate`), then times at the
closed 80 mmHg state (ms per call, best of --repeat batches, after compilation):

* force (no contact):   elastic + bending + pressure, the rest of a force evaluation;
* contact E+grad, full: the soft-min energy from its definition on the Verlet list
                        (`smooth.soft_energy_reference`: nearest-triangle pass + soft
                        minimum over all candidates of the live groups; this was the
                        solve's evaluation before the pruned list);
* contact E+grad, pruned: `SmoothContact.energy` on `soft_pairs.SoftPairs` (only the triangles within
                        PRUNE_REACH softness lengths of the nearest, plus the margin);
* Verlet rebuild, pruned-list build: what a refresh costs when it happens.

It checks that both give the same energy and forces (to 1e-12, relative) and prints the
pair counts and the ratio.
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxvalve
from jaxvalve.mechanics import assembly
from jaxvalve.solvers import equilibrium
from jaxvalve.contact import build_neighbours
from jaxvalve.contact.smooth import soft_energy_reference
from jaxvalve.contact.soft_pairs import build_soft_pairs
from jaxvalve.scene import Scene


def best_ms(f, *args, repeat=5, number=20):
    jax.block_until_ready(f(*args))
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            out = f(*args)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t0) / number * 1e3)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=Scene().h, help="mesh size, mm")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    sc = Scene(model="stvk", h=args.h)
    res = jaxvalve.simulate(sc)
    valve, x = res.valve, jnp.asarray(res.x)
    prob = valve.problem
    params = valve.params(sc.material(), sc.pressure, sc.contact_law(),
                          bending=sc.bending_law())
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, x.dtype), params)
    law = params.contact
    ref = assembly.prepare(prob, params)
    pairs = equilibrium.init_pairs(law, prob, x)
    base = pairs.base

    full = jax.jit(jax.value_and_grad(
        lambda y: soft_energy_reference(law, y, prob.triangles, base, ref.node_area)))
    pruned = jax.jit(jax.value_and_grad(
        lambda y: law.energy(y, prob.triangles, pairs, ref.node_area)))
    (e_f, g_f), (e_p, g_p) = full(x), pruned(x)
    err_e = abs(float(e_p - e_f)) / abs(float(e_f))
    err_g = float(jnp.max(jnp.abs(g_p - g_f)) / jnp.max(jnp.abs(g_f)))
    no_contact = jax.jit(lambda y: assembly.residual(y, prob, params.replace(contact=None),
                                                     ref, None, 0.0))
    rebuild = jax.jit(lambda y: build_neighbours(y, prob.triangles, prob.body, base.cutoff,
                                                 base.capacity, n_bodies=base.n_bodies))
    soft_build = jax.jit(lambda y: build_soft_pairs(base, y, prob.triangles, law,
                                                    pairs.soft_capacity))
    rows = [("force (no contact)", best_ms(no_contact, x, repeat=args.repeat)),
            ("contact E+grad, full", best_ms(full, x, repeat=args.repeat)),
            ("contact E+grad, pruned", best_ms(pruned, x, repeat=args.repeat)),
            ("Verlet rebuild", best_ms(rebuild, x, repeat=args.repeat)),
            ("pruned-list build", best_ms(soft_build, x, repeat=args.repeat))]
    print(f"closed benchmark valve, {len(prob.triangles)} triangles, {prob.n_nodes} nodes; "
          f"solve {sum(s.solve_s for s in res.solves):.2f} s "
          f"({'/'.join(str(s.steps) for s in res.solves)} FIRE steps)")
    print(f"Verlet candidates {int(base.n_pairs)} in {int(base.n_rows)} rows; pruned pairs "
          f"{int(pairs.n)} (capacity {pairs.soft_capacity})")
    print(f"pruned vs full: energy rel. diff {err_e:.1e}, force max rel. diff {err_g:.1e}")
    for name, ms in rows:
        print(f"  {name:26s} {ms:8.3f} ms")
    print(f"contact E+grad, full / pruned: {rows[1][1] / rows[2][1]:.1f}x; force evaluation "
          f"(no contact + contact), full / pruned: "
          f"{(rows[0][1] + rows[1][1]) / (rows[0][1] + rows[2][1]):.1f}x")
    assert err_e < 1e-12 and err_g < 1e-12, "the pruned list disagrees with the full one"


if __name__ == "__main__":
    main()
