"""Post-operative CTs as they look after surgery, made from a pre-operative CT by voxels
alone (issue 47): no scene, no FEM, nothing of `inverse.postop`'s construction.

Each segment's bone (the voxels above `BONE_HU` on its side of the scene file's cut
planes, one voxel grown) is moved rigidly at the voxel level; its old place reads as
fluid; the soft tissue stays where it was, or swells; the sinuses fill with fluid; plates
and screws sit across the cuts; the scan is then misplaced and noised."""

from __future__ import annotations

import dataclasses

import numpy as np

#: Bone for this construction (HU): below any bone threshold the tool uses.
BONE_HU = 150.0
#: What blood, fluid and swollen tissue read (HU).
FLUID_HU = 35.0
#: Plates and screws (HU): titanium on an extended-scale CT, or steel.
PLATE_HU = 8000.0
#: Beyond the post-operative scan's field of view (a scanner's padding).
PAD_HU = -3024.0


def _centres(v):
    return np.stack(np.meshgrid(*(v.centres(a) for a in range(3)), indexing="ij"), axis=-1)


def _side(x, plane) -> np.ndarray:
    return (x - np.asarray(plane["point"], float)) @ np.asarray(plane["normal"], float)


def segment_regions(v, spec: dict) -> dict:
    """{segment: bool mask (the volume's shape)} of the space each segment takes, from the
    scene file's planes (their normals up, left, anterior): the maxilla below the LeFort I
    cut (and in front of the pterygomaxillary one, or above the occlusal one), split at the
    mid-sagittal plane; the mandible below the occlusal plane, in front of the rami."""
    x = _centres(v)
    below = _side(x, spec["lefort1"]) < 0
    if "pterygomaxillary" in spec:
        below &= _side(x, spec["pterygomaxillary"]) > 0
    out = {}
    if "occlusal" in spec:
        lower = _side(x, spec["occlusal"]) < 0
        for k in ("ramus_L", "ramus_R"):
            lower &= _side(x, spec[k]) > 0
        out["mandible"] = lower
        below &= _side(x, spec["occlusal"]) >= 0
    left = _side(x, spec["midsagittal"]) > 0
    out["maxilla_L"], out["maxilla_R"] = below & left, below & ~left
    return out


