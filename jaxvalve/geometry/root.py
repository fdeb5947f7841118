"""The aortic root as data (`AorticRoot`) and the parametric benchmark root (`benchmark_root`).

Conventions (units mm)
----------------------
* ``axis`` is a unit vector pointing from the aorta to the ventricle (the systolic flow runs
  against it).  ``origin`` is a point on the axis.  The *axial coordinate* of a point p is
  ``(p - origin) . axis``: larger means more ventricular ("lower").
* Three commissures, ordered counter-clockwise seen from the aorta, i.e. by increasing polar
  angle about ``-axis`` (about +z for the benchmark, whose axis is (0, 0, -1)).
* Leaflet i spans commissure i -> commissure (i+1) % 3.  Its suturing path is a polyline on
  the aortic wall from commissure i down through its nadir (its most ventricular point) up
  to commissure i+1: ``paths[i][0] == commissures[i]``, ``paths[i][-1] ==
  commissures[(i+1) % 3]`` (exactly; endpoints within the tolerance are snapped).
* The annulus plane is normal to the axis through the three lowest path points
  (docs/metrics.md, effective height).  Its axial coordinate is `AorticRoot.annulus_level`.

Benchmark root (`benchmark_root`)
---------------------------------
The paper's benchmark (Section 3.1) is Marom et al.'s healthy valve with annulus diameter
d_AA = 24 mm; its other dimensions are not published with the benchmark, so they are chosen
here from published proportions.  Frame: axis (0, 0, -1), origin (0, 0, 0), z towards the
aorta, annulus plane z = 0.  Every number and its reason:

==========================  ===========  ==================================================
dimension                   default      reason
==========================  ===========  ==================================================
annulus diameter d_AA       24 mm        the benchmark (Marom et al.); the annulus is the
                                         circle of radius R_a = 12 mm at z = 0 through the
                                         three nadirs (the virtual basal ring).
STJ diameter d_STJ          26 mm        DESIGN: "a few mm wider than the annulus"; Marom
                                         et al. ("Systematic adjustment of root dimensions
                                         to cusp size in aortic valve repair") find the
                                         best closure with the STJ 2-4 mm wider than the
                                         annulus.  We take the lower end (R_c = 13 mm),
                                         which is also the closest to Labrosse et al. 2006
                                         (commissure radius 12 < base radius 13).
commissures                 at the STJ   DESIGN; at radius R_c, height H_c, polar angles
                                         ``first_commissure_angle + 120 deg * i``
                                         (default 0: commissure 0 on +x).
commissure height H_c       FITTED       the one shape parameter solved for, so that the
                                         path length equals the sutured length (below).
sinus height                = H_c        the STJ is at the commissure level; anatomical
                                         reference: sinus height / annulus radius =
                                         1.69 +- 0.18 (CT, 150 patients; DESIGN's "about
                                         1.7 annulus radii"), i.e. 20.3 +- 2.2 mm here.
path surface                cone         each path lies on the cone r(z) = R_a + (R_c -
                                         R_a) z / H_c joining the annulus circle to the STJ
                                         circle; the sinuses bulge *above* the paths (the
                                         paper's Fig. 1: "aortic sinuses are between
                                         suturing path and sinotubular junction").
path shape exponent p       4            see "path family" below.
sinus max radius R_s        1.45 R_a     DESIGN (Reul et al. 1990 proportions): 17.4 mm,
                            = 17.4 mm    reached at mid-sinus angle and half the sinus
                                         height.
LVOT stub (display)         2 mm         cylinder of radius R_a below the annulus.
ascending aorta (display)   10 mm        tube of radius R_c above the STJ.
==========================  ===========  ==================================================

Path family.  Let s in [-1, 1] be the polar angle from the leaflet's mid-plane in units of
60 degrees (s = -1, +1 at its commissures) and zeta = z / H_c.  The path is the power-law U
``zeta = |s|^p`` on the cone above: flat at the nadir (s = 0, z = 0, r = R_a), rising ever
more steeply to the commissures, which it reaches at a finite angle beta from the axial
direction, tan(beta) = (pi R_c / 3) / (p H_c) on the developed wall.  Neighbouring paths
thus enclose the interleaflet triangles (apex angle 2 beta, about 4.3 mm wide at half the
commissure height).  p = 4 makes beta = 10.7 / 9.3 / 8.2 / 7.4 degrees for L = 50 / 55 /
60 / 65 mm, close to the 10 degrees by which the Ozaki template's straight segments A-B and
C-D lean off the vertical (alpha = 160 degrees), so the straight parts of the sutured edge
run along path segments of about their own inclination.  Sampled at ``n_path`` points
uniformly in s (odd, so the nadir is a sample); `AorticRoot.resample_path` gives uniform
arc-length points.

Which parameter is fitted, and why.  With p and the radii fixed, every segment of the
sampled polyline has length sqrt(a_k^2 + H_c^2 b_k^2) (the polar angle and radius of each
sample do not depend on H_c), so the polyline length L(H_c) is strictly increasing: the
commissure height that matches a sutured length is unique, and `scipy.optimize.brentq`
finds it to 1e-9 relative in L.  It is searched in [0.5 R_a, 3 R_a] = [6, 36] mm (lengths
30.5-83.3 mm with the defaults, `benchmark_length_range`); outside, `benchmark_root` raises
`ParameterError` naming ``sutured_length``.  (Fitting the shape exponent at a fixed
commissure height 1.7 R_a instead cannot reach 65 mm: the length tends to ~61 mm as p
grows.)

Results and a geometric bound.  With the defaults, L = 50 / 55 / 60 / 65 mm gives
H_c = 18.08 / 20.86 / 23.60 / 26.30 mm = 1.51 / 1.74 / 1.97 / 2.19 R_a (measured sinus
height 1.69 +- 0.18 R_a: -1.0 / +0.3 / +1.5 / +2.8 sd).  Lower commissures need squarer
paths: p = 2 / 3 / 6 / 8 give 23.1 / 21.8 / 19.6 / 18.9 mm at 55 mm and 25.9 / 24.6 /
22.3 / 21.5 mm at 60 mm.  No shape does much better: a path on this wall spanning 120
degrees and rising H_c on both sides is at most about 2 H_c + (2 pi / 3) R_c long (a
rectangle with vertical sides, where neighbouring leaflets would be sewn along the same
line), so H_c >= (L - 27.2 mm) / 2, i.e. >= 14 / 16.4 / 19 mm for 55 / 60 / 65 mm.  Long
sutured edges in a 24 mm root therefore mean tall commissures; the sutured length is the
leaflet designer's (and optimiser's) choice, and `dimensions` records the height obtained.

Wall.  For display (and for checking that paths lie on it) the benchmark carries a
structured (theta, z) triangle mesh: the LVOT stub, the cone r_cone(z) below each path
(the interleaflet triangles), three sinus bulges above the paths,
``r = r_cone(z) + D cos^2(pi s / 2) sin^2(pi t)``, t = (z - z_path(s)) / (H_c - z_path(s)),
D = R_s - (R_a + R_c) / 2, up to the STJ, and the ascending-aorta tube.  The bulge is zero
with zero slope on the path, so the paths lie exactly on the continuous wall; on the
triangulated wall (1 degree x ~0.25 mm cells) they lie within ~0.005 mm (tested < 0.02
mm).  Triangles are oriented with normals pointing away from the axis.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy.optimize import brentq

from ..errors import MeshError, ParameterError
from .surface_query import distance_to_surface

__all__ = [
    "AorticRoot",
    "benchmark_root",
    "benchmark_path_length",
    "benchmark_length_range",
    "distance_to_surface",
    "BENCHMARK_HEIGHT_RANGE",
]

#: Commissure heights searched by `benchmark_root`, in annulus radii.
BENCHMARK_HEIGHT_RANGE = (0.5, 3.0)
#: Path endpoints may differ from the commissures by this much, relative to the root's size
#: (at least this many mm); they are then snapped onto the commissures.
ENDPOINT_RTOL = 1e-6


def _fmt(x):
    return np.array2string(np.asarray(x), precision=6, separator=", ")


def _as_points(value, field, shape_desc, rows=None):
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParameterError(f"{field} must be a numeric array of shape {shape_desc}; "
                             f"it could not be converted ({e})") from None
    if a.ndim != 2 or a.shape[1] != 3 or (rows is not None and a.shape[0] != rows):
        raise ParameterError(f"{field} must have shape {shape_desc}; got {a.shape}")
    if not np.all(np.isfinite(a)):
        k = int(np.argwhere(~np.isfinite(a))[0][0])
        raise ParameterError(f"{field} holds a non-finite value (NaN or inf) in row {k}; "
                             "every coordinate must be finite")
    return a


def _as_vector(value, field):
    try:
        v = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ParameterError(f"{field} must be 3 numbers; it could not be converted ({e})") \
            from None
    if v.shape != (3,):
        raise ParameterError(f"{field} must have shape (3,); got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ParameterError(f"{field} = {_fmt(v)} holds a non-finite value; it must be finite")
    return v


def _readonly(a):
    a = np.array(a)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class AorticRoot:
    """An aortic root: valve axis, commissures, suturing paths and (optionally) the wall.

    axis (3,): unit vector from the aorta to the ventricle (normalised on construction).
    origin (3,): a point on the valve axis.
    commissures (3, 3): counter-clockwise seen from the aorta.
    paths: 3 arrays (K_i, 3), K_i >= 3; path i runs commissure i -> nadir -> commissure
        (i+1) % 3, no repeated consecutive points.
    wall: optional ``(points (P, 3), triangles (Q, 3))`` surface for display and checks.
    name: a label.  dimensions: optional dict of the documented numbers used to build it.

    Arrays are stored as read-only float64 (triangles int32).  Construction validates every
    field (`validate`) and raises `ParameterError` / `MeshError` naming the field and rule.
    """

    axis: Any
    origin: Any
    commissures: Any
    paths: Any
    wall: Any = None
    name: str = "root"
    dimensions: Any = None

    def __post_init__(self):
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self):
        """Check (and normalise) every field; called on construction."""
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731  (frozen dataclass)
        axis = _as_vector(self.axis, "axis")
        norm = float(np.linalg.norm(axis))
        if not norm > 1e-12:
            raise ParameterError(f"axis = {_fmt(axis)} has zero length; it must be a non-zero "
                                 "vector pointing from the aorta to the ventricle")
        axis = axis / norm
        origin = _as_vector(self.origin, "origin")
        com = _as_points(self.commissures, "commissures", "(3, 3)", rows=3)

        paths = self.paths
        if isinstance(paths, np.ndarray) and paths.dtype != object:
            paths = list(paths)
        if not isinstance(paths, (list, tuple)) or len(paths) != 3:
            n = len(paths) if hasattr(paths, "__len__") else "a non-sequence"
            raise ParameterError(f"paths must be a sequence of 3 polylines (one per leaflet); "
                                 f"got {n}")
        paths = [_as_points(p, f"paths[{i}]", "(K, 3) with K >= 3") for i, p in enumerate(paths)]
        for i, p in enumerate(paths):
            if p.shape[0] < 3:
                raise ParameterError(f"paths[{i}] has {p.shape[0]} points; a suturing path "
                                     "needs at least 3 (commissure, nadir, commissure)")
        scale = max(1.0, float(np.max(np.ptp(np.concatenate(paths + [com]), axis=0))))
        tol = ENDPOINT_RTOL * scale
        for i in range(3):
            for end, k in ((0, i), (-1, (i + 1) % 3)):
                d = float(np.linalg.norm(paths[i][end] - com[k]))
                if d > tol:
                    which = "first" if end == 0 else "last"
                    raise ParameterError(
                        f"paths[{i}] must run from commissures[{i}] to commissures[{(i + 1) % 3}]"
                        f": its {which} point {_fmt(paths[i][end])} is {d:.3e} mm from "
                        f"commissures[{k}] = {_fmt(com[k])} (tolerance {tol:.1e} mm)")
            paths[i][0], paths[i][-1] = com[i], com[(i + 1) % 3]
            seg = np.linalg.norm(np.diff(paths[i], axis=0), axis=1)
            if np.any(seg <= 1e-12 * scale):
                k = int(np.argmin(seg))
                raise MeshError(f"paths[{i}] repeats a point: points {k} and {k + 1} coincide "
                                f"({_fmt(paths[i][k])}); consecutive path points must differ")
        for i in range(3):
            j = (i + 1) % 3
            if np.linalg.norm(com[i] - com[j]) <= 1e-9 * scale:
                raise ParameterError(f"commissures[{i}] and commissures[{j}] coincide; the "
                                     "three commissures must be distinct")
        # orientation: most ventricular point of each path strictly below its commissures
        for i, p in enumerate(paths):
            ax = (p - origin) @ axis
            k = int(np.argmax(ax))
            if not (0 < k < len(p) - 1 and ax[k] > max(ax[0], ax[-1]) + 1e-9 * scale):
                raise ParameterError(
                    f"paths[{i}] must dip from its commissures towards the ventricle: its most "
                    f"ventricular point (largest (p - origin) . axis) is "
                    f"{'an endpoint' if k in (0, len(p) - 1) else 'not below its ends'}; check "
                    "that axis points from the aorta to the ventricle")
        up = -axis
        turn = float(np.cross(com[1] - com[0], com[2] - com[0]) @ up)
        if not turn > 0:
            raise ParameterError(
                "commissures must be ordered counter-clockwise seen from the aorta (increasing "
                "polar angle about -axis); they are clockwise or collinear "
                f"(orientation {turn:.3e} mm^2): reorder them and their paths, or check axis")

        wall = self.wall
        if wall is not None:
            if not isinstance(wall, (tuple, list)) or len(wall) != 2:
                raise MeshError("wall must be None or a pair (points (P, 3), triangles (Q, 3))")
            wp = _as_points(wall[0], "wall points", "(P, 3)")
            wt = np.asarray(wall[1])
            if wt.ndim != 2 or wt.shape[1] != 3 or wt.shape[0] == 0:
                raise MeshError(f"wall triangles must have shape (Q, 3) with Q >= 1; "
                                f"got {wt.shape}")
            if not np.issubdtype(wt.dtype, np.integer):
                if not (np.all(np.isfinite(wt)) and np.all(wt == np.round(wt))):
                    raise MeshError("wall triangles must hold integer point indices")
            wt = wt.astype(np.int64)
            if wt.min() < 0 or wt.max() >= len(wp):
                raise MeshError(f"wall triangle indices must lie in [0, {len(wp) - 1}]; found "
                                f"[{wt.min()}, {wt.max()}]")
            wall = (_readonly(wp), _readonly(wt.astype(np.int32)))
        if not isinstance(self.name, str):
            raise ParameterError(f"name must be a str; got {type(self.name).__name__}")
        dims = self.dimensions
        if dims is not None:
            if not isinstance(dims, dict):
                raise ParameterError(f"dimensions must be a dict or None; got "
                                     f"{type(dims).__name__}")
            dims = dict(dims)
        set_("axis", _readonly(axis))
        set_("origin", _readonly(origin))
        set_("commissures", _readonly(com))
        set_("paths", tuple(_readonly(p) for p in paths))
        set_("wall", wall)
        set_("dimensions", dims)
        return self

    # ------------------------------------------------------------------ geometry
    def axial(self, p):
        """Axial coordinate(s) ``(p - origin) . axis`` of points (..., 3); larger = lower."""
        return (np.asarray(p, dtype=np.float64) - self.origin) @ self.axis

    def radial(self, p):
        """Distance(s) of points (..., 3) from the valve axis."""
        d = np.asarray(p, dtype=np.float64) - self.origin
        perp = d - (d @ self.axis)[..., None] * self.axis
        return np.linalg.norm(perp, axis=-1)

    @property
    def path_lengths(self):
        """Polyline lengths (3,) of the suturing paths, mm."""
        return np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in self.paths])

    @property
    def lowest_points(self):
        """(3, 3): the most ventricular vertex (largest axial coordinate) of each path."""
        return np.stack([p[int(np.argmax(self.axial(p)))] for p in self.paths])

    @property
    def annulus_level(self):
        """Axial coordinate of the annulus plane (normal to the axis).

        The plane passes through the three lowest path points; when they are not at the same
        level (an asymmetric root) it is the plane normal to the axis at their *mean* axial
        coordinate (a plane through three points at different levels would not be normal to
        the axis).  The spread is `annulus_spread`.
        """
        return float(np.mean(self.axial(self.lowest_points)))

    @property
    def annulus_spread(self):
        """max - min axial coordinate of the three lowest points (0 for a planar annulus)."""
        a = self.axial(self.lowest_points)
        return float(a.max() - a.min())

    @property
    def commissure_heights(self):
        """(3,) heights of the commissures above the annulus plane (towards the aorta)."""
        return self.annulus_level - self.axial(self.commissures)

    def commissure_distance(self, i):
        """Distance between commissures i and (i+1) % 3: the chord spanned by leaflet i."""
        i = self._leaflet(i)
        return float(np.linalg.norm(self.commissures[(i + 1) % 3] - self.commissures[i]))

    def resample_path(self, i, n):
        """n points uniformly spaced by arc length along path i (exact on the polyline).

        Returns ``(points (n, 3), s (n,))`` with s the arc length from commissure i
        (s[0] = 0, s[-1] = path length); the end points are exactly the commissures.
        """
        i = self._leaflet(i)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
            raise ParameterError(f"n = {n!r} must be an integer >= 2 (points on the path)")
        p = self.paths[i]
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.linspace(0.0, cum[-1], int(n))
        k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        w = ((s - cum[k]) / seg[k])[:, None]
        out = (1.0 - w) * p[k] + w * p[k + 1]
        out[0], out[-1] = p[0], p[-1]
        return out, s

    def transformed(self, R, t=(0.0, 0.0, 0.0)):
        """The root moved by the rigid motion x -> R x + t (R a proper rotation)."""
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ParameterError(f"R must be a finite (3, 3) rotation matrix; got shape {R.shape}")
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-10) and np.linalg.det(R) > 0):
            raise ParameterError("R must be a proper rotation (R^T R = I, det R = +1); "
                                 "reflections would reverse the commissure order")
        t = _as_vector(t, "t")
        move = lambda x: np.asarray(x) @ R.T + t  # noqa: E731
        wall = None if self.wall is None else (move(self.wall[0]), self.wall[1])
        return AorticRoot(axis=R @ self.axis, origin=move(self.origin),
                          commissures=move(self.commissures),
                          paths=tuple(move(p) for p in self.paths), wall=wall, name=self.name,
                          dimensions=self.dimensions)

    def wall_distance(self, points=None):
        """Distance (mm) of points (default: all path vertices, stacked) to the wall mesh."""
        if self.wall is None:
            raise ParameterError("wall_distance needs a wall surface; this root has wall=None")
        pts = np.concatenate(self.paths) if points is None else points
        return distance_to_surface(pts, *self.wall)

    def _leaflet(self, i):
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i <= 2:
            raise ParameterError(f"leaflet index i = {i!r} must be 0, 1 or 2")
        return int(i)

    def __repr__(self):
        k = [len(p) for p in self.paths]
        w = "none" if self.wall is None else f"{len(self.wall[0])} points"
        return (f"AorticRoot(name={self.name!r}, path points={k}, path lengths="
                f"{np.round(self.path_lengths, 3).tolist()} mm, wall={w})")


# ====================================================================== benchmark root
def _check_positive(name, v):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)) or not float(v) > 0:
        raise ParameterError(f"{name} = {v!r} must be a finite number > 0")
    return float(v)


def _check_finite(name, v, minimum=None):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)) or (minimum is not None and float(v) < minimum):
        bound = "" if minimum is None else f" and >= {minimum:g}"
        raise ParameterError(f"{name} = {v!r} must be a finite number{bound}")
    return float(v)


def _benchmark_geometry(annulus_diameter, stj_diameter, path_exponent, n_path):
    Ra = _check_positive("annulus_diameter", annulus_diameter) / 2
    Rc = _check_positive("stj_diameter", stj_diameter) / 2
    q = _check_positive("path_exponent", path_exponent)
    if not 1.0 <= q <= 32.0:
        raise ParameterError(f"path_exponent = {q!r} must lie in [1, 32] (1: V-shaped path, "
                             "2: parabola, large: nearly rectangular U)")
    if isinstance(n_path, bool) or not isinstance(n_path, (int, np.integer)) \
            or n_path < 5 or n_path % 2 == 0:
        raise ParameterError(f"n_path = {n_path!r} must be an odd integer >= 5 (the nadir is "
                             "the middle sample)")
    return Ra, Rc, q, int(n_path)


def _unit_path(p, n):
    """(s, zeta) of the power-law path zeta = |s|^p, sampled uniformly in s, n odd;
    exactly mirror-symmetric about s = 0."""
    m = (n - 1) // 2
    s_half = np.linspace(-1.0, 0.0, m + 1)
    z_half = np.abs(s_half) ** p
    s_half[0], z_half[0], s_half[-1], z_half[-1] = -1.0, 1.0, 0.0, 0.0
    s = np.concatenate([s_half, -s_half[-2::-1]])
    zeta = np.concatenate([z_half, z_half[-2::-1]])
    return s, zeta


def _path_xyz(s, zeta, H, Ra, Rc, theta_mid):
    theta = theta_mid + s * (np.pi / 3)
    r = Ra + (Rc - Ra) * zeta
    return np.stack([r * np.cos(theta), r * np.sin(theta), H * zeta], axis=1)


def benchmark_path_length(commissure_height, *, annulus_diameter=24.0, stj_diameter=26.0,
                          path_exponent=4.0, n_path=401):
    """Polyline length (mm) of one benchmark suturing path for a given commissure height."""
    Ra, Rc, q, n = _benchmark_geometry(annulus_diameter, stj_diameter, path_exponent, n_path)
    H = _check_positive("commissure_height", commissure_height)
    s, zeta = _unit_path(q, n)
    return _length_fn(s, zeta, Ra, Rc)(H)


def length_terms(s, zeta, Ra, Rc):
    """(a2, b2) per path segment: its squared length is a2 + H^2 b2 at commissure height H."""
    xy = _path_xyz(s, zeta, 0.0, Ra, Rc, 0.0)[:, :2]
    return np.sum(np.diff(xy, axis=0) ** 2, axis=1), np.diff(zeta) ** 2


def path_length(terms, H, xp=np):
    """Polyline length (mm) of a benchmark path at commissure height H (xp: numpy or
    jax.numpy, differentiable in H with the latter)."""
    a2, b2 = terms
    return xp.sum(xp.sqrt(a2 + H * H * b2))


def _length_fn(s, zeta, Ra, Rc):
    terms = length_terms(s, zeta, Ra, Rc)
    return lambda H: float(path_length(terms, H))


def benchmark_length_range(*, annulus_diameter=24.0, stj_diameter=26.0, path_exponent=4.0,
                           n_path=401):
    """Sutured lengths (min, max) mm that `benchmark_root` accepts: the path lengths at
    commissure heights `BENCHMARK_HEIGHT_RANGE` x annulus radius."""
    Ra = _check_positive("annulus_diameter", annulus_diameter) / 2
    kw = dict(annulus_diameter=annulus_diameter, stj_diameter=stj_diameter,
              path_exponent=path_exponent, n_path=n_path)
    return tuple(benchmark_path_length(f * Ra, **kw) for f in BENCHMARK_HEIGHT_RANGE)


def benchmark_root(sutured_length, *, annulus_diameter=24.0, stj_diameter=26.0,
                   sinus_radius_ratio=1.45, path_exponent=4.0, n_path=401,
                   first_commissure_angle=0.0, lvot_length=2.0, aorta_length=10.0,
                   wall=True, wall_theta_cells=360, wall_dz=0.25, name="benchmark"):
    """The symmetric benchmark root whose suturing paths have length ``sutured_length``.

    See the module docstring for every dimension.  The commissure height H_c (= STJ height)
    is fitted by brentq so that each path's polyline length equals ``sutured_length`` to
    1e-9 relative.  ``first_commissure_angle`` is in degrees.  ``wall`` builds the display
    surface (``wall_theta_cells`` columns, a multiple of 6, and rows ~``wall_dz`` mm apart
    in the sinus).  Returns an `AorticRoot` with axis (0, 0, -1), origin 0, annulus at
    z = 0 and ``dimensions`` holding every number used.
    """
    L = _check_positive("sutured_length", sutured_length)
    Ra, Rc, q, n = _benchmark_geometry(annulus_diameter, stj_diameter, path_exponent, n_path)
    ratio = _check_positive("sinus_radius_ratio", sinus_radius_ratio)
    Rs = ratio * Ra
    if not Rs > (Ra + Rc) / 2:
        raise ParameterError(
            f"sinus_radius_ratio = {ratio!r} gives a sinus radius {Rs:.3g} mm that does not bulge "
            f"beyond the wall (mean of annulus and STJ radii {(Ra + Rc) / 2:.3g} mm); it must "
            f"exceed {(Ra + Rc) / (2 * Ra):.4g}")
    lvot = _check_finite("lvot_length", lvot_length, minimum=0.0)
    aorta = _check_finite("aorta_length", aorta_length, minimum=0.0)
    th0 = math.radians(_check_finite("first_commissure_angle", first_commissure_angle))

    s, zeta = _unit_path(q, n)
    length = _length_fn(s, zeta, Ra, Rc)
    h_lo, h_hi = (f * Ra for f in BENCHMARK_HEIGHT_RANGE)
    L_lo, L_hi = length(h_lo), length(h_hi)
    if not L_lo <= L <= L_hi:
        raise ParameterError(
            f"sutured_length = {L:.6g} mm has no benchmark suturing path: with annulus diameter "
            f"{2 * Ra:g} mm, STJ diameter {2 * Rc:g} mm and path_exponent {q:g} the achievable "
            f"range is [{L_lo:.4f}, {L_hi:.4f}] mm (commissure heights [{h_lo:g}, {h_hi:g}] mm "
            f"= {BENCHMARK_HEIGHT_RANGE} annulus radii)")
    if L == L_lo:
        H = h_lo
    elif L == L_hi:
        H = h_hi
    else:
        H = brentq(lambda h: length(h) - L, h_lo, h_hi, xtol=1e-14, rtol=4 * np.finfo(float).eps,
                   maxiter=200)

    ang_c = th0 + 2 * np.pi * np.arange(3) / 3
    com = np.stack([Rc * np.cos(ang_c), Rc * np.sin(ang_c), np.full(3, H)], axis=1)
    paths = []
    for i in range(3):
        p = _path_xyz(s, zeta, H, Ra, Rc, ang_c[i] + np.pi / 3)
        p[0], p[-1] = com[i], com[(i + 1) % 3]
        paths.append(p)

    dims = {
        "sutured_length": L,
        "fitted_parameter": "commissure_height",
        "commissure_height": float(H),
        "sinus_height": float(H),
        "stj_height": float(H),
        "annulus_diameter": 2 * Ra,
        "annulus_radius": Ra,
        "stj_diameter": 2 * Rc,
        "stj_radius": Rc,
        "commissure_radius": Rc,
        "sinus_radius_ratio": ratio,
        "sinus_radius": Rs,
        "sinus_max_height": float(H) / 2,
        "path_exponent": q,
        "commissure_apex_half_angle_deg": math.degrees(math.atan(math.pi * Rc / 3 / (q * H))),
        "n_path": n,
        "first_commissure_angle_deg": float(first_commissure_angle),
        "commissure_distance": float(np.sqrt(3.0) * Rc),
        "lvot_length": lvot,
        "aorta_length": aorta,
        "height_range_mm": [h_lo, h_hi],
        "sutured_length_range_mm": [L_lo, L_hi],
    }
    w = None
    if wall:
        w = _benchmark_wall(Ra, Rc, Rs, H, q, th0, lvot, aorta, wall_theta_cells, wall_dz)
    return AorticRoot(axis=np.array([0.0, 0.0, -1.0]), origin=np.zeros(3), commissures=com,
                      paths=tuple(paths), wall=w, name=str(name), dimensions=dims)


def _benchmark_wall(Ra, Rc, Rs, H, q, th0, lvot, aorta, n_theta, dz):
    if isinstance(n_theta, bool) or not isinstance(n_theta, (int, np.integer)) \
            or n_theta < 12 or n_theta % 6:
        raise ParameterError(f"wall_theta_cells = {n_theta!r} must be a multiple of 6, >= 12 "
                             "(columns on every commissure and nadir)")
    dz = _check_positive("wall_dz", dz)
    n_theta = int(n_theta)
    theta = th0 + 2 * np.pi * np.arange(n_theta) / n_theta
    zs = [np.linspace(0.0, H, max(2, math.ceil(H / dz)) + 1)]
    if lvot > 0:
        zs.insert(0, np.linspace(-lvot, 0.0, max(1, math.ceil(lvot / (4 * dz))) + 1)[:-1])
    if aorta > 0:
        zs.append(np.linspace(H, H + aorta, max(1, math.ceil(aorta / (2 * dz))) + 1)[1:])
    z = np.concatenate(zs)
    # local coordinate s in [-1, 1) of each column within its sinus (nadir at s = 0)
    period = 2 * np.pi / 3
    delta = np.mod(theta - (th0 + np.pi / 3) + np.pi / 3, period) - np.pi / 3
    s = delta / (np.pi / 3)
    s = np.where(np.abs(np.abs(s) - 1) < 1e-12, np.sign(s), s)
    zeta_p = np.abs(s) ** q  # path height / H
    Z, S = np.meshgrid(z, s, indexing="ij")
    ZP = np.broadcast_to(zeta_p, Z.shape)
    zeta = np.clip(Z / H, 0.0, 1.0)
    room = 1.0 - ZP
    t = np.where((zeta > ZP) & (room > 0), (zeta - ZP) / np.where(room > 0, room, 1.0), 0.0)
    D = Rs - (Ra + Rc) / 2
    bulge = D * np.cos(np.pi * S / 2) ** 2 * np.sin(np.pi * t) ** 2
    r = np.where(Z < 0, Ra, np.where(Z > H, Rc, Ra + (Rc - Ra) * zeta + bulge))
    TH = np.broadcast_to(theta, Z.shape)
    pts = np.stack([r * np.cos(TH), r * np.sin(TH), Z], axis=-1).reshape(-1, 3)
    nz = len(z)
    k, j = np.meshgrid(np.arange(nz - 1), np.arange(n_theta), indexing="ij")
    v00 = (k * n_theta + j).ravel()
    v01 = (k * n_theta + (j + 1) % n_theta).ravel()
    v10 = v00 + n_theta
    v11 = v01 + n_theta
    tri = np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)])
    return pts, tri.astype(np.int32)
