"""File input/output: surfaces (any meshio format) and aortic roots.  meshio is used only here.

A patient root is two files:

* a **surface mesh** of the aortic wall in any format meshio reads (.stl, .vtk, .vtu, .ply,
  .obj, .off, ...).  Triangle cells are used; quad cells are split into two triangles;
  other cells (vertices, lines) are ignored.  It is for display and for checking that the
  paths lie on the wall; the mechanics never touch it.
* a **landmarks file**, JSON (``.json``) or TOML (``.toml``), with the fields

  ==============  ========  ======================================================
  field           required  meaning
  ==============  ========  ======================================================
  ``units``       yes       "mm", "cm" or "m"; landmarks *and* surface points are
                            converted to mm (the surface file carries no units).
  ``commissures`` yes       [[x, y, z], x 3], counter-clockwise seen from the aorta.
  ``paths``       yes       3 polylines [[x, y, z], ...], path i from commissure i
                            through its nadir to commissure (i+1) % 3.
  ``axis``        no        unit vector from the aorta to the ventricle.  Default:
                            the normal of the commissures' plane, pointing to the
                            side of the path nadirs (the ventricle).
  ``origin``      no        a point on the axis.  Default: the centroid of the three
                            commissures moved along the axis to the annulus plane
                            (so that ``annulus_level == 0``).
  ``name``        no        a label (default: the landmarks file's stem).
  ``dimensions``  no        a table of documented numbers, kept verbatim.
  ``meta``        no        anything; ignored (provenance, patient id, ...).
  ==============  ========  ======================================================

  Other keys are an error (a misspelt optional key would otherwise be silently ignored).

Every problem raises a `RootFileError` (a `JaxvalveError`) whose message names the file and
the field: `SurfaceFileError` (also a `MeshError`) for the surface, `LandmarksFileError` (also
a `ParameterError`) for the landmarks.

Point and cell data (`write_surface`) need ``.vtu``: meshio's other formats drop or reshape
arrays (PLY drops vectors, legacy VTK pads 2-vectors to 3, STL/OBJ keep nothing).  Boolean
arrays are stored as uint8.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import pathlib
import re
import tomllib
import warnings
from io import StringIO

import meshio
import numpy as np

from ..errors import (JaxvalveError, LandmarksFileError, MeshError, ParameterError,  # noqa: F401
                     RootFileError, SurfaceFileError)
from ..geometry.root import AorticRoot, distance_to_surface

__all__ = [
    "RootFileError", "SurfaceFileError", "LandmarksFileError",
    "read_surface", "write_surface", "read_landmarks", "write_landmarks", "read_root",
    "write_root", "check_out_dir",
    "UNITS",
]

#: Length units accepted in landmarks files, in mm.
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_DATA_SUFFIXES = (".vtu",)
_KEYS_REQUIRED = ("units", "commissures", "paths")
_KEYS_OPTIONAL = ("axis", "origin", "name", "dimensions", "meta")


# =========================================================================== surfaces
def _existing(path, err, what):
    p = pathlib.Path(path)
    if not p.exists():
        raise err(f"{what} file '{p}' does not exist")
    if not p.is_file():
        raise err(f"{what} file '{p}' is not a regular file")
    return p


def read_surface(path, *, return_cell_data=False):
    """Read a triangle surface: ``(points (N, 3) float64, triangles (M, 3) int32,
    point_data dict)``, plus ``cell_data`` (dict name -> (M, ...) array, following the
    triangle order) when ``return_cell_data``.  Quads are split into two triangles."""
    p = _existing(path, SurfaceFileError, "surface")
    chatter = StringIO()
    try:
        # meshio prints read errors and then calls sys.exit(1); capture both.
        with warnings.catch_warnings(), contextlib.redirect_stdout(chatter), \
                contextlib.redirect_stderr(chatter):
            # meshio's STL reader probes for a binary header with a uint32 product that
            # overflows on ASCII files; harmless.
            warnings.filterwarnings("ignore", "overflow encountered", RuntimeWarning)
            mesh = meshio.read(p)
    except (Exception, SystemExit) as e:  # meshio raises many types for unknown/corrupt files
        why = " ".join(chatter.getvalue().split()) or f"{type(e).__name__}: {e}"
        raise SurfaceFileError(f"surface file '{p}' cannot be read by meshio ({why}); use a "
                               "mesh format meshio supports (.stl, .vtk, .vtu, .ply, .obj, "
                               ".off, ...)") from None
    pts = np.asarray(mesh.points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3) or pts.shape[0] == 0:
        raise SurfaceFileError(f"surface file '{p}': points must have shape (N, 3); got "
                               f"{pts.shape}")
    if pts.shape[1] == 2:
        raise SurfaceFileError(f"surface file '{p}' holds 2D points; an aortic wall needs "
                               "3D points (N, 3)")
    pts = pts.astype(np.float64)
    if not np.all(np.isfinite(pts)):
        k = int(np.argwhere(~np.isfinite(pts))[0][0])
        raise SurfaceFileError(f"surface file '{p}': point {k} has a non-finite coordinate "
                               "(NaN or inf)")
    tris, cdata, kinds = [], {}, []
    names = list(mesh.cell_data)
    for b, block in enumerate(mesh.cells):
        kinds.append(block.type)
        if block.type == "triangle":
            t, rep = np.asarray(block.data), 1
        elif block.type == "quad":
            q = np.asarray(block.data)
            t = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
            rep = 2
        else:
            continue
        tris.append(t)
        for nm in names:
            v = np.asarray(mesh.cell_data[nm][b])
            cdata.setdefault(nm, []).append(np.concatenate([v] * rep) if rep > 1 else v)
    if not tris or sum(len(t) for t in tris) == 0:
        found = ", ".join(sorted(set(kinds))) or "no cells"
        raise SurfaceFileError(f"surface file '{p}' holds no triangles (cells found: {found}); "
                               "the wall must be a triangle (or quad) surface mesh")
    tri = np.concatenate(tris).astype(np.int64)
    if tri.min() < 0 or tri.max() >= len(pts):
        raise SurfaceFileError(f"surface file '{p}': triangle indices must lie in "
                               f"[0, {len(pts) - 1}]; found [{tri.min()}, {tri.max()}]")
    point_data = {k: np.asarray(v) for k, v in mesh.point_data.items()}
    if return_cell_data:
        cell_data = {k: np.concatenate(v) for k, v in cdata.items()}
        return pts, tri.astype(np.int32), point_data, cell_data
    return pts, tri.astype(np.int32), point_data


def _data_arrays(data, n, argname, rows_name):
    out = {}
    if data is None:
        return out
    if not isinstance(data, dict):
        raise ParameterError(f"{argname} must be a dict name -> array or None; got "
                             f"{type(data).__name__}")
    for k, v in data.items():
        if not isinstance(k, str) or not k:
            raise ParameterError(f"{argname} keys must be non-empty strings; got {k!r}")
        a = np.asarray(v)
        if a.dtype == bool:
            a = a.astype(np.uint8)
        if not (np.issubdtype(a.dtype, np.number)):
            raise ParameterError(f"{argname}['{k}'] must be numeric; got dtype {a.dtype}")
        if a.ndim not in (1, 2) or a.shape[0] != n:
            raise ParameterError(f"{argname}['{k}'] must have shape ({n},) or ({n}, k) (one row "
                                 f"per {rows_name}); got {a.shape}")
        out[k] = a
    return out


def write_surface(path, points, triangles, point_data=None, cell_data=None):
    """Write a triangle surface with optional point data (name -> (N,) or (N, k)) and cell
    data (name -> (M,) or (M, k)).  Data need a ``.vtu`` file.  Returns the path."""
    p = pathlib.Path(path)
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MeshError(f"points must have shape (N, 3); got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise MeshError("points hold a non-finite coordinate (NaN or inf)")
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0:
        raise MeshError(f"triangles must have shape (M, 3) with M >= 1; got {tri.shape}")
    if not np.issubdtype(tri.dtype, np.integer):
        raise MeshError(f"triangles must be integer indices; got dtype {tri.dtype}")
    if tri.min() < 0 or tri.max() >= len(pts):
        raise MeshError(f"triangle indices must lie in [0, {len(pts) - 1}]; found "
                        f"[{tri.min()}, {tri.max()}]")
    pd = _data_arrays(point_data, len(pts), "point_data", "point")
    cd = _data_arrays(cell_data, len(tri), "cell_data", "triangle")
    if (pd or cd) and p.suffix.lower() not in _DATA_SUFFIXES:
        raise ParameterError(f"point_data / cell_data need a .vtu file; '{p}' has suffix "
                             f"'{p.suffix}' (meshio's other formats drop or reshape arrays)")
    mesh = meshio.Mesh(pts, [("triangle", tri.astype(np.int32))], point_data=pd,
                       cell_data={k: [v] for k, v in cd.items()})
    try:
        kw = {"binary": True} if p.suffix.lower() == ".stl" else {}
        meshio.write(p, mesh, **kw)
    except (OSError, meshio.ReadError, meshio.WriteError, KeyError, ValueError) as e:
        raise SurfaceFileError(f"surface file '{p}' cannot be written by meshio "
                               f"({type(e).__name__}: {e})") from None
    return p


# =========================================================================== landmarks
def _load_landmarks(path):
    p = _existing(path, LandmarksFileError, "landmarks")
    suffix = p.suffix.lower()
    try:
        if suffix == ".json":
            with open(p, encoding="utf-8") as f:
                data = json.load(f)
        elif suffix == ".toml":
            with open(p, "rb") as f:
                data = tomllib.load(f)
        else:
            raise LandmarksFileError(f"landmarks file '{p}' must end in .json or .toml; got "
                                     f"'{suffix or '(no suffix)'}'")
    except json.JSONDecodeError as e:
        raise LandmarksFileError(f"landmarks file '{p}' is not valid JSON: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise LandmarksFileError(f"landmarks file '{p}' is not valid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise LandmarksFileError(f"landmarks file '{p}' is not UTF-8 text: {e}") from None
    if not isinstance(data, dict):
        raise LandmarksFileError(f"landmarks file '{p}' must hold an object/table at top "
                                 f"level; got {type(data).__name__}")
    return p, data


def _numeric_array(value, field, p, shape_desc):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float, list)):
            raise LandmarksFileError(f"landmarks file '{p}': field '{field}' must be "
                                     f"{shape_desc} of numbers; found {v!r}")
        if isinstance(v, list):
            for x in v:
                check(x)
    check(value)
    try:
        a = np.array(value, dtype=np.float64)
    except ValueError:
        raise LandmarksFileError(f"landmarks file '{p}': field '{field}' must be {shape_desc}; "
                                 "its rows have different lengths") from None
    if not np.all(np.isfinite(a)):
        raise LandmarksFileError(f"landmarks file '{p}': field '{field}' holds NaN or inf; "
                                 "every coordinate must be finite")
    return a


def read_landmarks(path):
    """Parse and check a landmarks file; return a dict with ``name``, ``units`` (the file's),
    ``scale`` (mm per unit), and ``axis``/``origin`` (None when absent), ``commissures``
    (3, 3), ``paths`` (3 arrays (K_i, 3)), ``dimensions`` -- coordinates converted to mm."""
    p, data = _load_landmarks(path)
    unknown = sorted(set(data) - set(_KEYS_REQUIRED) - set(_KEYS_OPTIONAL))
    if unknown:
        raise LandmarksFileError(f"landmarks file '{p}': unknown field(s) {unknown}; allowed "
                                 f"fields are {list(_KEYS_REQUIRED + _KEYS_OPTIONAL)}")
    for k in _KEYS_REQUIRED:
        if k not in data:
            raise LandmarksFileError(f"landmarks file '{p}': required field '{k}' is missing")
    units = data["units"]
    if units not in UNITS:
        raise LandmarksFileError(f"landmarks file '{p}': field 'units' = {units!r} must be one "
                                 f"of {list(UNITS)}")
    scale = UNITS[units]
    com = _numeric_array(data["commissures"], "commissures", p, "[[x, y, z] x 3]")
    if com.shape != (3, 3):
        raise LandmarksFileError(f"landmarks file '{p}': field 'commissures' must have shape "
                                 f"(3, 3) ([[x, y, z] x 3]); got {com.shape}")
    raw = data["paths"]
    if not isinstance(raw, list) or len(raw) != 3:
        n = len(raw) if isinstance(raw, list) else type(raw).__name__
        raise LandmarksFileError(f"landmarks file '{p}': field 'paths' must be a list of 3 "
                                 f"polylines (one per leaflet); got {n}")
    paths = []
    for i, r in enumerate(raw):
        a = _numeric_array(r, f"paths[{i}]", p, "[[x, y, z], ...]")
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3:
            raise LandmarksFileError(f"landmarks file '{p}': field 'paths[{i}]' must have shape "
                                     f"(K, 3) with K >= 3; got {a.shape}")
        paths.append(a * scale)
    out = {"units": units, "scale": scale, "commissures": com * scale, "paths": paths,
           "axis": None, "origin": None}
    for k in ("axis", "origin"):
        if k in data:
            v = _numeric_array(data[k], k, p, "[x, y, z]")
            if v.shape != (3,):
                raise LandmarksFileError(f"landmarks file '{p}': field '{k}' must be [x, y, z] "
                                         f"(shape (3,)); got {v.shape}")
            out[k] = v if k == "axis" else v * scale
    name = data.get("name", p.stem)
    if not isinstance(name, str):
        raise LandmarksFileError(f"landmarks file '{p}': field 'name' must be a string; got "
                                 f"{name!r}")
    out["name"] = name
    dims = data.get("dimensions")
    if dims is not None and not isinstance(dims, dict):
        raise LandmarksFileError(f"landmarks file '{p}': field 'dimensions' must be a table / "
                                 f"object; got {type(dims).__name__}")
    out["dimensions"] = dims
    return out


def _default_axis(com, paths):
    n = np.cross(com[1] - com[0], com[2] - com[0])
    nn = np.linalg.norm(n)
    if not nn > 0:
        return None
    n = n / nn
    centre = com.mean(axis=0)
    depth = np.mean([np.max((q - centre) @ n) + np.min((q - centre) @ n) for q in paths])
    return n if depth > 0 else -n


def read_root(surface_path, landmarks_path, *, wall_tolerance=None, sutured_length=None):
    """Read a patient root: a surface mesh (any meshio format) and a landmarks file.

    Coordinates are converted to mm using the landmarks' ``units``.  With
    ``wall_tolerance`` (mm), the commissures and path points must lie within that
    distance of the surface (else `SurfaceFileError`).  A 3D Slicer markups file
    (``.mrk.json``, LPS or RAS mm, the surface in the same frame) gives the commissures
    and the suture path curves, or the nadirs, from which the paths are fitted to
    ``sutured_length`` (mm; `jaxvalve.geometry.landmarks`).  Returns an `AorticRoot`.
    """
    from .markups import is_markups_file
    if is_markups_file(landmarks_path):
        return _read_markups_root(surface_path, landmarks_path, wall_tolerance,
                                  sutured_length)
    lm = read_landmarks(landmarks_path)
    lp = pathlib.Path(landmarks_path)
    pts, tri, _ = read_surface(surface_path)
    pts = pts * lm["scale"]
    com, paths = lm["commissures"], lm["paths"]
    axis = lm["axis"]
    if axis is None:
        axis = _default_axis(com, paths)
        if axis is None:
            raise LandmarksFileError(f"landmarks file '{lp}': field 'axis' is absent and the "
                                     "commissures are collinear, so no default axis exists")
    origin = lm["origin"]
    if origin is None:
        a = np.asarray(axis, float)
        a = a / (np.linalg.norm(a) or 1.0)
        c = com.mean(axis=0)
        level = np.mean([np.max((q - c) @ a) for q in paths])
        origin = c + level * a
    try:
        root = AorticRoot(axis=axis, origin=origin, commissures=com, paths=tuple(paths),
                          wall=(pts, tri), name=lm["name"], dimensions=lm["dimensions"])
    except MeshError as e:
        if "wall" in str(e):
            raise SurfaceFileError(f"surface file '{surface_path}': {e}") from None
        raise LandmarksFileError(f"landmarks file '{lp}': {e}") from None
    except JaxvalveError as e:
        raise LandmarksFileError(f"landmarks file '{lp}': {e}") from None
    if wall_tolerance is not None:
        tol = float(wall_tolerance)
        if not (math.isfinite(tol) and tol > 0):
            raise ParameterError(f"wall_tolerance = {wall_tolerance!r} must be a number > 0 "
                                 "(mm) or None")
        d = distance_to_surface(np.concatenate([com] + list(root.paths)), pts, tri)
        if d.max() > tol:
            raise SurfaceFileError(
                f"surface file '{surface_path}': the landmarks of '{lp}' lie up to "
                f"{d.max():.3g} mm from the wall (wall_tolerance {tol:g} mm); the commissures "
                "and suturing paths must lie on the aortic wall (check units and frames)")
    return root


def _read_markups_root(surface_path, landmarks_path, wall_tolerance, sutured_length):
    from ..geometry.landmarks import landmarks_from_markups, root_from_landmarks
    from .markups import read_markups
    lp = pathlib.Path(landmarks_path)
    pts, tri, _ = read_surface(surface_path)
    try:
        lm = landmarks_from_markups(read_markups(lp), source=f"markups file '{lp}'")
        root, _ = root_from_landmarks((pts, tri), lm, sutured_length=sutured_length,
                                      name=lp.name[:-len(".mrk.json")] or "patient")
    except LandmarksFileError:
        raise
    except JaxvalveError as e:
        raise LandmarksFileError(str(e) if str(e).startswith("markups file") else
                                 f"markups file '{lp}': {e}") from None
    if wall_tolerance is not None:
        d = distance_to_surface(np.concatenate([root.commissures] + list(root.paths)),
                                pts, tri)
        if d.max() > float(wall_tolerance):
            raise SurfaceFileError(f"surface file '{surface_path}': the landmarks of '{lp}' "
                                   f"lie up to {d.max():.3g} mm from the wall")
    return root


# =========================================================================== writing
def _toml_key(k):
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _toml_value(v, indent=""):
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise ParameterError(f"cannot write the non-finite number {f!r} to TOML")
        return repr(f)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        items = list(v)
        if items and isinstance(items[0], (list, tuple, np.ndarray)):
            inner = indent + "  "
            body = ",\n".join(inner + _toml_value(x, inner) for x in items)
            return "[\n" + body + ",\n" + indent + "]"
        return "[" + ", ".join(_toml_value(x, indent) for x in items) + "]"
    raise ParameterError(f"cannot write a value of type {type(v).__name__} to TOML: {v!r}")


def _landmarks_dict(root):
    d = {"name": root.name, "units": "mm", "axis": root.axis.tolist(),
         "origin": root.origin.tolist(), "commissures": root.commissures.tolist(),
         "paths": [p.tolist() for p in root.paths]}
    if root.dimensions:
        d["dimensions"] = {str(k): (v.tolist() if isinstance(v, np.ndarray) else v)
                           for k, v in root.dimensions.items()}
    return d


def write_landmarks(root, path):
    """Write the landmarks of ``root`` (mm) as JSON or TOML, by the file's suffix."""
    p = pathlib.Path(path)
    d = _landmarks_dict(root)
    suffix = p.suffix.lower()
    if suffix == ".json":
        text = json.dumps(d, indent=1, allow_nan=False, default=_json_default) + "\n"
    elif suffix == ".toml":
        lines = []
        for k in ("name", "units", "axis", "origin", "commissures", "paths"):
            lines.append(f"{k} = {_toml_value(d[k])}")
        if "dimensions" in d:
            lines.append("\n[dimensions]")
            for k, v in d["dimensions"].items():
                if v is None:
                    continue
                lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        text = "\n".join(lines) + "\n"
    else:
        raise LandmarksFileError(f"landmarks file '{p}' must end in .json or .toml; got "
                                 f"'{suffix or '(no suffix)'}'")
    p.write_text(text, encoding="utf-8")
    return p


def _json_default(v):
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.bool_):
        return bool(v)
    raise TypeError(f"cannot write a value of type {type(v).__name__} to JSON: {v!r}")


