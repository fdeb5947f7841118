"""Valve landmarks on a wall surface: commissures, nadirs and suture paths, and the
`AorticRoot` they make (`root_from_landmarks`).

The surgeon (or an engineer in 3D Slicer) marks the three commissures and either the
three suture paths (curves) or the three nadirs (each sinus's lowest point).  Every
point is projected onto the wall.  The valve axis is the normal of the commissures'
plane, turned towards the nadirs (the ventricle), through the commissures' centroid;
the commissures are put in counter-clockwise order seen from the aorta, and each nadir
is assigned to the leaflet whose commissures flank it.

Suture paths from nadirs (`fit_suture_path`).  In cylindrical coordinates about the axis
(polar angle phi, depth zeta towards the ventricle), each half of the path, from the
nadir (u = 0) to a commissure (u = 1), is

    phi(u) = phi_n + u (phi_c - phi_n),   zeta(u) = zeta_n - (zeta_n - zeta_c) u^p,

placed on the wall at the wall's radius there (the wall read as a radial graph
rho(phi, zeta), interpolated linearly between its vertices, then each point projected
exactly onto the wall).  p = 1 runs straight (on the unrolled wall) from the nadir to the
commissures; larger p keeps the path low round the sinus and then climbs steeply, as the
hinge line of a native leaflet does.  On a cylinder the path's length grows with p; on a
wall whose sinus bulges between the nadir and the commissures it need not.  p is chosen
in [1, `P_MAX`] (Brent's method) so that the length equals the template's sutured edge,
as the paper prescribes ("the suturing path is chosen to fit the length of the sutured
edge").  A template whose sutured edge lies outside the lengths at p = 1 and p = `P_MAX`
does not fit the root, and is refused with the range that fits.  Lengths in mm.
"""
from __future__ import annotations

import dataclasses
import re

import numpy as np

from ..errors import ParameterError
from .root import AorticRoot
from .surface_query import SurfaceIndex

__all__ = ["ValveLandmarks", "landmarks_from_markups", "landmarks_to_markups",
           "root_from_landmarks", "P_MAX", "WALL_TOLERANCE"]

#: The steepest path shape searched (see the module docstring).
P_MAX = 12.0
#: Landmarks farther than this from the wall (mm) are an error (wrong frame or scan).
WALL_TOLERANCE = 5.0
#: Points per suture path built from a nadir (odd: the nadir is a sample).
N_PATH = 61

_COMMISSURE = re.compile(r"^\s*(c|com|commissure)[\s_-]*([123])\s*$", re.I)
_NADIR = re.compile(r"^\s*(n|nadir)[\s_-]*([123])\s*$", re.I)


@dataclasses.dataclass(frozen=True)
class ValveLandmarks:
    """Commissures (3, 3), and nadirs (3, 3) or suture curves (3 arrays (K, 3)) or both,
    in mm, in the order given; ``source`` names where they came from (for messages)."""

    commissures: np.ndarray
    nadirs: np.ndarray | None = None
    curves: tuple | None = None
    source: str = "landmarks"

    def __post_init__(self):
        c = np.asarray(self.commissures, float)
        if c.shape != (3, 3) or not np.all(np.isfinite(c)):
            raise ParameterError(f"{self.source}: commissures must be three finite points "
                                 f"(3, 3); got shape {c.shape}")
        object.__setattr__(self, "commissures", c)
        if self.nadirs is not None:
            n = np.asarray(self.nadirs, float)
            if n.shape != (3, 3) or not np.all(np.isfinite(n)):
                raise ParameterError(f"{self.source}: nadirs must be three finite points "
                                     f"(3, 3); got shape {n.shape}")
            object.__setattr__(self, "nadirs", n)
        if self.curves is not None:
            cv = tuple(np.asarray(q, float).reshape(-1, 3) for q in self.curves)
            if len(cv) != 3 or any(len(q) < 2 for q in cv):
                raise ParameterError(f"{self.source}: give three suture curves of at least 2 "
                                     "points each")
            object.__setattr__(self, "curves", cv)
        if self.nadirs is None and self.curves is None:
            raise ParameterError(f"{self.source}: give the three nadirs (N1-N3) or the three "
                                 "suture path curves besides the commissures")


