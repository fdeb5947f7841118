"""From a CT volume to the aortic wall: the phantom, the segmentation, the surface and the
volume files (NIfTI, DICOM).  Small phantoms (0.8 mm voxels) keep each test to seconds."""
import numpy as np
import pytest

from jaxvalve.errors import MeshError, ParameterError
from jaxvalve.geometry.surface_query import distance_to_surface
from jaxvalve.imaging.phantom import RootPhantom, phantom_volume, true_wall
from jaxvalve.imaging.segment import SegmentParams, find_seed, segment
from jaxvalve.imaging.surface import _edges, mesh_quality, taubin, wall_surface
from jaxvalve.imaging.volume import Volume

PH = RootPhantom(spacing=(0.8, 0.8, 0.8), supersample=2, noise_hu=20.0)


@pytest.fixture(scope="module")
def scan():
    return phantom_volume(PH, seed=1)


@pytest.fixture(scope="module")
def seg(scan):
    return segment(scan)


def _voxel_points(v):
    return v.to_world(np.stack(np.meshgrid(*[np.arange(n) for n in v.shape], indexing="ij"),
                               axis=-1))


# ------------------------------------------------------------------------- phantom
def test_phantom_truth_is_the_zero_level_and_its_sinuses_differ():
    P, T = true_wall(PH, step=0.5)
    assert np.abs(PH.lumen_level(P)).max() < 0.02       # marching cubes of the level
    # three unequal sinuses: at mid-height each bulges by its own amount (radius - base)
    z_mid = 0.5 * PH.sinus_height
    th = np.deg2rad(np.array(PH.sinus_angles))
    h = (z_mid - PH.annulus_z(th)) / PH.sinus_height
    base = PH.r_lvot + (PH.r_stj - PH.r_lvot) * h
    bulge = (PH.lumen_radius(th, z_mid) - base) / np.sin(np.pi * h) ** 2
    np.testing.assert_allclose(bulge, PH.sinus_bulge, rtol=1e-9)
    # a tilted, non-planar annulus: its height varies round the root by more than 2 mm
    ring = PH.annulus_z(np.linspace(0, 2 * np.pi, 361))
    assert np.ptp(ring) > 2.0


def test_phantom_intensities_and_voxels(scan):
    assert scan.shape == tuple(int(n) for n in np.floor(np.subtract(*PH.extent()[::-1])
                                                        / 0.8) + 1)
    np.testing.assert_allclose(scan.spacing, 0.8)
    P = _voxel_points(scan)
    inside = PH.lumen_level(P) < -2.0
    fat = (PH.lumen_level(P) > 12.0) & (PH.neighbour_level(P) > 5.0)
    assert abs(np.mean(scan.data[inside]) - PH.blood_hu) < 2.0
    assert abs(np.mean(scan.data[fat]) - PH.fat_hu) < 2.0
    assert 15.0 < np.std(scan.data[inside]) < 25.0           # the noise, 20 HU
    with pytest.raises(ParameterError, match="spacing"):
        RootPhantom(spacing=(0.4, 0.4))
    with pytest.raises(ParameterError, match="neighbour_gap"):
        RootPhantom(neighbour_gap=0.0)
    with pytest.raises(ParameterError, match="sinus_angles"):
        RootPhantom(sinus_angles=(0.0, 120.0))


# ------------------------------------------------------------------- segmentation
def test_the_seed_is_the_ascending_aorta(scan):
    seed, circle = find_seed(scan)
    x, y, z = scan.to_world(seed)
    assert np.hypot(x, y) < 1.0 and z > PH.z_top - 4.0
    assert abs(circle["radius_mm"] - PH.r_stj) < 1.0
    # the neighbour is a candidate too, but smaller
    assert any(abs(c["radius_mm"] - PH.neighbour_radius) < 1.0 for c in circle["candidates"])