def write_root(root, surface_path, landmarks_path):
    """Write ``root`` as a surface mesh (its ``wall``, any meshio format) and a landmarks
    file (JSON or TOML, mm).  `read_root` reads them back."""
    if not isinstance(root, AorticRoot):
        raise ParameterError(f"root must be an AorticRoot; got {type(root).__name__}")
    if root.wall is None:
        raise ParameterError("root.wall is None: write_root needs a wall surface to write to "
                             "surface_path (build the root with a wall)")
    if pathlib.Path(landmarks_path).suffix.lower() not in (".json", ".toml"):
        raise LandmarksFileError(f"landmarks file '{landmarks_path}' must end in .json or "
                                 ".toml")
    write_surface(surface_path, *root.wall)
    write_landmarks(root, landmarks_path)


def check_out_dir(path, flag: str = "--out") -> pathlib.Path | None:
    """Check, before any solve, that the output folder ``path`` can be written (None: no
    output folder): an existing folder must be writable; a missing one needs its nearest
    existing parent to be a writable folder (it is created when the outputs are written,
    so that a run refused later for bad input leaves nothing behind).  Raises
    `ParameterError` naming ``flag`` (the parameter, in the messages)."""
    if path is None:
        return None
    out = pathlib.Path(path)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"{flag} '{out}' is an existing file; {flag} takes a folder "
                             "(created if missing)")
    base = out if out.exists() else next(
        (p for p in out.absolute().parents if p.exists()), None)
    if base is None or not base.is_dir():
        raise ParameterError(f"{flag} '{out}': cannot create the folder under '{base}', "
                             "which is not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ParameterError(f"{flag} '{out}': '{base}' is not writable")
    return out
