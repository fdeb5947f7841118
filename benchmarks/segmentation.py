"""Segmentation accuracy on the synthetic ceCTA phantom: the distance between the segmented
wall surface and the phantom's true wall, at two noise levels and two voxel sizes.

    python benchmarks/segmentation.py
    python benchmarks/segmentation.py --noise 20 60 --spacing 0.4,0.4,0.6 0.8,0.8,1.0

For each scan: the phantom's volume (`imaging.phantom.phantom_volume`), the segmentation
(Hough seed, region growing, opening: `imaging.segment.segment`) and the wall surface
(`imaging.surface.wall_surface`), timed; then the distance from each vertex of the
segmented surface to the true wall, and from each vertex of the true wall (meshed on a
0.25 mm grid) to the segmented surface, both away from the volume's open ends (1.5 mm).
Targets: mean below 0.3 mm, 95th percentile below 1 mm.  Then the last scan's wall
remeshed to each ``--edge`` length (`imaging.remesh`): triangles, edge lengths, smallest
angles and the distance to the true wall, timed.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from jaxvalve.geometry.surface_query import distance_to_surface  # noqa: E402
from jaxvalve.imaging.phantom import RootPhantom, phantom_volume, true_wall  # noqa: E402
from jaxvalve.imaging.segment import segment  # noqa: E402
from jaxvalve.imaging.surface import mesh_quality, wall_surface  # noqa: E402


def _spacing(text):
    v = tuple(float(x) for x in text.split(","))
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"a spacing is three sizes, mm (e.g. 0.4,0.4,0.6); "
                                         f"got {text!r}")
    return v


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[20.0, 60.0],
                    help="noise standard deviations, HU")
    ap.add_argument("--spacing", type=_spacing, nargs="+",
                    default=[(0.4, 0.4, 0.6), (0.8, 0.8, 1.0)], help="voxel sizes x,y,z mm")
    ap.add_argument("--edge", type=float, nargs="*", default=[1.0, 1.5, 2.0],
                    help="target edge lengths of the remeshed wall, mm")
    args = ap.parse_args(argv)
    print("| voxel mm | noise HU | voxels | phantom s | segment + surface s | triangles | "
          "mean edge mm | seg -> true mean / p95 / max mm | true -> seg mean / p95 / max mm | "
          "neighbour removed voxels | targets |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    ok = True
    for sp in args.spacing:
        truth = None
        for noise in args.noise:
            ph = RootPhantom(spacing=sp, noise_hu=noise)
            if truth is None:
                truth = true_wall(ph, step=0.25)
            t0 = time.perf_counter()
            vol = phantom_volume(ph)
            t_ph = time.perf_counter() - t0
            t0 = time.perf_counter()
            seg = segment(vol)
            P, T = wall_surface(vol, seg)
            t_seg = time.perf_counter() - t0
            lo, hi = ph.extent()

            def inner(x):
                return (x[:, 2] > lo[2] + 1.5) & (x[:, 2] < hi[2] - 1.5)
            d1 = distance_to_surface(P[inner(P)], *truth)
            d2 = distance_to_surface(truth[0][inner(truth[0])], P, T)
            q = mesh_quality(P, T)
            met = max(d1.mean(), d2.mean()) < 0.3 and max(np.percentile(d1, 95),
                                                          np.percentile(d2, 95)) < 1.0
            ok &= met
            print(f"| {sp[0]:g} x {sp[1]:g} x {sp[2]:g} | {noise:g} | {np.prod(vol.shape)} | "
                  f"{t_ph:.1f} | {t_seg:.1f} | {q['triangles']} | {q['edge_mm']['mean']:.2f} | "
                  f"{d1.mean():.3f} / {np.percentile(d1, 95):.3f} / {d1.max():.2f} | "
                  f"{d2.mean():.3f} / {np.percentile(d2, 95):.3f} / {d2.max():.2f} | "
                  f"{seg.report['separate']['removed_voxels']} | {'met' if met else 'MISSED'} |",
                  flush=True)
    print(f"\nall targets met: {ok}")
    print(f"\nremeshed, the last scan ({sp[0]:g} x {sp[1]:g} x {sp[2]:g} mm, {noise:g} HU):\n")
    print("| target edge mm | remesh s | triangles | edge mm min / mean / max | smallest angle "
          "min / p5 deg | seg -> true mean / p95 mm |")
    print("|---|---|---|---|---|---|")
    for edge in [None] + list(args.edge):
        t0 = time.perf_counter()
        P, T = wall_surface(vol, seg, edge_mm=edge)
        dt = time.perf_counter() - t0
        q = mesh_quality(P, T)
        d1 = distance_to_surface(P[inner(P)], *truth)
        e, a = q["edge_mm"], q["min_angle_deg"]
        print(f"| {'none' if edge is None else f'{edge:g}'} | {dt:.1f} | {q['triangles']} | "
              f"{e['min']:.3f} / {e['mean']:.2f} / {e['max']:.2f} | {a['min']:.1f} / "
              f"{a['p5']:.1f} | {d1.mean():.3f} / {np.percentile(d1, 95):.3f} |", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
