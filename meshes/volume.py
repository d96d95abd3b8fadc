"""CT volumes read into orthodiff's frame.

`read_volume(path)` reads a DICOM series (a folder), NIfTI (``.nii``, ``.nii.gz``), NRRD,
MetaImage (``.mha``/``.mhd``) with SimpleITK, which honours spacing, origin and direction
cosines, and InVesalius projects (``.inv3``). The image's patient frame (LPS: x to the
patient's left, y to posterior, z to superior) becomes orthodiff's (x left, y anterior,
z superior): ``x_ours = diag(1, -1, 1) x_LPS``, the same map as `meshes.transforms`. The
voxels are reoriented (permuted and flipped, no interpolation) so that array axes 0, 1, 2
run along +x, +y, +z; an oblique image (gantry tilt) is resampled linearly onto that grid.
"""

from __future__ import annotations

import dataclasses
import plistlib
import tarfile
from pathlib import Path

import numpy as np

from meshes.errors import MeshError

#: LPS -> orthodiff frame (x left, y anterior, z superior).
F = np.diag([1.0, -1.0, 1.0])
#: Largest deviation of a direction cosine from the axes before an image is resampled.
AXIS_TOL = 1e-4
#: The CT pipeline works on voxels at least this far apart (mm, `Volume.coarsened`): a CBCT's
#: 0.2-0.4 mm voxels are averaged in blocks of k per axis, k = floor(WORK_VOXEL_MM / voxel).
#: A mesh edge of 1.4 mm (fine) or more cannot use finer detail, and the averaging cuts a
#: CBCT's noise. Cranium resampled at 0.4 mm (612 x 612 x 405 voxels) to a paper scene, AMD
#: EPYC, 1 rank: 59.0 s and 2.9 GB peak on every voxel (the frame estimated on every 2nd);
#: figures of the averaged grid in BENCHMARKS.md (`bench.py ct`). Voxels of 0.45 mm or more
#: (Cranium 0.96 mm, headsq 1.5-3.2 mm, every test CT) are used as they are.
WORK_VOXEL_MM = 0.9


