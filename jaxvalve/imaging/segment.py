"""Segmentation of the contrast-filled aortic root and ascending aorta in a ceCTA volume,
after the paper's pipeline (its Section 2):

1. **Seed** (`find_seed`): the ascending aorta is the brightest large circle on a top
   axial slice: a Hough circle transform (scikit-image) of the slice's edges over radii
   ``radius_mm``, keeping circles whose mean intensity is blood's; the largest of the
   strong ones is the aorta and its centre the seed.  A seed can be given instead.
2. **Region growing** (`segment`): the voxels connected to the seed whose (lightly
   smoothed) intensity lies in a window from the half-maximum level between the blood
   at the seed and the vessel wall (``wall_hu``) up to ``max_hu`` (calcium and metal
   above it are left out).  The half-maximum level puts the lumen's boundary where a
   blurred step between blood and wall crosses half its height.
3. **Separation**: bright neighbours that touch the aorta in the image (the pulmonary
   artery, the left atrium) join it through thin bridges of partial-volume voxels; an
   opening (erosion by a ball of ``separation_mm``, the seed's connected component,
   dilation by the same ball, within the grown region) cuts bridges thinner than twice
   that radius and keeps the aorta, with the top of the outflow tract that it opens
   into, as the paper's mask M_a does.

Every parameter, and what each step kept, is recorded in `Segmentation.report` for the
output JSON.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ParameterError
from .volume import Volume

__all__ = ["SegmentParams", "Segmentation", "find_seed", "segment"]


@dataclasses.dataclass(frozen=True)
class SegmentParams:
    """top_offset: slices below the top one where the aorta is sought (the topmost slices
    can be cut obliquely).  radius_mm: the range of the ascending aorta's radius.
    min_blood_hu: the least mean HU of a circle taken for contrast blood.  wall_hu: the
    vessel wall's HU (the lower end of the half-maximum level).  max_hu: the upper end of
    the blood window.  smooth_mm: Gaussian pre-smoothing (standard deviation) against
    noise.  separation_mm: the opening's ball radius."""

    top_offset: int = 3
    radius_mm: tuple = (8.0, 20.0)
    min_blood_hu: float = 150.0
    wall_hu: float = 80.0
    max_hu: float = 1000.0
    smooth_mm: float = 0.4
    separation_mm: float = 2.0

    def __post_init__(self):
        if not (isinstance(self.top_offset, int) and self.top_offset >= 0):
            raise ParameterError(f"top_offset must be an integer >= 0; got {self.top_offset!r}")
        lo, hi = self.radius_mm
        if not (np.isfinite(lo) and np.isfinite(hi) and 1.0 <= lo < hi <= 50.0):
            raise ParameterError(f"radius_mm must be (lo, hi) with 1 <= lo < hi <= 50 mm; got "
                                 f"{self.radius_mm!r}")
        if not (np.isfinite(self.wall_hu) and np.isfinite(self.min_blood_hu)
                and self.wall_hu < self.min_blood_hu < self.max_hu):
            raise ParameterError("the intensity levels must satisfy wall_hu < min_blood_hu < "
                                 f"max_hu; got {self.wall_hu!r}, {self.min_blood_hu!r}, "
                                 f"{self.max_hu!r}")
        for name in ("smooth_mm", "separation_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= 10.0):
                raise ParameterError(f"{name} must lie in [0, 10] mm; got {v!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class Segmentation:
    """mask (I, J, K) bool: the aorta's lumen.  seed (3,) int: its voxel.  threshold:
    the lower level of the window, HU.  image (I, J, K) float32: the smoothed image that
    was thresholded (the surface is its level set).  report: the steps' parameters and
    results."""

    mask: np.ndarray
    seed: np.ndarray
    threshold: float
    image: np.ndarray
    report: dict


def _slice(volume: Volume, offset: int):
    """The top axial slice ``offset`` slices down: (index along the axial axis, 2D image,
    the two in-plane axes)."""
    ax, sign = volume.axial_axis()
    n = volume.shape[ax]
    if offset >= n:
        raise ParameterError(f"top_offset {offset} must be below the {n} axial slices")
    k = n - 1 - offset if sign > 0 else offset
    return k, np.take(volume.data, k, axis=ax), [a for a in range(3) if a != ax]


def find_seed(volume: Volume, params: SegmentParams = SegmentParams()):
    """The ascending aorta on a top axial slice (module docstring, step 1): (seed voxel
    (3,) int, a dict of the circle: centre (mm), radius (mm), mean HU, Hough score, and the
    candidates considered)."""
    from skimage.feature import canny
    from skimage.transform import hough_circle, hough_circle_peaks
    k, img, inplane = _slice(volume, params.top_offset)
    px = float(np.mean(volume.spacing[inplane]))
    radii = np.arange(max(2, int(params.radius_mm[0] / px)),
                      int(np.ceil(params.radius_mm[1] / px)) + 1)
    edges = canny(np.asarray(img, float), sigma=max(1.0, 1.0 / px))
    acc = hough_circle(edges, radii, normalize=True)
    score, cx, cy, rad = hough_circle_peaks(acc, radii, total_num_peaks=12,
                                            min_xdistance=int(radii[0]),
                                            min_ydistance=int(radii[0]))
    ii, jj = np.meshgrid(np.arange(img.shape[0]), np.arange(img.shape[1]), indexing="ij")
    cands = []
    for s, x, y, r in zip(score, cx, cy, rad):
        # hough_circle_peaks returns (column, row) = (second, first) image index
        disc = (ii - y) ** 2 + (jj - x) ** 2 <= (0.7 * r) ** 2
        cands.append(dict(score=float(s), row=int(y), col=int(x), radius_mm=float(r * px),
                          mean_hu=float(np.mean(img[disc]))))
    bright = [c for c in cands if c["mean_hu"] >= params.min_blood_hu]
    if not bright:
        raise ParameterError(f"no bright circle of radius {params.radius_mm[0]:g}-"
                             f"{params.radius_mm[1]:g} mm with a mean of at least "
                             f"{params.min_blood_hu:g} HU on the axial slice {k}: is this a "
                             "contrast-enhanced scan with the aorta at the top? (give the "
                             "seed point instead)")
    top = max(c["score"] for c in bright)
    strong = [c for c in bright if c["score"] >= 0.5 * top]
    best = max(strong, key=lambda c: (c["radius_mm"], c["mean_hu"]))
    seed = np.zeros(3, int)
    seed[[a for a in range(3) if a not in inplane][0]] = k
    seed[inplane[0]], seed[inplane[1]] = best["row"], best["col"]
    info = dict(slice=int(k), centre_mm=volume.to_world(seed).tolist(),
                radius_mm=best["radius_mm"], mean_hu=best["mean_hu"], score=best["score"],
                candidates=cands)
    return seed, info


def _ball(spacing, radius_mm):
    """A boolean ball of radius_mm on the voxel grid of ``spacing`` (anisotropic)."""
    n = np.maximum(np.floor(radius_mm / np.asarray(spacing)), 0).astype(int)
    g = np.meshgrid(*[np.arange(-m, m + 1) * s for m, s in zip(n, spacing)], indexing="ij")
    return sum(x ** 2 for x in g) <= radius_mm ** 2 + 1e-9


def segment(volume: Volume, seed=None, params: SegmentParams = SegmentParams(),
            say=lambda msg: None) -> Segmentation:
    """The aortic lumen's mask (module docstring).  seed: a voxel index (3,) or None to
    find it (`find_seed`).  say: progress, one line a step."""
    from scipy import ndimage
    report = dict(params=dataclasses.asdict(params), spacing_mm=volume.spacing.tolist(),
                  shape=list(volume.shape))
    if seed is None:
        say("finding the ascending aorta (Hough circle on a top axial slice)")
        seed, circle = find_seed(volume, params)
        report["seed"] = dict(source="hough", voxel=seed.tolist(), **circle)
    else:
        seed = np.asarray(seed)
        if seed.shape != (3,) or not np.all((seed >= 0) & (seed < volume.shape)):
            raise ParameterError(f"seed must be a voxel index inside the volume "
                                 f"{volume.shape}; got {seed.tolist()}")
        seed = seed.astype(int)
        report["seed"] = dict(source="given", voxel=seed.tolist(),
                              centre_mm=volume.to_world(seed).tolist())
    data = np.asarray(volume.data, np.float32)
    if params.smooth_mm > 0:
        data = ndimage.gaussian_filter(data, params.smooth_mm / volume.spacing)
    # the blood's level: the median within 3 mm of the seed
    r = np.ceil(3.0 / volume.spacing).astype(int)
    lo, hi = np.maximum(seed - r, 0), np.minimum(seed + r + 1, volume.shape)
    g = np.meshgrid(*[(np.arange(a, b) - c) * d for a, b, c, d
                      in zip(lo, hi, seed, volume.spacing)], indexing="ij")
    near = sum(x ** 2 for x in g) <= 9.0
    blood = float(np.median(data[tuple(slice(a, b) for a, b in zip(lo, hi))][near]))
    if blood < params.min_blood_hu:
        raise ParameterError(f"the seed {seed.tolist()} lies in {blood:.0f} HU, below "
                             f"min_blood_hu = {params.min_blood_hu:g}: not in contrast blood")
    threshold = 0.5 * (blood + params.wall_hu)
    say(f"growing the region from the seed: {threshold:.0f} to {params.max_hu:g} HU "
        f"(blood {blood:.0f} HU)")
    window = (data >= threshold) & (data <= params.max_hu)
    six = ndimage.generate_binary_structure(3, 1)
    lab, _ = ndimage.label(window, structure=six)
    grown = lab == lab[tuple(seed)]
    report["grow"] = dict(blood_hu=blood, threshold_hu=threshold, voxels=int(grown.sum()))
    mask = grown
    if params.separation_mm > 0:
        say(f"separating touching bright structures (opening, {params.separation_mm:g} mm)")
        ball = _ball(volume.spacing, params.separation_mm)
        core = ndimage.binary_erosion(grown, structure=ball)
        lab, _ = ndimage.label(core, structure=six)
        if lab[tuple(seed)] == 0:
            raise ParameterError(f"the opening of {params.separation_mm:g} mm removed the "
                                 "seed's neighbourhood: lower separation_mm")
        core = lab == lab[tuple(seed)]
        mask = ndimage.binary_dilation(core, structure=ball) & grown
    report["separate"] = dict(voxels=int(mask.sum()),
                              removed_voxels=int(grown.sum() - mask.sum()))
    report["volume_ml"] = float(mask.sum() * np.prod(volume.spacing) / 1000.0)
    return Segmentation(mask=mask, seed=seed, threshold=threshold, image=data, report=report)
