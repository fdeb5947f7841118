"""A synthetic contrast-enhanced CT (ceCTA) of an asymmetric aortic root, with its true wall.

The lumen is a tube along +z (LPS: z runs from the feet to the head, so the ascending
aorta is at the top of the volume): a left-ventricular outflow tract (radius
``r_lvot``) below a tilted, non-planar annulus, three sinuses of unequal bulge between the
annulus and the sinotubular junction, and the ascending aorta (radius ``r_stj``) above.
Beside the ascending aorta runs a second contrast-filled tube (a pulmonary-artery-like
neighbour) whose lumen comes within ``neighbour_gap`` mm of the aorta's, so that the
blurred image joins the two and the segmentation must separate them.

Intensities (Hounsfield units): blood in the aorta ``blood_hu``, in the neighbour
``neighbour_hu``, a vessel wall of ``wall_mm`` at ``wall_hu``, myocardium round the
outflow tract at ``myocardium_hu``, fat elsewhere at ``fat_hu``; each voxel is the mean
over ``supersample``^3 sub-points (partial volume), blurred by a Gaussian point-spread
function of ``psf_mm`` (standard deviation) and given Gaussian noise of ``noise_hu``.

The truth is the lumen's boundary, the zero level of `RootPhantom.lumen_level` (negative
inside), which `true_wall` meshes finely.  All lengths in mm.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ParameterError
from .volume import Volume

__all__ = ["RootPhantom", "phantom_volume", "true_wall"]


@dataclasses.dataclass(frozen=True)
class RootPhantom:
    """Geometry and intensities of the phantom (module docstring).  Angles in degrees."""

    r_lvot: float = 12.0
    r_stj: float = 13.0
    sinus_height: float = 20.0          # annulus (its mean level, z = 0) to the STJ
    sinus_bulge: tuple = (4.5, 3.2, 2.0)   # the three sinuses' outward bulge, mm
    sinus_angles: tuple = (90.0, 210.0, 330.0)  # their centres
    annulus_tilt: float = 3.0           # the annulus plane's rise across the root, mm
    annulus_tilt_angle: float = 30.0
    annulus_scallop: float = 1.5        # its non-planar wave (three crests), mm
    z_bottom: float = -14.0             # extent of the volume along z
    z_top: float = 40.0
    neighbour_radius: float = 9.0
    neighbour_angle: float = 150.0      # direction of the neighbour from the aortic axis
    neighbour_gap: float = 0.5          # lumen to lumen, mm
    neighbour_from: float = 22.0        # the neighbour spans z >= this
    margin: float = 6.0                 # fat round the outermost structure, mm
    wall_mm: float = 1.5
    myocardium_mm: float = 8.0
    blood_hu: float = 400.0
    neighbour_hu: float = 330.0
    wall_hu: float = 70.0
    myocardium_hu: float = 90.0
    fat_hu: float = -100.0
    psf_mm: float = 0.5
    noise_hu: float = 20.0
    spacing: tuple = (0.4, 0.4, 0.6)
    supersample: int = 3

    def __post_init__(self):
        for name in ("r_lvot", "r_stj", "sinus_height", "neighbour_radius", "wall_mm",
                     "myocardium_mm", "neighbour_gap"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ParameterError(f"phantom {name} must be a positive length (mm); "
                                     f"got {v!r}")
        for name in ("psf_mm", "noise_hu", "margin"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ParameterError(f"phantom {name} must be finite and >= 0; got {v!r}")
        if len(self.spacing) != 3 or not all(np.isfinite(s) and 0.05 <= s <= 5.0
                                             for s in self.spacing):
            raise ParameterError("phantom spacing must be three voxel sizes in "
                                 f"[0.05, 5] mm; got {self.spacing!r}")
        if len(self.sinus_angles) != 3 or not np.all(np.isfinite(self.sinus_angles)):
            raise ParameterError("phantom sinus_angles must be three finite angles (degrees); "
                                 f"got {self.sinus_angles!r}")
        if len(self.sinus_bulge) != 3 or min(self.sinus_bulge) < 0:
            raise ParameterError("phantom sinus_bulge must be three lengths >= 0 (mm); got "
                                 f"{self.sinus_bulge!r}")
        if not (isinstance(self.supersample, int) and 1 <= self.supersample <= 5):
            raise ParameterError("phantom supersample must be an integer in [1, 5]; got "
                                 f"{self.supersample!r}")
        if not self.z_bottom < -abs(self.annulus_tilt) - abs(self.annulus_scallop) - 2.0:
            raise ParameterError("phantom z_bottom must lie at least 2 mm below the annulus "
                                 f"(below {-abs(self.annulus_tilt) - abs(self.annulus_scallop) - 2.0:g} mm);"
                                 f" got {self.z_bottom!r}")
        if not self.z_top > self.sinus_height + 5.0:
            raise ParameterError("phantom z_top must lie at least 5 mm above the sinotubular "
                                 f"junction ({self.sinus_height + 5.0:g} mm); got {self.z_top!r}")

    # ------------------------------------------------------------------ geometry
    def annulus_z(self, theta):
        """z of the annulus (mm) at the angle theta (radians) round the axis."""
        t = np.deg2rad(self.annulus_tilt_angle)
        return (0.5 * self.annulus_tilt * np.cos(theta - t)
                + self.annulus_scallop * np.cos(3.0 * (theta - np.deg2rad(self.sinus_angles[0]))))

    def lumen_radius(self, theta, z):
        """The aortic lumen's radius (mm) at angle theta (radians) and height z (mm)."""
        h = np.clip((z - self.annulus_z(theta)) / self.sinus_height, 0.0, 1.0)
        base = self.r_lvot + (self.r_stj - self.r_lvot) * h
        bulge = np.zeros(np.broadcast(theta, z).shape)
        for amp, ang in zip(self.sinus_bulge, self.sinus_angles):
            d = np.angle(np.exp(1j * (theta - np.deg2rad(ang))))    # in (-pi, pi]
            lobe = np.clip(np.cos(1.5 * d), 0.0, None) ** 2          # zero at +-60 degrees
            bulge = bulge + amp * lobe
        return base + bulge * np.sin(np.pi * h) ** 2

    def lumen_level(self, p):
        """Level function of the aortic lumen at points p (..., 3) mm: rho - R(theta, z),
        negative inside; its zero level is the true wall."""
        p = np.asarray(p, float)
        theta = np.arctan2(p[..., 1], p[..., 0])
        rho = np.hypot(p[..., 0], p[..., 1])
        return rho - self.lumen_radius(theta, p[..., 2])

    def landmarks(self):
        """The true valve landmarks on the wall, mm: ``(commissures (3, 3), nadirs (3,
        3))``.  The commissures stand at the sinotubular junction midway (in angle)
        between neighbouring sinuses, the nadirs at the annulus below each sinus's
        centre; commissure i and i + 1 flank nadir i, counter-clockwise seen from the
        aorta (increasing angle about +z)."""
        ang = np.sort(np.deg2rad(np.asarray(self.sinus_angles, float)) % (2 * np.pi))
        gaps = np.diff(np.concatenate([ang, ang[:1] + 2 * np.pi]))
        com_t = ang - 0.5 * np.roll(gaps, 1)        # between sinus i - 1 and sinus i
        z_c = self.annulus_z(com_t) + self.sinus_height
        z_n = self.annulus_z(ang)

        def at(t, z):
            r = self.lumen_radius(t, z)
            return np.stack([r * np.cos(t), r * np.sin(t), z], -1)
        return at(com_t, z_c), at(ang, z_n)

    def neighbour_centre(self):
        d = self.r_stj + self.neighbour_gap + self.neighbour_radius
        a = np.deg2rad(self.neighbour_angle)
        return np.array([d * np.cos(a), d * np.sin(a)])

    def neighbour_level(self, p):
        """Level function of the neighbour's lumen (negative inside): a vertical tube
        from z = neighbour_from up."""
        p = np.asarray(p, float)
        c = self.neighbour_centre()
        radial = np.hypot(p[..., 0] - c[0], p[..., 1] - c[1]) - self.neighbour_radius
        return np.maximum(radial, self.neighbour_from - p[..., 2])

    def extent(self):
        """(lo, hi) corners of the imaged box, mm."""
        c = self.neighbour_centre()
        reach = self.r_stj + max(self.sinus_bulge) + self.wall_mm + self.myocardium_mm
        lo = np.minimum([-reach, -reach], c - self.neighbour_radius - self.wall_mm)
        hi = np.maximum([reach, reach], c + self.neighbour_radius + self.wall_mm)
        return (np.array([*(lo - self.margin), self.z_bottom]),
                np.array([*(hi + self.margin), self.z_top]))

    def intensity(self, p):
        """Noise- and blur-free HU at points p (..., 3) mm."""
        f = self.lumen_level(p)
        g = self.neighbour_level(p)
        below = p[..., 2] < self.annulus_z(np.arctan2(p[..., 1], p[..., 0])) + 2.0
        hu = np.full(f.shape, self.fat_hu)
        hu = np.where(below & (f < self.wall_mm + self.myocardium_mm), self.myocardium_hu, hu)
        hu = np.where((f < self.wall_mm) | (g < self.wall_mm), self.wall_hu, hu)
        hu = np.where(g < 0, self.neighbour_hu, hu)
        return np.where(f < 0, self.blood_hu, hu)