def test_segmentation_keeps_the_aorta_and_cuts_the_touching_neighbour(scan, seg):
    P = _voxel_points(scan)
    truth = PH.lumen_level(P) < 0
    neighbour = PH.neighbour_level(P) < 0
    rep = seg.report
    # region growing joined the neighbour (it touches the aorta in the image) ...
    assert rep["grow"]["voxels"] > truth.sum() + 0.8 * neighbour.sum()
    # ... and the opening cut it off, all but a rim of bridge voxels where they touch
    # (52 voxels of 8690 at this seed)
    assert (seg.mask & neighbour).sum() < 0.01 * neighbour.sum()
    dice = 2 * (seg.mask & truth).sum() / (seg.mask.sum() + truth.sum())
    assert dice > 0.97
    assert rep["seed"]["source"] == "hough" and rep["params"]["separation_mm"] == 2.0
    # a given seed gives the same mask
    again = segment(scan, seed=seg.seed)
    assert again.report["seed"]["source"] == "given"
    np.testing.assert_array_equal(again.mask, seg.mask)


def test_bad_segmentation_input_is_named():
    flat = Volume(np.full((20, 20, 10), -100.0, np.float32), np.eye(4))
    with pytest.raises(ParameterError, match="no bright circle"):
        segment(flat)
    with pytest.raises(ParameterError, match="min_blood_hu"):
        segment(flat, seed=(5, 5, 5))
    with pytest.raises(ParameterError, match="seed must be a voxel index"):
        segment(flat, seed=(5, 5, 50))
    with pytest.raises(ParameterError, match="radius_mm"):
        SegmentParams(radius_mm=(20.0, 8.0))
    with pytest.raises(ParameterError, match="wall_hu < min_blood_hu"):
        SegmentParams(wall_hu=200.0)
    with pytest.raises(ParameterError, match="3D"):
        Volume(np.zeros((4, 4)), np.eye(4))
    nan = np.zeros((4, 4, 4))
    nan[1, 2, 3] = np.nan
    with pytest.raises(ParameterError, match="1 values that are not finite"):
        Volume(nan, np.eye(4))


# ------------------------------------------------------------------------ surface
def test_wall_surface_lies_on_the_true_wall(scan, seg):
    P, T = wall_surface(scan, seg)
    truth = true_wall(PH, step=0.25)
    lo, hi = PH.extent()
    away = (P[:, 2] > lo[2] + 1.5) & (P[:, 2] < hi[2] - 1.5)    # off the open ends
    d = distance_to_surface(P[away], *truth)
    assert d.mean() < 0.3 and np.percentile(d, 95) < 1.0
    q = mesh_quality(P, T)
    assert q["non_manifold_edges"] == 0 and q["boundary_edges"] > 0     # an open tube
    assert 0.5 < q["edge_mm"]["mean"] < 1.0
    # remeshed to a target edge length: even triangles, still on the true wall
    P2, T2 = wall_surface(scan, seg, edge_mm=1.6)
    q2 = mesh_quality(P2, T2)
    assert 1.4 < q2["edge_mm"]["mean"] < 1.8 and len(T2) < len(T) / 2
    assert q["min_angle_deg"]["min"] < 5.0 < q2["min_angle_deg"]["min"]   # slivers gone
    assert q2["min_angle_deg"]["p5"] > 35.0 and q2["non_manifold_edges"] == 0
    away = (P2[:, 2] > lo[2] + 1.5) & (P2[:, 2] < hi[2] - 1.5)
    d2 = distance_to_surface(P2[away], *truth)
    assert d2.mean() < 0.3 and np.percentile(d2, 95) < 1.0
    with pytest.raises(ParameterError, match="edge_mm"):
        wall_surface(scan, seg, edge_mm=0.1)


def _sphere(r=10.0, step=0.5):
    from skimage import measure
    ax = np.arange(-r - 2, r + 2 + step / 2, step)
    X = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1)
    pts, tris, _, _ = measure.marching_cubes(np.linalg.norm(X, axis=-1), r,
                                             spacing=(step,) * 3)
    return pts + ax[0], tris


def _tube(r=8.0, step=0.5, height=12.0):
    """An open tube by marching cubes (slivers and all), outward normals."""
    from skimage import measure
    ax = np.arange(-r - 2, r + 2 + step / 2, step)
    az = np.arange(0.0, height + step / 2, step)
    X = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1)
    pts, tris, _, _ = measure.marching_cubes(np.hypot(X[..., 0], X[..., 1]), r,
                                             spacing=(step,) * 3)
    return pts + np.array([ax[0], ax[0], 0.0]), tris.astype(np.int64)


