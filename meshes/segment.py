"""A CT volume (HU) or a label map to the labelled volume the mesher needs.

Labels: `OUTSIDE` (air around the head), `AIRWAY` (air inside it), `TISSUE` (the soft tissue
that is meshed), `BONE`, `CROP` (beyond a held crop face), `CROP_FREE` (beyond a free one).

Decisions, each for a reason:

* **Body**: HU > ``skin_hu``, the largest 6-connected component (drops the headrest and the
  table, which air separates from the head).
* **Bone**: HU > ``bone_hu`` inside the body, closed by one voxel (thin orbital and sinus walls
  fall below the threshold by partial volume and would leak), bone specks smaller than
  `MIN_BONE_MM3` (streaks of dental fillings, calcifications) are tissue.
* **Air inside the head** (nasal airway, sinuses, a closed mouth): the air that no axial
  slice connects to the air around the head, and any air the body encloses in 3-D. It stays
  air: its walls are free surfaces, not skin. Filling it with tissue would tie the nose and
  the lips to the nasal floor and the tongue with a stiffness they do not have; it carries no
  landmark and is not seen. Air pockets smaller than `MIN_AIR_MM3` (dark streaks of fillings
  inside the lips) are tissue.
* **The skull is hollow**: soft tissue that does not touch the air around the head (the
  brain, marrow, the contents of a closed sinus) is not simulated; it is labelled bone, the
  rigid skull it lies in.
* **Crop**: the region of interest, a box in mm. Its faces get the Dirichlet condition u = 0
  of the synthetic heads' rim (tissue cut far from the osteotomies, attached to fixed bone
  beyond the crop) unless named free, e.g. a field of view that ends through the lip.
"""

from __future__ import annotations

import numpy as np

from meshes.errors import MeshError
from meshes.volume import Volume

OUTSIDE, AIRWAY, TISSUE, BONE, CROP, CROP_FREE = 0, 1, 2, 3, 4, 5
#: Thresholds, HU. Skin: halfway between air (-1000) and fat (-100); the skin edge is steep, so
#: ±100 HU moves it by less than a voxel (headsq: VTK's example uses -524). Bone: above
#: muscle and enhanced vessels (< 100 HU), below cortical bone (> 700 HU); 3D Slicer's and
#: InVesalius's bone presets use 226 (Cranium.inv3's own mask), VTK's headsq example 126:
#: the 3.2 mm voxels of headsq blur thin bone, so its example file sets 150.
SKIN_HU, BONE_HU = -400.0, 226.0
#: Bone components below this volume (mm³) are tissue: metal streaks, calcified nodes.
MIN_BONE_MM3 = 30.0
#: Enclosed air pockets below this volume (mm³) are tissue: dark streaks inside the lips.
MIN_AIR_MM3 = 100.0
#: Largest share of the bone surface voxels that may touch the air around the head (teeth
#: between parted lips, a thin scalp at coarse voxels) before the input is refused.
BONE_EXPOSED_MAX = 0.25
#: Label-map values (3D Slicer segmentation exported as NRRD/NIfTI): 0 air, 1 soft tissue,
#: 2 bone, unless a mapping is given. A mapping may also name ``"fat"`` and ``"muscle"``
#: (lean tissue) labels, which are soft tissue too; with ``"fat"`` the scene has tissue
#: classes (`meshes.tissue`), fat where the label is, lean tissue elsewhere.
LABELMAP_DEFAULT = {"tissue": 1, "bone": 2}
#: Crop faces, named by axis and side.
FACES = ("-x", "+x", "-y", "+y", "-z", "+z")
#: The face's envelope (`envelope_depth`): the labelled body closed by this radius (mm),
#: wider than a nostril (7-12 mm) or an ear canal's opening (7-9 mm), so that both close.
ENVELOPE_CLOSE_MM = 12.0
#: The envelope's voxels (mm, `Volume.coarsened` of the body): a depth read against a 6 mm
#: lining (`meshes.ct.LINING_MM`) after a 12 mm closing needs no finer grid. Cranium at paper
#: on its own 0.96 mm voxels: 1.73 s, 0.69 s on 1.92 mm, 31 of 183921 cells' tissue changed,
#: the landmarks of a 5 mm LeFort I within 0.003 mm (its CBCT-size copy: BENCHMARKS.md, ct).
ENVELOPE_VOXEL_MM = 2.0


def _components(mask, structure=None):
    from scipy import ndimage

    return ndimage.label(mask, structure=structure)


def _drop_small(mask, min_voxels: int) -> np.ndarray:
    """mask without its 6-connected components of fewer than min_voxels voxels."""
    lab, n = _components(mask)
    if n == 0:
        return mask
    size = np.bincount(lab.ravel())
    small = size < min_voxels
    small[0] = False
    return mask & ~small[lab]


def fill_axial(mask) -> np.ndarray:
    """mask with every hole of each axial slice filled, and its 3-D holes."""
    from scipy import ndimage

    out = ndimage.binary_fill_holes(mask)
    for k in range(mask.shape[2]):
        out[:, :, k] |= ndimage.binary_fill_holes(mask[:, :, k])
    return out


def body_mask(volume: Volume, skin_hu: float = SKIN_HU) -> np.ndarray:
    """The body (bool, the volume's shape) of a CT in HU: above ``skin_hu``, the largest
    component (see the module docstring)."""
    hu = volume.array
    lab, n = _components(hu > skin_hu)
    if n == 0:
        raise MeshError(f"no body found in {volume.name} at the skin threshold {skin_hu:g} HU "
                        f"(values span {hu.min():g} to {hu.max():g}); is it a CT in HU?")
    size = np.bincount(lab.ravel())
    size[0] = 0
    return lab == int(np.argmax(size))


