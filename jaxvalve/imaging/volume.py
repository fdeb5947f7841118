"""A CT volume in physical coordinates: voxel values (Hounsfield units) and the affine map
from voxel indices to patient coordinates (LPS, mm: x to the patient's left, y to the
back, z to the head, the DICOM convention; NIfTI's RAS is converted on reading)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ParameterError

__all__ = ["Volume"]


@dataclasses.dataclass(frozen=True, eq=False)
class Volume:
    """data (I, J, K) float32 HU; affine (4, 4): LPS mm = affine @ (i, j, k, 1)."""

    data: np.ndarray
    affine: np.ndarray

    def __post_init__(self):
        d = np.asarray(self.data)
        if d.ndim != 3 or min(d.shape) < 2:
            raise ParameterError(f"a CT volume must be 3D with at least 2 voxels along "
                                 f"each axis; got an array of shape {d.shape}")
        bad = int(np.sum(~np.isfinite(d)))
        if bad:
            raise ParameterError(f"a CT volume holds {bad} values that are not finite (NaN "
                                 "or inf)")
        a = np.asarray(self.affine, float)
        if a.shape != (4, 4) or not np.all(np.isfinite(a)):
            raise ParameterError(f"a volume's affine must be a finite 4 x 4 matrix; got "
                                 f"shape {a.shape}")
        if abs(np.linalg.det(a[:3, :3])) < 1e-12:
            raise ParameterError("a volume's affine is singular (a voxel size of 0)")
        object.__setattr__(self, "data", d)
        object.__setattr__(self, "affine", a)

    @property
    def shape(self):
        return self.data.shape

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along each index axis, mm (3,)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def to_world(self, ijk) -> np.ndarray:
        """Index coordinates (..., 3), fractional allowed, to LPS mm (..., 3)."""
        ijk = np.asarray(ijk, float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def to_index(self, xyz) -> np.ndarray:
        """LPS mm (..., 3) to fractional index coordinates (..., 3)."""
        inv = np.linalg.inv(self.affine[:3, :3])
        return (np.asarray(xyz, float) - self.affine[:3, 3]) @ inv.T

    def axial_axis(self) -> tuple[int, int]:
        """(index axis nearest the patient's z, +1 or -1: whether z grows with it)."""
        col = self.affine[:3, :3] / self.spacing
        ax = int(np.argmax(np.abs(col[2])))
        return ax, int(np.sign(col[2, ax]))