# ============================================================================ markups
def landmarks_from_markups(markups, source: str = "markups") -> ValveLandmarks:
    """The valve landmarks of Slicer markups (`jaxvalve.io.markups.Markup`): control points
    labelled C1, C2, C3 (or ``commissure 1`` ...) are the commissures, N1, N2, N3 (or
    ``nadir 1`` ...) the nadirs, in any point list; every ``Curve`` markup is a suture
    path (three of them, in any order and direction)."""
    com, nad, curves = {}, {}, []
    for m in markups:
        if m.kind == "Curve":
            curves.append(m.points)
            continue
        if m.kind != "Fiducial":
            continue
        for lab, x in zip(m.labels, m.points):
            for pat, into, what in ((_COMMISSURE, com, "commissure"), (_NADIR, nad, "nadir")):
                hit = pat.match(lab)
                if hit:
                    k = int(hit.group(2)) - 1
                    if k in into:
                        raise ParameterError(f"{source}: {what} {k + 1} is given twice "
                                             f"(label '{lab}')")
                    into[k] = x
    if len(com) != 3:
        found = [lab for m in markups if m.kind == "Fiducial" for lab in m.labels]
        raise ParameterError(
            f"{source}: needs three commissures, control points labelled C1, C2, C3 (or "
            f"'commissure 1' ...) in a point list; found {len(com)} (labels {found})")
    nadirs = np.array([nad[k] for k in range(3)]) if len(nad) == 3 else None
    if nad and nadirs is None:
        raise ParameterError(f"{source}: give all three nadirs N1, N2, N3 or none; found "
                             f"{sorted(k + 1 for k in nad)}")
    if curves and len(curves) != 3:
        raise ParameterError(f"{source}: needs three suture path curves (one per leaflet) or "
                             f"none; found {len(curves)}")
    return ValveLandmarks(np.array([com[k] for k in range(3)]), nadirs,
                          tuple(curves) if curves else None, source)


def landmarks_to_markups(root: AorticRoot, nadirs=None):
    """Markups of ``root`` for Slicer: a point list ``valve landmarks`` with C1-C3 and
    N1-N3 (``nadirs``, default each path's most ventricular point) and one ``Curve`` per
    suture path (``suture path 1`` ...)."""
    from ..io.markups import Markup
    if nadirs is None:
        nadirs = np.array([p[int(np.argmax(root.axial(p)))] for p in root.paths])
    pts = np.concatenate([root.commissures, np.asarray(nadirs, float)])
    labels = [f"C{i + 1}" for i in range(3)] + [f"N{i + 1}" for i in range(3)]
    out = [Markup("Fiducial", labels, pts, "valve landmarks")]
    for i, p in enumerate(root.paths):
        out.append(Markup("Curve", [f"P{i + 1}-{k + 1}" for k in range(len(p))], p,
                          f"suture path {i + 1}",
                          f"commissure C{i + 1} through nadir N{i + 1} to commissure "
                          f"C{(i + 1) % 3 + 1}"))
    return out


# ============================================================================ geometry
class _Frame:
    """Cylindrical coordinates about the valve axis: ``axis`` (aorta -> ventricle)
    through ``centre``; polar angle counter-clockwise seen from the aorta."""

    def __init__(self, centre, axis, first):
        self.c, self.n = np.asarray(centre, float), np.asarray(axis, float)
        e1 = np.asarray(first, float) - self.c
        e1 = e1 - (e1 @ self.n) * self.n
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(-self.n, self.e1)

    def coords(self, x):
        d = np.asarray(x, float) - self.c
        zeta = d @ self.n
        r = d - zeta[..., None] * self.n
        return np.arctan2(r @ self.e2, r @ self.e1), zeta, np.linalg.norm(r, axis=-1)

    def point(self, phi, zeta, rho):
        return (self.c + np.multiply.outer(zeta, self.n)
                + rho[..., None] * (np.multiply.outer(np.cos(phi), self.e1)
                                    + np.multiply.outer(np.sin(phi), self.e2)))


def _wall_chart(frame, V, zeta_range, scale):
    """The wall as a radial graph rho(phi, zeta) over the depths ``zeta_range`` (+- 3 mm):
    linear interpolation between the wall's vertices, phi unrolled by +- 2 pi."""
    from scipy.interpolate import LinearNDInterpolator
    phi, zeta, rho = frame.coords(V)
    keep = (zeta > zeta_range[0] - 3.0) & (zeta < zeta_range[1] + 3.0)
    phi, zeta, rho = phi[keep], zeta[keep], rho[keep]
    ph = np.concatenate([phi, phi - 2 * np.pi, phi + 2 * np.pi])
    ze, rh = np.tile(zeta, 3), np.tile(rho, 3)
    near = np.abs(ph) < np.pi + 1.0
    return LinearNDInterpolator(np.stack([ph[near] * scale, ze[near]], 1), rh[near]), scale