def _topology(T):
    """(Euler characteristic, boundary loops) of a triangle mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    e, count = _edges(T)
    b = e[count == 1]
    n = T.max() + 1
    _, lab = connected_components(coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])),
                                             shape=(n, n)), directed=False)
    return len(np.unique(T)) - len(e) + len(T), len(np.unique(lab[b.ravel()]))


def _outward(P, T):
    n = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    c = P[T].mean(axis=1)
    return np.mean(np.sum(n[:, :2] * c[:, :2], axis=1) > 0)


def test_remesh_makes_even_triangles_on_the_surface_and_keeps_its_topology():
    from jaxvalve.imaging.remesh import remesh
    P, T = _tube()
    q0 = mesh_quality(P, T)
    assert q0["min_angle_deg"]["min"] < 5.0                       # marching cubes' slivers
    sign = 1.0 if _outward(P, T) > 0.5 else -1.0
    for L in (0.8, 1.5):
        P2, T2 = remesh(P, T, L)
        q = mesh_quality(P2, T2)
        assert abs(q["edge_mm"]["mean"] - L) < 0.15 * L
        assert q["min_angle_deg"]["min"] > 25.0 and q["min_angle_deg"]["p5"] > 35.0
        # every vertex on the input surface (exact projection), so on the cylinder
        assert distance_to_surface(P2, P, T).max() < 1e-9
        assert np.abs(np.hypot(P2[:, 0], P2[:, 1]) - 8.0).max() < 0.02
        # the same topology (an open tube: chi 0, two loops) and orientation
        assert _topology(T2) == _topology(T) == (0, 2)
        assert q["non_manifold_edges"] == 0
        assert (_outward(P2, T2) if sign > 0 else 1 - _outward(P2, T2)) == 1.0
        # the area kept within 1 %
        area = lambda P, T: 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]],
                                                          P[T[:, 2]] - P[T[:, 0]]), axis=1).sum()
        assert abs(area(P2, T2) / area(P, T) - 1) < 0.01
    with pytest.raises(ParameterError, match="edge_mm"):
        remesh(P, T, 0.0)
    bad = np.vstack([T, [[T[0, 0], T[0, 1], len(P) - 1]]])       # a third face on an edge
    with pytest.raises(MeshError, match="manifold"):
        remesh(P, bad, 1.0)


def test_taubin_smooths_without_shrinking_where_a_laplacian_shrinks():
    P, T = _sphere()
    noisy = P + np.random.default_rng(0).normal(0, 0.1, P.shape)
    sm = taubin(noisy, T, iterations=20)
    r0, r1 = np.linalg.norm(noisy, axis=1), np.linalg.norm(sm, axis=1)
    assert abs(r1.mean() - 10.0) < 0.05                 # no shrinkage
    assert r1.std() < 0.5 * r0.std()                   # the noise is smoothed
    # the same number of plain Laplacian steps (lam = 0.5 each) shrinks the sphere
    from jaxvalve.imaging.surface import _umbrella
    M, lap = _umbrella(T, len(noisy)), noisy
    for _ in range(40):
        lap = lap + 0.5 * (M @ lap - lap)
    assert np.linalg.norm(lap, axis=1).mean() < 10.0 - 0.1
    with pytest.raises(ParameterError, match="lam < -mu"):
        taubin(P, T, lam=0.6, mu=-0.5)


# ---------------------------------------------------------------------- volume files
def test_nifti_round_trip_in_lps(tmp_path, scan, seg):
    from jaxvalve.io.volumes import read_mask, read_volume, write_mask, write_volume
    import nibabel as nib
    f = write_volume(tmp_path / "ct.nii.gz", scan)
    back = read_volume(f)
    np.testing.assert_array_equal(back.data, scan.data)
    np.testing.assert_allclose(back.affine, scan.affine)
    # on disk the affine is RAS: x and y change sign
    ras = nib.load(str(f)).affine
    np.testing.assert_allclose(ras[:2], -scan.affine[:2])
    np.testing.assert_allclose(ras[2:], scan.affine[2:])
    m = write_mask(tmp_path / "mask.nii.gz", seg.mask, scan)
    mask, aff = read_mask(m)
    np.testing.assert_array_equal(mask, seg.mask)
    np.testing.assert_allclose(aff, scan.affine)


def test_bad_volume_files_are_named(tmp_path):
    from jaxvalve.io.volumes import VolumeFileError, read_mask, read_volume, write_volume
    import nibabel as nib
    with pytest.raises(VolumeFileError, match="no such file"):
        read_volume(tmp_path / "none.nii")
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(VolumeFileError, match="not a NIfTI file"):
        read_volume(tmp_path / "a.txt")
    (tmp_path / "bad.nii").write_bytes(b"not nifti at all" * 30)
    with pytest.raises(VolumeFileError, match="bad.nii: unreadable NIfTI"):
        read_volume(tmp_path / "bad.nii")
    nib.save(nib.Nifti1Image(np.zeros((8, 8, 1), np.float32), np.eye(4)), str(tmp_path / "flat.nii"))
    with pytest.raises(VolumeFileError, match="flat.nii.*3D"):
        read_volume(tmp_path / "flat.nii")
    nib.save(nib.Nifti1Image(np.full((4, 4, 4), 3.0, np.float32), np.eye(4)),
             str(tmp_path / "notmask.nii"))
    with pytest.raises(VolumeFileError, match="only 0 and 1"):
        read_mask(tmp_path / "notmask.nii")
    with pytest.raises(VolumeFileError, match="as NIfTI"):
        write_volume(tmp_path / "x.mha", Volume(np.zeros((3, 3, 3)), np.eye(4)))
    with pytest.raises(VolumeFileError, match="no such file"):
        read_volume(tmp_path / "missing_folder")


def _write_dicom_series(folder, hu, spacing, origin, z_positions, *, series="1.2.3"):
    """A CT series of axial slices hu[:, :, k] (columns, rows) at z_positions."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid
    folder.mkdir(exist_ok=True)
    for k, z in enumerate(z_positions):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.SeriesInstanceUID, ds.Modality = series, "CT"
        plane = np.asarray(hu[:, :, k]).T                   # (rows, columns)
        ds.Rows, ds.Columns = plane.shape
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
        ds.PixelRepresentation, ds.SamplesPerPixel = 1, 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.PixelSpacing = [spacing[1], spacing[0]]          # (row, column) spacing
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [origin[0], origin[1], float(z)]
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = np.round(plane + 1024).astype(np.int16).tobytes()
        # shuffled names: the reader sorts by position, not by file name
        ds.save_as(str(folder / f"s{(7 * k) % len(z_positions):03d}.dcm"),
                   enforce_file_format=True)


