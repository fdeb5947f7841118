"""CT volumes in and out: NIfTI (``.nii``, ``.nii.gz``, through nibabel) and a folder of
DICOM slices (pydicom), as a `jaxvalve.imaging.volume.Volume` in Hounsfield units and LPS
millimetres.  NIfTI stores RAS: x and y change sign on the way in and out.  Every
problem raises a `VolumeFileError` naming the file and what is wrong."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import RootFileError
from ..imaging.volume import Volume

__all__ = ["VolumeFileError", "read_volume", "write_volume", "write_mask", "read_mask"]

#: RAS <-> LPS: the same matrix both ways
_FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])


class VolumeFileError(RootFileError):
    """A CT volume or mask file (or DICOM folder) is missing, unreadable or not a 3D volume."""


def _nifti(path: Path) -> bool:
    return path.name.endswith((".nii", ".nii.gz"))


def read_volume(path) -> Volume:
    """The CT volume of a NIfTI file or a folder of DICOM slices (module docstring)."""
    path = Path(path)
    if not path.exists():
        raise VolumeFileError(f"{path}: no such file or folder")
    if path.is_dir():
        return _read_dicom(path)
    if not _nifti(path):
        raise VolumeFileError(f"{path}: not a NIfTI file (.nii, .nii.gz) or a DICOM folder")
    import nibabel as nib
    try:
        img = nib.load(str(path))
        data = np.asarray(img.get_fdata(dtype=np.float32))
    except Exception as e:      # nibabel raises several kinds
        raise VolumeFileError(f"{path}: unreadable NIfTI ({type(e).__name__}: {e})") from e
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3 or min(data.shape) < 2:
        raise VolumeFileError(f"{path}: not a 3D volume (array of shape {data.shape})")
    return _volume(path, data, _FLIP @ np.asarray(img.affine, float))


def _volume(path, data, affine):
    try:
        return Volume(data, affine)
    except Exception as e:
        raise VolumeFileError(f"{path}: {e}") from e


def write_volume(path, volume: Volume, data=None, dtype=np.float32) -> Path:
    """Write ``data`` (default the volume's) on the volume's grid as NIfTI (RAS affine)."""
    import nibabel as nib
    path = Path(path)
    if not _nifti(path):
        raise VolumeFileError(f"{path}: a volume is written as NIfTI (.nii or .nii.gz)")
    arr = np.asarray(volume.data if data is None else data).astype(dtype)
    if arr.shape != volume.shape:
        raise VolumeFileError(f"{path}: data of shape {arr.shape} on a volume of shape "
                              f"{volume.shape}")
    img = nib.Nifti1Image(arr, _FLIP @ volume.affine)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(path))
    return path


def write_mask(path, mask, volume: Volume) -> Path:
    """A segmentation mask (bool, the volume's shape) as a uint8 NIfTI on its grid."""
    return write_volume(path, volume, np.asarray(mask, bool), dtype=np.uint8)


def read_mask(path) -> tuple[np.ndarray, np.ndarray]:
    """A mask written by `write_mask`: (bool array, LPS affine)."""
    v = read_volume(path)
    if not np.all(np.isin(v.data, (0.0, 1.0))):
        raise VolumeFileError(f"{path}: a mask holds only 0 and 1")
    return v.data > 0.5, v.affine


def _read_dicom(folder: Path) -> Volume:
    """A folder of axial (or any parallel) DICOM slices of one series: sorted along the
    slice normal, checked for one orientation, one pixel grid and even spacing (a
    missing slice shows as a gap), scaled to HU by RescaleSlope and RescaleIntercept."""
    import pydicom
    files = sorted(p for p in folder.iterdir() if p.is_file())
    slices = []
    for f in files:
        try:
            ds = pydicom.dcmread(str(f))
        except Exception:
            continue                      # not DICOM (a readme, a thumbnail)
        if "PixelData" in ds:
            slices.append((f, ds))
    if len(slices) < 2:
        raise VolumeFileError(f"{folder}: {len(slices)} DICOM image slice(s); a volume needs "
                              "at least 2")
    series = {str(ds.get("SeriesInstanceUID", "")) for _, ds in slices}
    if len(series) > 1:
        raise VolumeFileError(f"{folder}: slices of {len(series)} series; give one series a "
                              "folder")
    try:
        orient = np.array([[float(v) for v in ds.ImageOrientationPatient] for _, ds in slices])
        pos = np.array([[float(v) for v in ds.ImagePositionPatient] for _, ds in slices])
        px = np.array([[float(v) for v in ds.PixelSpacing] for _, ds in slices])
    except AttributeError as e:
        raise VolumeFileError(f"{folder}: a slice lacks its geometry ({e})") from e
    if np.ptp(orient, axis=0).max() > 1e-4:
        raise VolumeFileError(f"{folder}: the slices have different orientations")
    if np.ptp(px, axis=0).max() > 1e-4:
        raise VolumeFileError(f"{folder}: the slices have different pixel spacings")
    row, col = orient[0, :3], orient[0, 3:]
    normal = np.cross(row, col)
    order = np.argsort(pos @ normal)
    pos, slices = pos[order], [slices[i] for i in order]
    gaps = np.diff(pos @ normal)
    if gaps.min() <= 1e-6:
        raise VolumeFileError(f"{folder}: two slices at the same position "
                              f"({slices[int(np.argmin(gaps))][0].name})")
    if np.ptp(gaps) > 1e-3 * max(gaps.min(), 1e-6) + 1e-3:
        k = int(np.argmax(gaps))
        raise VolumeFileError(f"{folder}: uneven slice spacing ({gaps.min():.4g} to "
                              f"{gaps.max():.4g} mm): a slice is missing after "
                              f"{slices[k][0].name}?")
    try:
        planes = []
        for f, ds in slices:
            a = np.asarray(ds.pixel_array, np.float32)
            planes.append(a * float(ds.get("RescaleSlope", 1.0))
                          + float(ds.get("RescaleIntercept", 0.0)))
    except Exception as e:
        raise VolumeFileError(f"{folder}: unreadable pixel data ({e})") from e
    if len({p.shape for p in planes}) > 1:
        raise VolumeFileError(f"{folder}: the slices have different sizes")
    # pixel_array is (rows, columns): rows advance along col, columns along row
    data = np.stack([p.T for p in planes], axis=-1)       # (columns, rows, slices)
    affine = np.eye(4)
    affine[:3, 0] = row * px[0, 1]        # PixelSpacing = (row spacing, column spacing)
    affine[:3, 1] = col * px[0, 0]
    affine[:3, 2] = normal * float(np.mean(gaps))
    affine[:3, 3] = pos[0]
    return _volume(folder, data, affine)
