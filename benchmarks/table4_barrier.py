"""The paper's Table 4 (mass-spring, E1 x E2, E3 = 1.2 MPa) closed with the barrier contact
and the projected Newton solver, one cell after the other (`jaxvalve.simulate`).

For each cell: whether both closures converged, Newton steps at 3 and 80 mmHg, the final
relative residual, the smallest leaflet gap, the heights h and h_c against the paper's,
crossings (the project's exact triangle test and the IPC toolkit's `has_intersections`,
commissure rings excluded: neighbours are sewn to one point there), and the wall time.

    python benchmarks/table4_barrier.py [--h 1.5] [--cells "E1,E2;..."] [--out FILE]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from closure_speed import Tee  # noqa: E402  (this folder is on the path of a script)
from jaxvalve import Scene, simulate  # noqa: E402
from jaxvalve.contact.ipc_pairs import build_pairs  # noqa: E402
from jaxvalve.cli.sweep import TABLE4_E1, TABLE4_E2, TABLE4_E3, TABLE4_PAPER  # noqa: E402
from jaxvalve.simulation import build_scene_valve  # noqa: E402
from jaxvalve.valve import leaflet_crossings  # noqa: E402


def ipctk_intersections(valve, x):
    """True where the IPC toolkit finds two triangles of the closed valve intersecting,
    the triangles at a commissure pin left out (None without ipctk)."""
    try:
        import ipctk
    except ImportError:
        return None
    tri = valve.triangles
    pin = valve.barrier_topology.pin
    keep = ~np.any(pin[tri] >= 0, axis=1)
    t = tri[keep]
    used, inv = np.unique(t, return_inverse=True)
    t = inv.reshape(t.shape).astype(np.int32)
    v = np.asarray(x, float)[used]
    return bool(ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(t), t), v))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h", type=float, default=1.5, help="mesh size, mm")
    ap.add_argument("--out", default=None, help="also write the table here")
    ap.add_argument("--cells", default=None,
                    help="only these cells, as 'E1,E2;E1,E2' in MPa (default: all nine)")
    args = ap.parse_args(argv)
    cells = None
    if args.cells:
        cells = {tuple(float(v) for v in c.split(",")) for c in args.cells.split(";")}
    say = Tee()
    say(f"Table 4 with the barrier contact and projected Newton, h = {args.h} mm")
    say("| E1 MPa | E2 MPa | result | steps 3/80 | residual | min gap mm | h mm (paper) "
        "| h_c mm (paper) | crossings exact/ipctk | wall s |")
    say("|---|---|---|---|---|---|---|---|---|---|")
    valve = None
    n_ok = 0
    for e1 in TABLE4_E1:
        for e2 in TABLE4_E2:
            if cells is not None and (e1, e2) not in cells:
                continue
            sc = Scene(model="mass-spring", E1=e1, E2=e2, E3=TABLE4_E3, h=args.h,
                       contact="barrier", solver="newton")
            valve = build_scene_valve(sc) if valve is None else valve
            t0 = time.perf_counter()
            res = simulate(sc, valve=valve, throw=False)
            wall = time.perf_counter() - t0
            s3, s80 = res.solves
            gap = build_pairs(valve.barrier_topology, res.x, 1.0).min_distance
            ph, phc = TABLE4_PAPER.get((e1, e2), (float("nan"), float("nan")))
            cross = len(leaflet_crossings(valve, res.x))
            ipc = ipctk_intersections(valve, res.x)
            status = "converged" if res.converged else f"{s3.result}/{s80.result}"
            n_ok += res.converged
            say(f"| {e1:g} | {e2:g} | {status} | {s3.steps}/{s80.steps} | {s80.residual:.1e} "
                f"| {gap:.3f} | {res.metrics.h:.2f} ({ph:g}) | {res.metrics.h_c:.2f} ({phc:g}) "
                f"| {cross}/{'-' if ipc is None else int(ipc)} | {wall:.1f} |")
    n_all = len(cells) if cells is not None else len(TABLE4_E1) * len(TABLE4_E2)
    say(f"converged: {n_ok} of {n_all}")
    say.write(args.out)


if __name__ == "__main__":
    main()
