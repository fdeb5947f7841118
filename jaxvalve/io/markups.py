"""3D Slicer markups files (``.mrk.json``): point lists and curves, in LPS millimetres.

A markups file holds a list ``markups``; each has a ``type`` (``Fiducial`` for a point
list, ``Curve``, ``ClosedCurve``, ``Line``, ...), a ``coordinateSystem`` (``LPS``, the
default since Slicer 4.11, or ``RAS``), optional ``coordinateUnits`` (``mm`` or ``um``)
and ``controlPoints``, each with a ``label`` and a ``position``.  `read_markups` returns
every markup with its points converted to LPS mm (RAS -> LPS negates x and y); control
points whose ``positionStatus`` is ``undefined`` (placeholders not yet placed in Slicer)
are left out.  `write_markups` writes a file Slicer loads (schema 1.0.3), in LPS or RAS.
What the points mean for a valve (commissures, nadirs, suture paths) is decided in
`jaxvalve.geometry.landmarks`.  Every problem raises `MarkupsFileError` naming the file.
"""
from __future__ import annotations

import dataclasses
import json
import pathlib

import numpy as np

from ..errors import LandmarksFileError

__all__ = ["Markup", "MarkupsFileError", "read_markups", "write_markups", "is_markups_file",
           "SCHEMA"]

SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
          "Resources/Schema/markups-schema-v1.0.3.json#")
_UNITS = {"mm": 1.0, "um": 1e-3}
_FLIP = np.array([-1.0, -1.0, 1.0])          # RAS <-> LPS


class MarkupsFileError(LandmarksFileError):
    """A Slicer markups file cannot be read or written; the message names the file."""


@dataclasses.dataclass(frozen=True)
class Markup:
    """One markup: ``kind`` (Slicer's ``type``), control point ``labels`` (K,) and
    ``points`` (K, 3) in LPS mm, optional ``name`` and ``description``."""

    kind: str
    labels: tuple
    points: np.ndarray
    name: str = ""
    description: str = ""

    def __post_init__(self):
        pts = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "labels", tuple(str(s) for s in self.labels))
        if len(self.labels) != len(pts):
            raise MarkupsFileError(f"markup '{self.name}': {len(self.labels)} labels for "
                                   f"{len(pts)} points")
        if not np.all(np.isfinite(pts)):
            raise MarkupsFileError(f"markup '{self.name}': a point holds NaN or inf")


def is_markups_file(path) -> bool:
    """Whether ``path`` names a Slicer markups file (``.mrk.json``)."""
    return str(path).lower().endswith(".mrk.json")


def read_markups(path) -> list[Markup]:
    """Every markup of a Slicer ``.mrk.json`` file, points in LPS mm."""
    p = pathlib.Path(path)
    if not p.is_file():
        raise MarkupsFileError(f"markups file '{p}' does not exist or is not a file")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise MarkupsFileError(f"markups file '{p}' is not valid JSON: {e}") from None
    items = data.get("markups") if isinstance(data, dict) else None
    if not isinstance(items, list) or not items:
        raise MarkupsFileError(f"markups file '{p}' has no 'markups' list (a Slicer .mrk.json "
                               "holds {\"markups\": [{\"type\": ..., \"controlPoints\": "
                               "[...]}]})")
    out = []
    for m, item in enumerate(items):
        where = f"markups file '{p}', markups[{m}]"
        if not isinstance(item, dict):
            raise MarkupsFileError(f"{where} must be an object")
        kind = item.get("type")
        if not isinstance(kind, str):
            raise MarkupsFileError(f"{where}: 'type' must be a string (Fiducial, Curve, ...); "
                                   f"got {kind!r}")
        system = str(item.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise MarkupsFileError(f"{where}: coordinateSystem must be 'LPS' or 'RAS'; got "
                                   f"{item.get('coordinateSystem')!r}")
        units = item.get("coordinateUnits", "mm")
        if isinstance(units, list) and units:       # the coded form ["mm", "UCUM", ...]
            units = units[0]
        if units not in _UNITS:
            raise MarkupsFileError(f"{where}: coordinateUnits must be one of {list(_UNITS)}; "
                                   f"got {units!r}")
        cps = item.get("controlPoints", [])
        if not isinstance(cps, list):
            raise MarkupsFileError(f"{where}: 'controlPoints' must be a list")
        labels, pts = [], []
        for k, cp in enumerate(cps):
            if not isinstance(cp, dict):
                raise MarkupsFileError(f"{where}.controlPoints[{k}] must be an object")
            if cp.get("positionStatus", "defined") != "defined":
                continue
            pos = cp.get("position")
            ok = (isinstance(pos, list) and len(pos) == 3
                  and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                          for v in pos))
            if not ok or not np.all(np.isfinite(np.asarray(pos, float))):
                raise MarkupsFileError(f"{where}.controlPoints[{k}].position must be three "
                                       f"finite numbers; got {pos!r}")
            pts.append(np.asarray(pos, float) * _UNITS[units])
            labels.append(str(cp.get("label", f"{k + 1}")))
        pts = np.asarray(pts, float).reshape(-1, 3)
        if system == "RAS":
            pts = pts * _FLIP
        out.append(Markup(kind, tuple(labels), pts, str(item.get("name", "")),
                          str(item.get("description", ""))))
    return out


def write_markups(path, markups, coordinate_system: str = "LPS") -> pathlib.Path:
    """Write ``markups`` (a list of `Markup`, points in LPS mm) as a Slicer ``.mrk.json``
    in ``coordinate_system`` (``LPS`` or ``RAS``).  Returns the path."""
    p = pathlib.Path(path)
    if not is_markups_file(p):
        raise MarkupsFileError(f"markups file '{p}' must end in .mrk.json")
    system = str(coordinate_system).upper()
    if system not in ("LPS", "RAS"):
        raise MarkupsFileError(f"coordinate_system must be 'LPS' or 'RAS'; got "
                               f"{coordinate_system!r}")
    items = []
    for m in markups:
        if not isinstance(m, Markup):
            raise MarkupsFileError(f"markups must be Markup objects; got {type(m).__name__}")
        pts = m.points * _FLIP if system == "RAS" else m.points
        item = {"type": m.kind, "coordinateSystem": system, "coordinateUnits": "mm",
                "controlPoints": [
                    {"id": str(k + 1), "label": lab, "position": [float(v) for v in x],
                     "positionStatus": "defined"}
                    for k, (lab, x) in enumerate(zip(m.labels, pts))]}
        if m.name:
            item["name"] = m.name
        if m.description:
            item["description"] = m.description
        items.append(item)
    p.write_text(json.dumps({"@schema": SCHEMA, "markups": items}, indent=1,
                            allow_nan=False) + "\n", encoding="utf-8")
    return p
