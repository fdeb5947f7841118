"""Segment the contrast-filled aortic root of a CT scan (NIfTI file or DICOM folder) and
write its wall surface, the mask, a quality-control figure and a JSON report; with
--landmarks (a 3D Slicer .mrk.json of the commissures C1-C3 and the nadirs N1-N3 or the
suture path curves) also the landmarks projected onto the wall, with the suture paths,
as DIR/landmarks.mrk.json, which `jaxvalve simulate --root DIR/root.stl
DIR/landmarks.mrk.json` takes.  Needs the extra `pip install jaxvalve[imaging]`.
"""
from __future__ import annotations

import json
import sys
import time

FORMATS = ("stl", "vtu", "ply")


def add_parser(sub):
    p = sub.add_parser("segment", help="segment the aortic root of a CT scan and mesh its wall",
                       description=__doc__, allow_abbrev=False,
                       epilog="Example: jaxvalve segment scan.nii.gz --out patient "
                              "--landmarks points.mrk.json")
    p.add_argument("ct", metavar="CT", help="a NIfTI file (.nii, .nii.gz) or a folder of "
                                            "DICOM slices of one series")
    p.add_argument("--out", metavar="DIR", required=True, help="output folder")
    p.add_argument("--seed", type=int, nargs=3, metavar=("I", "J", "K"),
                   help="a voxel inside the ascending aorta (default: found by a Hough "
                        "circle on a top axial slice)")
    p.add_argument("--landmarks", metavar="FILE.mrk.json",
                   help="Slicer markups: commissures C1-C3 and nadirs N1-N3 (a point list) "
                        "or three suture path curves")
    p.add_argument("--edge", type=float, metavar="MM",
                   help="target edge length of the wall mesh, mm: the marching-cubes "
                        "surface is remeshed to even triangles of this size (default: not "
                        "remeshed, edges of about a voxel)")
    p.add_argument("--smooth", type=int, default=10, metavar="N",
                   help="Taubin smoothing passes (default 10; 0: none)")
    p.add_argument("--separation", type=float, default=2.0, metavar="MM",
                   help="radius of the opening that cuts touching bright structures, mm "
                        "(default 2)")
    p.add_argument("--format", choices=FORMATS, default="stl",
                   help="surface file format (default stl)")
    for flag, text in (("--r", "template arc radius r, mm (benchmark 12)"),
                       ("--a", "template extension a, mm (benchmark 7.1)"),
                       ("--alpha", "template arc angle alpha, degrees (benchmark 160)")):
        p.add_argument(flag, type=float, metavar="FLOAT",
                       help=text + "; the suture paths from nadirs are fitted to the sutured "
                                   "edge 2 a + r alpha")
    p.add_argument("--no-figure", action="store_true", help="skip the QC figure")
    return p


def run(args) -> int:
    from ..errors import ParameterError
    from ..io.files import check_out_dir

    def say(msg):
        print(f"[jaxvalve] {msg}", file=sys.stdout, flush=True)

    out = check_out_dir(args.out)
    for name in ("edge", "separation"):
        v = getattr(args, name)
        if v is not None and not v >= 0:
            raise ParameterError(f"--{name} must be a length >= 0 (mm); got {v}")
    lm = None
    if args.landmarks is not None:                  # bad landmarks fail before the work
        from ..geometry.landmarks import landmarks_from_markups
        from ..io.markups import read_markups
        lm = landmarks_from_markups(read_markups(args.landmarks),
                                    source=f"markups file '{args.landmarks}'")
    sutured = _sutured_length(args)
    try:
        from ..imaging.segment import SegmentParams, segment
        from ..imaging.surface import mesh_quality, wall_surface
        from ..io.volumes import read_volume, write_mask
    except ImportError as e:
        raise ParameterError(f"jaxvalve segment needs the imaging extra (pip install "
                             f"'jaxvalve[imaging]'): {e}") from None
    from ..io.files import write_surface

    times = {}
    t = time.perf_counter()
    say(f"reading {args.ct}")
    vol = read_volume(args.ct)
    times["read_s"] = time.perf_counter() - t
    say(f"volume {vol.shape[0]} x {vol.shape[1]} x {vol.shape[2]} voxels of "
        f"{' x '.join(f'{s:.3g}' for s in vol.spacing)} mm")
    t = time.perf_counter()
    seg = segment(vol, seed=args.seed, params=SegmentParams(separation_mm=args.separation),
                  say=say)
    times["segment_s"] = time.perf_counter() - t
    say("meshing the wall (marching cubes, Taubin smoothing"
        + (f", remeshing to {args.edge:g} mm edges)" if args.edge else ")"))
    t = time.perf_counter()
    P, T = wall_surface(vol, seg, edge_mm=args.edge, smooth_iterations=args.smooth)
    quality = mesh_quality(P, T)
    times["surface_s"] = time.perf_counter() - t
    out.mkdir(parents=True, exist_ok=True)
    written = [write_surface(out / f"root.{args.format}", P, T),
               write_mask(out / "mask.nii.gz", seg.mask, vol)]
    report = {"ct": str(args.ct), "coordinates": "LPS mm", "segmentation": seg.report,
              "surface": {"file": written[0].name, **quality}}
    root = None
    if lm is not None:
        from ..geometry.landmarks import landmarks_to_markups, root_from_landmarks
        from ..io.markups import write_markups
        say("projecting the landmarks onto the wall"
            + ("" if lm.curves is not None else
               f"; fitting the suture paths to the sutured edge ({sutured:.2f} mm)"))
        t = time.perf_counter()
        root, lrep = root_from_landmarks((P, T), lm, sutured_length=sutured, name="patient")
        written.append(write_markups(out / "landmarks.mrk.json",
                                     landmarks_to_markups(root, lrep.get("nadirs"))))
        times["landmarks_s"] = time.perf_counter() - t
        report["landmarks"] = {"file": "landmarks.mrk.json", "source": str(args.landmarks),
                               "sutured_length_mm": sutured, **lrep}
    if not args.no_figure:
        from ..io.qc_figure import segmentation_figure
        say("drawing the QC figure")
        fig = segmentation_figure(vol, seg, (P, T), out / "qc.png", root=root)
        written.append(out / "qc.png")
        import matplotlib.pyplot as plt
        plt.close(fig)
    report["timings"] = times
    (out / "segmentation.json").write_text(json.dumps(report, indent=1, allow_nan=False,
                                                      default=_plain) + "\n")
    written.append(out / "segmentation.json")
    g = report["segmentation"]
    say(f"lumen {g['volume_ml']:.1f} ml, level {g['grow']['threshold_hu']:.0f} HU; wall "
        f"{quality['vertices']} vertices, {quality['triangles']} triangles, edges "
        f"{quality['edge_mm']['mean']:.2f} mm on average")
    say(f"wrote {', '.join(str(w.name) for w in written)} to {out}")
    return 0


def _sutured_length(args):
    from ..errors import ParameterError
    from ..geometry.template import sutured_length
    from ..scene import Scene
    d = Scene()
    r = d.r if args.r is None else args.r
    a = d.a if args.a is None else args.a
    alpha = d.alpha if args.alpha is None else args.alpha
    for name, v, ok, rng in (("r", r, r > 0, "> 0 mm"), ("a", a, a > 0, "> 0 mm"),
                             ("alpha", alpha, 0 < alpha <= 180, "in (0, 180] degrees")):
        if not ok:
            raise ParameterError(f"--{name} = {v:g} must be {rng}")
    return float(sutured_length(r, a, alpha))


def _plain(v):
    import numpy as np
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"cannot write {type(v).__name__} to JSON")