def _half(u, phi_n, zeta_n, phi_c, zeta_c, p):
    return phi_n + u * (phi_c - phi_n), zeta_n - (zeta_n - zeta_c) * u ** p


def _path_points(frame, chart, ends, nadir, p, n):
    """Wall points (n, 3) of the path commissure a -> nadir -> commissure b for shape p."""
    interp, scale = chart
    (pa, za), (pb, zb), (pn, zn) = ends[0], ends[1], nadir
    m = (n - 1) // 2
    u = np.linspace(0.0, 1.0, m + 1)
    phl, zel = _half(u[::-1], pn, zn, pa, za, p)
    phr, zer = _half(u[1:], pn, zn, pb, zb, p)
    phi, zeta = np.concatenate([phl, phr]), np.concatenate([zel, zer])
    wrapped = np.angle(np.exp(1j * phi))
    rho = interp(np.stack([wrapped * scale, zeta], 1))
    if not np.all(np.isfinite(rho)):
        raise ParameterError("a suture path leaves the wall surface (the wall does not "
                             "cover the depths between the commissures and the nadirs)")
    return frame.point(phi, zeta, rho)


def _length(x):
    return float(np.sum(np.linalg.norm(np.diff(x, axis=0), axis=1)))


def fit_suture_path(frame, chart, ends, nadir, sutured_length, *, n=N_PATH, leaflet=0):
    """The path of shape exponent p in [1, `P_MAX`] whose length is ``sutured_length``:
    (points (n, 3), p).  Raises `ParameterError` with the lengths that fit."""
    from scipy.optimize import brentq
    L = lambda p: _length(_path_points(frame, chart, ends, nadir, p, n))  # noqa: E731
    lo, hi = sorted((L(1.0), L(P_MAX)))
    if not lo <= sutured_length <= hi:
        raise ParameterError(
            f"the template's sutured edge ({sutured_length:.2f} mm) does not fit leaflet "
            f"{leaflet + 1}: suture paths on this wall between its commissures and nadir are "
            f"{lo:.2f} to {hi:.2f} mm long; choose r, a and alpha so that 2 a + r alpha "
            "lies in that range")
    p = brentq(lambda q: L(q) - sutured_length, 1.0, P_MAX, xtol=1e-10, rtol=1e-12)
    return _path_points(frame, chart, ends, nadir, p, n), p


def _densify(q, step=0.5):
    """The polyline q (K, 3) with each segment split into pieces of at most ``step`` mm
    (its own points kept)."""
    out = [q[:1]]
    for a, b in zip(q[:-1], q[1:]):
        m = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + np.outer(np.arange(1, m + 1) / m, b - a))
    return np.concatenate(out)