def motion(rotvec_deg, t, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 of x -> R (x - centre) + centre + t, R of the rotation vector ``rotvec_deg``
    (degrees): a segment's motion, or a scan's misplacement (about the origin)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    centre = np.asarray(centre, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, float) + centre - R @ centre
    return T


#: The hostile post-operative CTs: what fills and surrounds the moved bone.
VARIANTS = {"fluid in the sinuses": dict(fluid=True, plates=False),
            "soft tissue swollen 3 mm": dict(fluid=False, plates=False, swell_mm=3.0),
            "plates and screws": dict(fluid=False, plates=True),
            "all three": dict(fluid=True, plates=True, swell_mm=3.0)}


def truth(spec: dict) -> tuple:
    """({segment: 4x4} the true motions, 4x4 the scan's misplacement) about the LeFort I
    cut's point: the halves advanced 3.5-4 mm, impacted 1.5-2 mm and pitched 1.5-2 degrees
    (one a little turned), the mandible (where the scene file has one) advanced 4 mm and
    turned 1 degree."""
    c = np.asarray(spec["lefort1"]["point"], float)
    out = {"maxilla_L": motion([-2.0, 0, 0], [0, 4.0, 2.0], c),
           "maxilla_R": motion([-1.5, 0.5, 0], [0.2, 3.5, 1.5], c)}
    if "occlusal" in spec:
        out["mandible"] = motion([0, 0, 1.0], [0, 4.0, 2.0], c)
    return out, motion([1.5, -1.0, 2.0], [3.0, -2.0, 2.5], c)


def rms_mm(T: np.ndarray, want: np.ndarray, points: np.ndarray) -> float:
    """RMS distance (mm) between points (K, 3) moved by T and by ``want`` (4x4 each)."""
    d = points @ (T - want)[:3, :3].T + (T - want)[:3, 3]
    return float(np.sqrt((d ** 2).sum(axis=1).mean()))


def hostile_postop(pre, spec: dict, truth: dict, misplace: np.ndarray, *, fluid=True,
                   swell_mm=0.0, plates=True, noise_hu=15.0, seed=0):
    """The post-operative CT (`meshes.volume.Volume`, HU) of ``pre`` with each segment of
    ``truth`` ({segment: 4x4 in pre's frame}) moved, its old place fluid, the sinuses filled
    (``fluid``), the soft tissue swollen by ``swell_mm`` below the LeFort I cut, metal
    plates and screws across the cuts (``plates``), then moved by ``misplace`` (4x4) and
    noised (Gaussian, ``noise_hu``)."""
    from scipy import ndimage

    from meshes.volume import Volume

    a = pre.array.astype(np.float32)
    x = _centres(pre)
    bone = a > BONE_HU
    regions = segment_regions(pre, spec)
    post = a.copy()
    ball = ndimage.generate_binary_structure(3, 1)
    if swell_mm:
        around = ndimage.binary_fill_holes(a > -400)
        grown = ndimage.binary_dilation(around, ball, iterations=int(
            round(swell_mm / pre.spacing.min())))
        low = _side(x, spec["lefort1"]) < 20.0
        post[grown & ~around & low] = FLUID_HU
    if fluid:   # the sinuses beside the nasal cavity, up to 25 mm above the cut
        h = _side(x, spec["lefort1"])
        off = np.abs(_side(x, spec["midsagittal"]))
        inside = ndimage.binary_fill_holes(a > -400)
        for k in range(a.shape[2]):
            inside[:, :, k] |= ndimage.binary_fill_holes(a[:, :, k] > -400)
        post[(a < -400) & inside & (h > -5) & (h < 25) & (off > 8) & (off < 40)] = FLUID_HU
    moved = {}
    for name, T in truth.items():
        mask = ndimage.binary_dilation(bone & regions[name], ball)
        post[mask] = FLUID_HU   # the bone's old place
        Ti = np.linalg.inv(T)
        src = (x.reshape(-1, 3) @ Ti[:3, :3].T + Ti[:3, 3] - pre.origin) / pre.spacing
        # mode nearest: a segment that the pre-operative view cuts (Cranium's crowns) goes
        # on beyond it in the post-operative one, as its edge slice
        inside = ndimage.map_coordinates(mask.astype(np.float32), src.T, order=0,
                                         mode="nearest").reshape(a.shape) > 0.5
        moved[name] = inside
    for name, inside in moved.items():
        Ti = np.linalg.inv(truth[name])
        src = (x[inside] @ Ti[:3, :3].T + Ti[:3, 3] - pre.origin) / pre.spacing
        post[inside] = ndimage.map_coordinates(a, src.T, order=1, mode="nearest")
    if plates:
        _plates(post, pre, x, spec, truth)
    out = Volume(post, pre.spacing.copy(), pre.origin.copy(), "hostile post-op")
    out = _misplaced(out, misplace)
    rng = np.random.default_rng(seed)
    out.array = (out.array + rng.normal(0, noise_hu, out.array.shape)).astype(np.float32)
    return out


def _plates(post, pre, x, spec, truth):
    """Two plates per maxilla half across the LeFort I cut on the bone's anterior
    face (2 x 1 x 14 mm, lying on the moved bone below the cut and the fixed bone above), each
    with two screws (1.6 mm across, 6 mm into the bone)."""
    n = np.asarray(spec["lefort1"]["normal"], float)
    mid = np.asarray(spec["midsagittal"]["point"], float)
    bone = post > BONE_HU
    for name, side in (("maxilla_L", 1.0), ("maxilla_R", -1.0)):
        if name not in truth:
            continue
        for dx in (12.0, 22.0):
            px = mid[0] + side * dx
            cut = np.asarray(spec["lefort1"]["point"], float)
            z = cut[2] + ((cut - [px, cut[1], cut[2]]) @ n) / n[2]   # the cut at this x
            col = bone & (np.abs(x[..., 0] - px) < 1.0) & (np.abs(x[..., 2] - z) < 7.0)
            if not col.any():
                continue
            front = x[col][:, 1].max()
            plate = (np.abs(x[..., 0] - px) < 1.0) & (np.abs(x[..., 2] - z) < 7.0) \
                & (x[..., 1] > front) & (x[..., 1] < front + 1.0)
            post[plate] = PLATE_HU
            for dz in (-4.5, 4.5):
                screw = ((x[..., 0] - px) ** 2 + (x[..., 2] - z - dz) ** 2 < 0.8 ** 2) \
                    & (x[..., 1] > front - 6.0) & (x[..., 1] <= front + 1.0)
                post[screw] = PLATE_HU


def _misplaced(v, M):
    """The volume's content moved by M (4x4), resampled linearly on the same grid; where
    nothing was scanned, the scanner's padding."""
    from scipy import ndimage

    Mi = np.linalg.inv(M)
    s, o = v.spacing, v.origin
    matrix = (Mi[:3, :3] * s[None, :]) / s[:, None]
    offset = (Mi[:3, :3] @ o + Mi[:3, 3] - o) / s
    a = ndimage.affine_transform(v.array, matrix, offset, order=1, cval=PAD_HU)
    return dataclasses.replace(v, array=a.astype(np.float32))
