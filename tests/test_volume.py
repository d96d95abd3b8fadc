"""CT volumes read into the scene's frame (`meshes.volume`): the formats SimpleITK reads, a
DICOM series, and a CBCT's fine voxels averaged."""

from pathlib import Path

import numpy as np
import pytest

#: The tests' tier (conftest.py): one part, no head.
TIER = "unit"


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd", ".mhd"])
def test_volume_formats_read_back_in_the_scene_frame(tmp_path, suffix):
    """NIfTI, NRRD and MetaImage (SimpleITK) give back the same voxels, spacing and origin in
    the scene's frame as the volume written (through LPS and back)."""
    from meshes.synthetic import synthetic_ct
    from meshes.volume import read_volume, write_volume

    v = synthetic_ct("class1", 4.0)
    write_volume(v, tmp_path / f"ct{suffix}")
    w = read_volume(tmp_path / f"ct{suffix}")
    assert np.array_equal(w.array, v.array)
    np.testing.assert_allclose(w.spacing, v.spacing, atol=1e-6)
    np.testing.assert_allclose(w.origin, v.origin, atol=1e-4)


def test_a_cbcts_fine_voxels_are_averaged_in_blocks():
    """Voxels finer than half of WORK_VOXEL_MM become block means (HU) or the block's middle
    label, each at its block's centre, so a position keeps its value; coarser ones stay."""
    from meshes.volume import WORK_VOXEL_MM, Volume

    sp = np.array([0.3, 0.4, 1.0])    # k = 3, 2, 1 per axis
    i, j = np.meshgrid(np.arange(10), np.arange(7), np.arange(4), indexing="ij")[:2]
    origin = np.array([-5.0, 2.0, 7.0])
    v = Volume((30 * i + 4 * j).astype(np.int16), sp, origin, "ct")   # linear in position
    w = v.coarsened()
    k = np.maximum(1, np.floor(WORK_VOXEL_MM / sp)).astype(int)
    assert k.tolist() == [3, 2, 1]
    assert w.array.shape == (3, 3, 4) and np.allclose(w.spacing, sp * k)
    np.testing.assert_allclose(w.origin, origin + sp * (k - 1) / 2)
    # a block's mean is the value at its centre (the last, partial blocks dropped)
    ci, cj = ((w.centres(a) - origin[a]) / sp[a] for a in (0, 1))
    np.testing.assert_allclose(w.array, (30 * ci[:, None, None] + 4 * cj[None, :, None])
                               + np.zeros((1, 1, 4)), atol=1e-4)
    labels = Volume(np.arange(10 * 7 * 4).reshape(10, 7, 4) % 3, sp, origin, "labels")
    m = labels.coarsened(labels=True)
    assert m.array.dtype == labels.array.dtype and m.array.shape == (3, 3, 4)
    assert np.array_equal(m.array, labels.array[1:9:3, 1:7:2])   # each block's middle voxel
    np.testing.assert_allclose(m.origin, w.origin)
    coarse = Volume(v.array, np.array([0.5, 0.96, 3.2]), origin, "ct")
    assert coarse.coarsened() is coarse


def _write_dicom_series(v, folder: Path) -> None:
    """``v`` as a CT DICOM series, one file per axial slice, with the tags a scanner writes
    (position and orientation in LPS, spacing, slice thickness, int16 HU: SimpleITK's
    DICOM series example)."""
    import SimpleITK as sitk

    from meshes.volume import F

    image = sitk.GetImageFromArray(np.ascontiguousarray(v.array.transpose(2, 1, 0)
                                                        .astype(np.int16)))
    image.SetSpacing([float(s) for s in v.spacing])
    image.SetOrigin([float(o) for o in F @ v.origin])
    image.SetDirection(F.ravel().tolist())
    D = np.array(image.GetDirection()).reshape(3, 3)
    orientation = "\\".join(f"{c:g}" for c in (*D[:, 0], *D[:, 1]))
    folder.mkdir()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(image.GetDepth()):
        sl = image[:, :, k]
        for tag, value in {
                "0008|0060": "CT", "0008|0016": "1.2.840.10008.5.1.4.1.1.2",
                "0020|000d": "1.2.826.0.1.3680043.2.1125.1", "0020|000e":
                "1.2.826.0.1.3680043.2.1125.1.1", "0020|0037": orientation,
                "0020|0032": "\\".join(f"{c:.6f}" for c in
                                        image.TransformIndexToPhysicalPoint((0, 0, k))),
                "0020|0013": str(k + 1), "0018|0050": f"{v.spacing[2]:g}",
                "0028|1053": "1", "0028|1052": "0",
                "0008|0018": f"1.2.826.0.1.3680043.2.1125.1.1.{k + 1}"}.items():
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"slice{k:04d}.dcm"))
        writer.Execute(sl)


def test_dicom_series_folder_reads_back_in_the_scene_frame(tmp_path):
    """A DICOM series (a folder, as a scanner or PACS exports it) gives back the voxels,
    spacing and origin of the volume written, in the scene's frame."""
    from meshes.synthetic import synthetic_ct
    from meshes.volume import read_volume

    v = synthetic_ct("class1", 4.0)
    _write_dicom_series(v, tmp_path / "series")
    w = read_volume(tmp_path / "series")
    assert np.array_equal(w.array, v.array)
    np.testing.assert_allclose(w.spacing, v.spacing, atol=1e-5)
    np.testing.assert_allclose(w.origin, v.origin, atol=1e-4)