@dataclasses.dataclass
class Volume:
    """A scalar volume on an axis-aligned grid in orthodiff's frame.

    Attributes:
        array: (nx, ny, nz) values (HU for a CT, labels for a label map); axis 0 runs along
            +x (left), 1 along +y (anterior), 2 along +z (superior).
        spacing: (3,) voxel size, mm.
        origin: (3,) position of voxel (0, 0, 0)'s centre, mm.
        name: source, for messages and reports.
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    name: str = "volume"

    def centres(self, axis: int) -> np.ndarray:
        """Voxel-centre coordinates (n_axis,) mm along one axis."""
        return self.origin[axis] + self.spacing[axis] * np.arange(self.array.shape[axis])

    def at(self, points: np.ndarray) -> np.ndarray:
        """Values (K,) of the voxels nearest to points (K, 3) mm (clamped to the grid)."""
        ijk = np.rint((np.asarray(points, float) - self.origin) / self.spacing).astype(int)
        ijk = np.clip(ijk, 0, np.array(self.array.shape) - 1)
        return self.array[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    def crop(self, lo, hi) -> "Volume":
        """The sub-volume of the voxels whose centres lie in the box [lo, hi] (mm)."""
        sl = []
        for a in range(3):
            c = self.centres(a)
            keep = np.flatnonzero((c >= lo[a]) & (c <= hi[a]))
            if len(keep) == 0:
                raise MeshError(f"the crop [{lo[a]:g}, {hi[a]:g}] mm along {'xyz'[a]} leaves no "
                                f"voxel of {self.name} (it spans [{c[0]:g}, {c[-1]:g}] mm)")
            sl.append(slice(keep[0], keep[-1] + 1))
        origin = self.origin + self.spacing * np.array([s.start for s in sl])
        return Volume(self.array[tuple(sl)], self.spacing.copy(), origin, self.name)

    def coarsened(self, min_mm: float = WORK_VOXEL_MM, labels: bool = False) -> "Volume":
        """The volume on voxels about ``min_mm`` apart where its own are finer: blocks of k
        voxels per axis (k = floor(min_mm / spacing), at least 1; a partial block at the far
        end is dropped) become one at their centre, the mean (HU, float32) or, for a label
        map (``labels``), the label at the block's middle voxel. ``self`` where every k is 1."""
        k = np.maximum(1, np.floor(min_mm / self.spacing * (1 + 1e-9))).astype(int)   # 1.2/0.4
        if (k == 1).all():
            return self
        n = np.array(self.array.shape) // k
        if labels:
            a = self.array[tuple(slice(j // 2, j // 2 + m * j, j) for j, m in zip(k, n))]
        else:
            a = self.array[:n[0] * k[0], :n[1] * k[1], :n[2] * k[2]]
            a = a.reshape(n[0], k[0], n[1], k[1], n[2], k[2]).mean(axis=(1, 3, 5),
                                                                  dtype=np.float32)
        return Volume(np.ascontiguousarray(a), self.spacing * k,
                      self.origin + self.spacing * (k - 1) / 2, self.name)


def read_volume(path) -> Volume:
    """Read a CT or label volume (see the module docstring); raises `MeshError` with one line
    when the file is no readable 3-D image."""
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path} does not exist")
    if path.suffix.lower() == ".inv3":
        return _read_inv3(path)
    return _read_sitk(path)


def _read_sitk(path: Path) -> Volume:
    import SimpleITK as sitk

    try:
        if path.is_dir():
            reader = sitk.ImageSeriesReader()
            files = reader.GetGDCMSeriesFileNames(str(path))
            if not files:
                raise MeshError(f"{path} is a folder with no DICOM series")
            reader.SetFileNames(files)
            image = reader.Execute()
        else:
            image = sitk.ReadImage(str(path))
    except RuntimeError as e:
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        why = next((ln for ln in reversed(lines) if "ERROR" in ln), lines[-1] if lines else "")
        why = why.split("ERROR:", 1)[-1].strip()
        raise MeshError(f"cannot read {path} as an image (DICOM folder, NIfTI, NRRD, MetaImage "
                        f"or .inv3): {why[:160]}") from None
    if image.GetDimension() != 3 or min(image.GetSize()) < 2:
        raise MeshError(f"{path} is a {image.GetDimension()}-D image of size "
                        f"{list(image.GetSize())}; a 3-D volume is needed")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise MeshError(f"{path} has {image.GetNumberOfComponentsPerPixel()} components per "
                        "voxel; a scalar CT or label volume is needed")
    image = sitk.DICOMOrient(image, "LAS")   # axes along +x L, +y A, +z S (in LPS: diag F)
    D = np.array(image.GetDirection()).reshape(3, 3)
    if np.abs(D - F).max() > AXIS_TOL:   # oblique: resample onto the aligned grid
        image = _resample_aligned(image)
    array = sitk.GetArrayFromImage(image).transpose(2, 1, 0)   # (z, y, x) -> (x, y, z)
    return Volume(np.ascontiguousarray(array), np.array(image.GetSpacing(), float),
                  F @ np.array(image.GetOrigin(), float), path.name)


def _resample_aligned(image):
    """Linear resampling of an oblique image onto the axis-aligned grid that covers it."""
    import SimpleITK as sitk

    size = np.array(image.GetSize())
    corners = np.array([image.TransformContinuousIndexToPhysicalPoint(
        [float(c) for c in np.array([i, j, k]) * (size - 1)])
        for i in (0, 1) for j in (0, 1) for k in (0, 1)]) @ F   # ours (F is its own inverse)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    spacing = np.full(3, min(image.GetSpacing()))
    n = np.ceil((hi - lo) / spacing).astype(int) + 1
    ref = sitk.Image([int(v) for v in n], image.GetPixelID())
    ref.SetSpacing(spacing.tolist())
    ref.SetDirection(F.ravel().tolist())
    ref.SetOrigin((F @ lo).tolist())
    low = float(sitk.GetArrayViewFromImage(image).min())
    return sitk.Resample(image, ref, sitk.Transform(), sitk.sitkLinear, low)


def _read_inv3(path: Path) -> Volume:
    """An InVesalius 3 project: a gzipped tar of ``main.plist`` (shape, spacing, dtype) and
    ``matrix.dat`` (C-order (z, y, x) int16 HU, axial slices from inferior to superior, image
    rows from posterior to anterior, columns to the patient's left: InVesalius stores its
    slices flipped vertically, as VTK draws them). The origin is not stored: voxel
    (0, 0, 0) is put at 0."""
    try:
        with tarfile.open(path, "r:*") as tar:
            members = {Path(m.name).name: m for m in tar.getmembers() if m.isfile()}
            main = plistlib.loads(tar.extractfile(members["main.plist"]).read())
            info = main["matrix"]
            raw = tar.extractfile(members[Path(info["filename"]).name]).read()
    except (tarfile.TarError, KeyError, OSError, plistlib.InvalidFileException) as e:
        raise MeshError(f"cannot read {path} as an InVesalius project (.inv3): "
                        f"{type(e).__name__}: {e}") from None
    shape = tuple(int(s) for s in info["shape"])
    if len(shape) != 3:
        raise MeshError(f"{path}: a {len(shape)}-D matrix; a 3-D volume is needed")
    if int(main.get("orientation", 1)) != 1:
        raise MeshError(f"{path}: only axial InVesalius projects are supported (orientation "
                        f"{main.get('orientation')})")
    data = np.frombuffer(raw, dtype=np.dtype(info["dtype"]))
    if data.size != np.prod(shape):
        raise MeshError(f"{path}: matrix.dat holds {data.size} values, the shape {shape} "
                        f"needs {np.prod(shape)}")
    array = data.reshape(shape).transpose(2, 1, 0)   # (z, y, x) -> (x, y, z)
    spacing = np.array(main["spacing"], dtype=float)
    return Volume(np.ascontiguousarray(array), spacing, np.zeros(3), path.name)


def write_volume(volume: Volume, path) -> None:
    """Write ``volume`` with SimpleITK (format by suffix: .mha, .nii.gz, .nrrd ...) in its
    patient frame (LPS), so that `read_volume` gives it back."""
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.ascontiguousarray(volume.array.transpose(2, 1, 0)))
    image.SetSpacing([float(s) for s in volume.spacing])
    image.SetOrigin([float(v) for v in F @ volume.origin])
    image.SetDirection(F.ravel().tolist())
    sitk.WriteImage(image, str(path))


def rotate_volume(volume: Volume, R, centre, fill: float | None = None) -> Volume:
    """The volume with its content rotated by R (3, 3) about ``centre`` (3,) mm, resampled
    (linearly) on the axis-aligned grid of the same spacing that covers it: a head tilted in
    the scanner. Voxels from outside the input get ``fill`` (default: its minimum, air)."""
    from scipy import ndimage

    R, c = np.asarray(R, float), np.asarray(centre, float)
    s, o = volume.spacing, volume.origin
    n = np.array(volume.array.shape)
    corners = o + np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) \
        * (n - 1) * s
    moved = (corners - c) @ R.T + c
    lo, hi = moved.min(axis=0), moved.max(axis=0)
    shape = np.ceil((hi - lo) / s).astype(int) + 1
    # output index j -> position x = lo + j s -> source R^T (x - c) + c -> index (.. - o) / s
    matrix = (R.T * s[None, :]) / s[:, None]
    offset = (R.T @ (lo - c) + c - o) / s
    fill = float(volume.array.min()) if fill is None else float(fill)
    out = ndimage.affine_transform(volume.array.astype(np.float32), matrix, offset,
                                   output_shape=tuple(shape), order=1, cval=fill)
    return Volume(np.rint(out).astype(volume.array.dtype), s.copy(), lo,
                  f"{volume.name} rotated")