def phantom_volume(phantom: RootPhantom | None = None, *, seed: int = 0) -> Volume:
    """The phantom's CT volume (`Volume`, HU, LPS mm): partial volume by supersampling,
    Gaussian blur, Gaussian noise (``seed``)."""
    from scipy import ndimage
    ph = RootPhantom() if phantom is None else phantom
    lo, hi = ph.extent()
    sp = np.asarray(ph.spacing, float)
    shape = tuple(int(n) for n in np.floor((hi - lo) / sp) + 1)
    s = ph.supersample
    offs = (np.arange(s) + 0.5) / s - 0.5           # sub-voxel offsets, in voxels
    axes = [lo[i] + sp[i] * np.arange(shape[i]) for i in range(3)]
    data = np.empty(shape, np.float32)
    # slab by slab along z keeps the memory of the supersampled points small
    X, Y = np.meshgrid(axes[0], axes[1], indexing="ij")
    for k, z in enumerate(axes[2]):
        acc = np.zeros(X.shape)
        for ox in offs:
            for oy in offs:
                for oz in offs:
                    pts = np.stack([X + ox * sp[0], Y + oy * sp[1],
                                    np.full(X.shape, z + oz * sp[2])], axis=-1)
                    acc += ph.intensity(pts)
        data[:, :, k] = acc / s ** 3
    if ph.psf_mm > 0:
        data = ndimage.gaussian_filter(data, sigma=ph.psf_mm / sp, mode="nearest")
    if ph.noise_hu > 0:
        data = data + np.random.default_rng(seed).normal(0.0, ph.noise_hu, shape)
    affine = np.eye(4)
    affine[:3, :3] = np.diag(sp)
    affine[:3, 3] = lo
    return Volume(np.asarray(data, np.float32), affine)


def true_wall(phantom: RootPhantom | None = None, *, step: float = 0.25):
    """The true wall, the zero level of `RootPhantom.lumen_level` within the imaged box,
    meshed by marching cubes on a grid of ``step`` mm: (points (P, 3) mm, triangles
    (T, 3)), an open tube (no caps at the box's ends)."""
    from skimage import measure
    ph = RootPhantom() if phantom is None else phantom
    lo, hi = ph.extent()
    axes = [np.arange(lo[i], hi[i] + 0.5 * step, step) for i in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    level = ph.lumen_level(P)
    pts, tris, _, _ = measure.marching_cubes(level, 0.0, spacing=(step,) * 3,
                                             allow_degenerate=False)
    return pts + lo, tris.astype(np.int64)
