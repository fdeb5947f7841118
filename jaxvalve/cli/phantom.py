"""Write the synthetic patient-like ceCTA scan (an asymmetric aortic root with unequal
sinuses, a tilted non-planar annulus and a touching bright neighbour;
`jaxvalve.imaging.phantom`) as DIR/ct.nii.gz, with its true commissures and nadirs as a
3D Slicer markups file DIR/landmarks_true.mrk.json (LPS mm).  A scan to try
`jaxvalve segment` on.  Needs the extra `pip install jaxvalve[imaging]`.
"""
from __future__ import annotations

import sys


def add_parser(sub):
    p = sub.add_parser("phantom", help="write a synthetic CT scan of an asymmetric aortic root",
                       description=__doc__, allow_abbrev=False,
                       epilog="Example: jaxvalve phantom --out scan && jaxvalve segment "
                              "scan/ct.nii.gz --out patient --landmarks "
                              "scan/landmarks_true.mrk.json")
    p.add_argument("--out", metavar="DIR", required=True, help="output folder")
    p.add_argument("--spacing", type=float, nargs=3, default=(0.4, 0.4, 0.6),
                   metavar=("X", "Y", "Z"), help="voxel size, mm (default 0.4 0.4 0.6)")
    p.add_argument("--noise", type=float, default=20.0, metavar="HU",
                   help="Gaussian noise, HU (default 20)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    return p


def run(args) -> int:
    import numpy as np

    from ..errors import ParameterError
    from ..io.files import check_out_dir
    from ..io.markups import Markup, write_markups
    out = check_out_dir(args.out)
    try:
        from ..imaging.phantom import RootPhantom, phantom_volume
        from ..io.volumes import write_volume
    except ImportError as e:
        raise ParameterError(f"jaxvalve phantom needs the imaging extra (pip install "
                             f"'jaxvalve[imaging]'): {e}") from None
    ph = RootPhantom(spacing=tuple(args.spacing), noise_hu=args.noise)
    print(f"[jaxvalve] building the phantom scan ({args.spacing[0]:g} x {args.spacing[1]:g} "
          f"x {args.spacing[2]:g} mm voxels, noise {args.noise:g} HU)", flush=True)
    vol = phantom_volume(ph, seed=args.seed)
    out.mkdir(parents=True, exist_ok=True)
    ct = write_volume(out / "ct.nii.gz", vol)
    com, nad = ph.landmarks()
    lm = write_markups(out / "landmarks_true.mrk.json", [Markup(
        "Fiducial", [f"C{i + 1}" for i in range(3)] + [f"N{i + 1}" for i in range(3)],
        np.concatenate([com, nad]), "valve landmarks (true)")])
    print(f"[jaxvalve] wrote {ct.name} ({vol.shape[0]} x {vol.shape[1]} x {vol.shape[2]} "
          f"voxels) and {lm.name} to {out}", file=sys.stdout, flush=True)
    return 0