def test_dicom_series_reads_in_hu_and_lps(tmp_path):
    from jaxvalve.io.volumes import VolumeFileError, read_volume
    rng = np.random.default_rng(0)
    hu = np.round(rng.uniform(-1000, 1500, (6, 5, 4)))
    _write_dicom_series(tmp_path / "ok", hu, (0.5, 0.7), (-10.0, 20.0),
                        [3.0, 3.6, 4.2, 4.8])
    (tmp_path / "ok" / "README").write_text("not DICOM")
    v = read_volume(tmp_path / "ok")
    np.testing.assert_array_equal(v.data, hu)
    np.testing.assert_allclose(v.spacing, [0.5, 0.7, 0.6])
    np.testing.assert_allclose(v.to_world([1, 2, 3]), [-9.5, 21.4, 4.8])
    _write_dicom_series(tmp_path / "gap", hu, (0.5, 0.7), (0.0, 0.0), [3.0, 3.6, 4.8, 5.4])
    with pytest.raises(VolumeFileError, match="gap: uneven slice spacing.*missing"):
        read_volume(tmp_path / "gap")
    _write_dicom_series(tmp_path / "one", hu[:, :, :1], (0.5, 0.7), (0.0, 0.0), [3.0])
    with pytest.raises(VolumeFileError, match="1 DICOM image slice"):
        read_volume(tmp_path / "one")