def labels_from_ct(volume: Volume, skin_hu: float = SKIN_HU, bone_hu: float = BONE_HU):
    """(body, bone) boolean masks of a CT in HU, by thresholds (see the module docstring)."""
    from scipy import ndimage

    hu = volume.array
    body = body_mask(volume, skin_hu)
    bone = (hu > bone_hu) & body
    if not bone.any():
        raise MeshError(f"no bone found in {volume.name} above {bone_hu:g} HU")
    bone = ndimage.binary_closing(bone, structure=ndimage.generate_binary_structure(3, 1),
                                  border_value=0) & body | bone
    return body, bone


def labels_from_map(volume: Volume, mapping: dict | None = None):
    """(body, bone) masks of a label map (values per `LABELMAP_DEFAULT` or ``mapping``)."""
    mapping = {**LABELMAP_DEFAULT, **(mapping or {})}
    values = np.unique(volume.array)
    bone = np.isin(volume.array, np.atleast_1d(mapping["bone"]))
    soft = [v for k in ("tissue", "fat", "muscle") for v in np.atleast_1d(mapping.get(k, []))]
    tissue = np.isin(volume.array, soft)
    if not tissue.any():
        raise MeshError(f"label map {volume.name} has no tissue label {soft} "
                        f"(values: {values[:10].tolist()})")
    if not bone.any():
        raise MeshError(f"label map {volume.name} has no bone label {mapping['bone']}")
    return tissue | bone, bone


def envelope_depth(labels: Volume) -> Volume:
    """Depth (mm, float32, on voxels about `ENVELOPE_VOXEL_MM` apart) under the face's
    envelope: the body of ``labels`` (a `label_volume` on its grid; every label but
    `OUTSIDE` and the crop) closed by `ENVELOPE_CLOSE_MM` and its holes filled; 0 outside
    it. The air around the head in the nasal cavity, behind the nostrils, or in an ear canal
    lies deep under it; the air at the face's skin does not."""
    from scipy import ndimage

    body = Volume(np.isin(labels.array, (AIRWAY, TISSUE, BONE)).astype(np.float32),
                  labels.spacing, labels.origin).coarsened(ENVELOPE_VOXEL_MM)
    spacing = body.spacing
    pad = int(np.ceil(ENVELOPE_CLOSE_MM / np.min(spacing))) + 1
    inside = np.pad(body.array >= 0.5, pad)   # a block that is mostly body
    dilated = ndimage.distance_transform_edt(~inside, sampling=spacing) <= ENVELOPE_CLOSE_MM
    closed = ndimage.distance_transform_edt(dilated, sampling=spacing) > ENVELOPE_CLOSE_MM
    closed = ndimage.binary_fill_holes(closed | inside)
    depth = ndimage.distance_transform_edt(closed, sampling=spacing).astype(np.float32)
    return Volume(depth[pad:-pad, pad:-pad, pad:-pad], spacing, body.origin, labels.name)


def label_volume(volume: Volume, body, bone, free_faces=()) -> np.ndarray:
    """The labelled volume (uint8, the shape of ``volume`` plus one voxel of crop on every
    side) from body and bone masks. Raises `MeshError` when no tissue is left or bone lies
    outside the skin."""
    from scipy import ndimage

    voxel = float(np.prod(volume.spacing))
    face6 = ndimage.generate_binary_structure(3, 1)
    bone = _drop_small(bone, int(np.ceil(MIN_BONE_MM3 / voxel)))
    filled = fill_axial(body)
    outside = ~filled
    inner_air = filled & ~body
    airway = _drop_small(inner_air, int(np.ceil(MIN_AIR_MM3 / voxel)))
    soft = body & ~bone | inner_air & ~airway   # small pockets are tissue
    # the skull is hollow: tissue that touches no outside air is not simulated
    near_out = ndimage.binary_dilation(outside, face6)
    lab, _ = _components(soft)
    touching = np.unique(lab[near_out & soft])
    keep = np.isin(lab, touching[touching > 0])
    if not keep.any():
        raise MeshError(f"no soft tissue under the skin is left in {volume.name}: the crop "
                        "leaves no tissue, or the thresholds find none")
    exposed = near_out & bone
    shell = bone & ~ndimage.binary_erosion(bone, face6)
    if exposed.sum() > BONE_EXPOSED_MAX * max(shell.sum(), 1):
        raise MeshError(f"bone lies outside the skin in {volume.name}: {exposed.sum()} of "
                        f"{shell.sum()} bone surface voxels touch the air around the head; "
                        "check the thresholds or the label map")
    labels = np.full(volume.array.shape, OUTSIDE, dtype=np.uint8)
    labels[airway] = AIRWAY
    labels[bone | soft & ~keep] = BONE
    labels[keep] = TISSUE
    padded = np.full(np.array(labels.shape) + 2, CROP, dtype=np.uint8)
    padded[1:-1, 1:-1, 1:-1] = labels
    for face in free_faces:
        if face not in FACES:
            raise MeshError(f"unknown crop face {face!r}; faces: {list(FACES)}")
        axis, side = "xyz".index(face[1]), (0 if face[0] == "-" else -1)
        idx = [slice(None)] * 3
        idx[axis] = side
        padded[tuple(idx)] = CROP_FREE
    return padded