def root_from_landmarks(wall, landmarks: ValveLandmarks, *, sutured_length=None,
                        name: str = "patient", n_path: int = N_PATH):
    """The `AorticRoot` of ``landmarks`` on ``wall`` = (points (P, 3), triangles (T, 3)),
    mm.  Suture curves, where given, are used (their segments split to 0.5 mm, every
    point projected onto the wall); else the paths are fitted from the nadirs to ``sutured_length`` (mm).
    Returns (root, report): the report holds each landmark's distance to the wall, the
    axis, and per path its length and (when fitted) its shape exponent and its nadir on
    the wall (``nadirs``, in the root's leaflet order)."""
    src = landmarks.source
    index = SurfaceIndex(*wall)
    d_com, com, _ = index.closest(landmarks.commissures)
    moved = {"commissures": d_com}
    nad = None
    if landmarks.nadirs is not None:
        d_nad, nad, _ = index.closest(landmarks.nadirs)
        moved["nadirs"] = d_nad
    for what, d in moved.items():
        k = int(np.argmax(d))
        if d[k] > WALL_TOLERANCE:
            raise ParameterError(
                f"{src}: {what[:-1]} {k + 1} lies {d[k]:.2f} mm from the wall surface "
                f"(at most {WALL_TOLERANCE:g} mm): landmarks must be placed on the aortic "
                "wall of the same scan; check the coordinate system (LPS or RAS)")
    curves = None
    if landmarks.curves is not None:
        curves = []
        for q in landmarks.curves:
            dq, x, _ = index.closest(_densify(q))
            if dq.max() > WALL_TOLERANCE:
                raise ParameterError(f"{src}: a suture curve lies up to {dq.max():.2f} mm "
                                     f"from the wall (at most {WALL_TOLERANCE:g} mm)")
            curves.append(x)
    centre = com.mean(axis=0)
    normal = np.cross(com[1] - com[0], com[2] - com[0])
    if not np.linalg.norm(normal) > 1e-9:
        raise ParameterError(f"{src}: the three commissures are collinear")
    normal /= np.linalg.norm(normal)
    deep = nad if nad is not None else np.concatenate(curves)
    if np.mean((deep - centre) @ normal) < 0:
        normal = -normal
    frame = _Frame(centre, normal, com[0])
    phi_c, zeta_c, rho_c = frame.coords(com)
    phi_c = np.mod(phi_c, 2 * np.pi)
    order = np.argsort(phi_c)                       # counter-clockwise from the aorta, C1 first
    com, phi_c, zeta_c = com[order], phi_c[order], zeta_c[order]
    report = {"commissure_wall_distance_mm": moved["commissures"][order].tolist(),
              "axis": normal.tolist(), "centre": centre.tolist()}
    paths, exps = [], []
    if curves is not None:
        for i in range(3):
            paths.append(_curve_path(curves, com, i, src))
    else:
        if sutured_length is None:
            raise ParameterError(f"{src} gives no suture path curves, only commissures and "
                                 "nadirs: the paths are fitted to the template's sutured "
                                 "edge, so sutured_length (mm) is needed")
        phi_n, zeta_n, _ = frame.coords(nad)
        report["nadir_wall_distance_mm"], report["nadirs"] = [], []
        zr = (float(min(zeta_c.min(), zeta_n.min())), float(zeta_n.max()))
        chart = _wall_chart(frame, index.points, zr, float(np.mean(rho_c)))
        for i in range(3):
            a, b = phi_c[i], phi_c[(i + 1) % 3] + (2 * np.pi if i == 2 else 0.0)
            hits = [j for j in range(3)
                    if a < (a + np.mod(phi_n[j] - a, 2 * np.pi)) < b]
            if len(hits) != 1:
                raise ParameterError(
                    f"{src}: leaflet {i + 1} (between commissures {int(order[i]) + 1} and "
                    f"{int(order[(i + 1) % 3]) + 1}) must have exactly one nadir between its "
                    f"commissures; found {len(hits)}")
            j = hits[0]
            pn = a + np.mod(phi_n[j] - a, 2 * np.pi)
            x, p = fit_suture_path(frame, chart, ((a, zeta_c[i]), (b, zeta_c[(i + 1) % 3])),
                                   (pn, zeta_n[j]), float(sutured_length), n=n_path,
                                   leaflet=i)
            _, x, _ = index.closest(x)              # exactly on the wall
            x[0], x[-1] = com[i], com[(i + 1) % 3]
            paths.append(x)
            exps.append(p)
            report["nadir_wall_distance_mm"].append(float(moved["nadirs"][j]))
            report["nadirs"].append(nad[j].tolist())
        report["path_shape_exponent"] = exps
    lengths = [_length(x) for x in paths]
    report["path_length_mm"] = lengths
    level = np.mean([np.max((x - centre) @ normal) for x in paths])
    root = AorticRoot(axis=normal, origin=centre + level * normal, commissures=com,
                      paths=tuple(paths), wall=(index.points, index.triangles), name=name,
                      dimensions={"suture_path_lengths_mm": lengths})
    return root, report


def _curve_path(curves, com, i, src):
    """The curve that joins commissures i and i + 1, oriented from i, ends snapped."""
    a, b = com[i], com[(i + 1) % 3]
    for q in curves:
        for x in (q, q[::-1]):
            if np.linalg.norm(x[0] - a) < WALL_TOLERANCE and np.linalg.norm(x[-1] - b) < WALL_TOLERANCE:
                x = x.copy()
                x[0], x[-1] = a, b
                keep = np.concatenate([[True], np.linalg.norm(np.diff(x, axis=0), axis=1) > 1e-6])
                keep[-1] = True
                return x[keep]
    raise ParameterError(f"{src}: no suture curve runs from commissure {i + 1} to commissure "
                         f"{(i + 1) % 3 + 1} (its ends must lie within {WALL_TOLERANCE:g} mm "
                         "of them)")
