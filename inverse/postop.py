"""A post-operative CT in the validation against the outcome (`scripts/validate.py`,
docs/validation.md).

1. **Registered** to the pre-operative CT the scene was made from, on the bone that surgery
   does not move (`register_ct`): the scene's fixed bone facets on the same rule as the face
   scan's skin (`inverse.validation.stable_mask`: `STABLE_ABOVE_MM` above the moving bone,
   off the nose), as a shell of voxels along them (`shell_mask`). A rigid registration of the
   pre-operative CT (fixed, masked by that shell) to the post-operative one with SimpleITK:
   mean squares on HU, three resolutions (`register_volumes`). Its residual
   (`bone_residual`) is a distance: the scene's bone surface moved by the registration,
   against the post-operative CT's bone surface at the same HU. A registration whose
   residual exceeds `RESIDUAL_MAX_MM` failed: a one-line error, never a number in a report;
   so is a post-operative CT whose mirror image fits better (`MIRROR_RATIO`). Metal (plates,
   screws) is left out of both images' metrics (`METAL_MARGIN_MM`), and each fit reports its
   `fit_condition`.
2. **How each segment moved** (`measure_bone`): its own bone facets' shell registered the
   same way, from the stable registration: its motion in the scene's frame (4×4, the
   modelling convention of `meshes.transforms`) and its residual.
3. **The skin** (`skin_surface`): the outer surface of the pipeline's body
   (`meshes.segment.labels_from_ct` at the scene's skin threshold, the air inside the head
   filled as the pipeline fills it) at sub-voxel position: marching cubes (scikit-image) on
   the HU at that threshold.

`synthetic_postop` makes a post-operative CT with a known truth (tests, benchmarks): the
FEM displacement in the tissue, each segment's rigid motion in its bone, the rest fixed,
then misplaced and noised.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from meshes.errors import MeshError
from meshes.volume import Volume

#: The shell of voxels a bone surface's registration uses: from this far outside the bone
#: (mm, in the tissue: the edge) to this far inside it, along the scene's bone facets.
SHELL_MM = (-1.5, 4.0)
#: The fixed image is cropped to the shell's box plus this margin (mm); the moving image to
#: that box, mapped by the initial transform, plus `SEARCH_MM`: the post-operative CT lies
#: within this of the pre-operative one (place it roughly in 3D Slicer first otherwise).
MARGIN_MM, SEARCH_MM = 10.0, 30.0
#: SimpleITK's multi-resolution schedule: shrink factors and Gaussian sigmas (mm) per level.
SHRINK, SIGMAS_MM = (4, 2, 1), (2.0, 1.0, 0.0)
#: The metric's random samples per level (fixed seed: the same answer on every run), and
#: the regular-step gradient descent: first step (mm, scaled by physical shift), last step,
#: iterations per level (a last step of 1e-4 in 300 iterations stopped 0.17 degrees off on
#: the voxelised synthetic skull, misplaced by 4 degrees; 0.04 with these, in 5 s).
SAMPLES, SEED = 50_000, 7
STEP_MM, MIN_STEP_MM, ITERATIONS = 2.0, 1e-5, 1000
#: SimpleITK's threads for a registration: a fixed count sums the metric in the same order on
#: every machine and under any rank count (the same transform, bit for bit).
ITK_THREADS = 2
#: Voxels at or below this (HU) lie outside the scanner's field of view, not in air (-1000):
#: CT scanners pad the reconstruction circle with -2048 or -3024 (DICOM Pixel Padding
#: Value). The registration's metric leaves them out: a segment that a field of view cuts
#: (Cranium's teeth) moved out of it by surgery is not air.
FOV_PAD_HU = -2000.0
#: Metal (plates, screws, brackets) and this much around it (mm) are left out of both
#: registrations' metrics: the post-operative CT has plates the pre-operative one has not.
#: Plates and screws of 8000 HU across a hostile post-operative Cranium's LeFort I cut
#: (`tests/hostile_postop.py`) put the halves' measurement 0.26 and 0.53 mm RMS off with
#: them in the metric, 0.10 and 0.07 mm without. A 1 mm titanium plate saturated at 3071 HU
#: and blurred by the scan reads below `meshes.metal.METAL_HU` and stays in (0.10-0.17 mm).
METAL_MARGIN_MM = 2.0
#: A post-operative CT is mirrored when its mirror image's residual on the stable bone is
#: below this share of its own.
MIRROR_RATIO = 0.8
#: A registration fails when the RMS distance (mm) between the bone surfaces after it
#: exceeds this: the CT's voxels are 0.3-1 mm, and a good registration leaves a fraction.
RESIDUAL_MAX_MM = 1.0
#: Points of a bone surface the residual is measured at (the first of every k-th).
RESIDUAL_POINTS = 4000
#: The residual's points lie within this distance (mm) of the scene's bone facets: the
#: bone's surface, not its inner structure (pulp canals, marrow spaces, the far side of a
#: thin wall) that a rescan's partial volume fills or opens. A post-operative Cranium at
#: coarse, registered at the true motion: maxilla_R 0.46 mm RMS over the whole shell, of it
#: 0.27 within 1.5 mm (0.24 within 1, 0.28 within 2); the outliers, 3 mm off, are a molar's
#: inner surfaces 1.5-3.3 mm under the facets (docs/decisions.md).
RESIDUAL_NEAR_MM = 1.5
#: Fixed-point iterations that invert the forward displacement in `synthetic_postop`, the
#: grid (mm) it is computed on before it is interpolated onto the voxels, and how far (mm)
#: beyond the mesh it reaches.
INVERSE_ITERATIONS, WARP_GRID_MM, WARP_MARGIN_MM = 8, 2.0, 15.0


@dataclasses.dataclass
class BoneSurface:
    """A part of the scene's bone surface at rest, scene frame: ``points`` (K, 3) mm,
    ``tris`` (T, 3), oriented out of the tissue (into the bone)."""

    points: np.ndarray
    tris: np.ndarray

    def subset(self, keep: np.ndarray) -> "BoneSurface":
        """The triangles whose three vertices are kept (``keep`` (K,) bool)."""
        return BoneSurface(self.points, self.tris[keep[self.tris].all(axis=1)])


def bone_surfaces(scene) -> dict:
    """{"fixed": ..., segment name: ...} `BoneSurface` of ``scene`` (`inverse.scene.Scene`):
    the fixed bone's facets, and each segment's bone and teeth. Collective."""
    from meshes.anatomy import FIXED, segment_tags

    dom = scene.domain
    zero = np.zeros_like(scene.eq.u_eq.array)
    parts = {"fixed": [FIXED], **{n: list(segment_tags(t)) for n, t in dom.segments.items()}}
    out = {}
    for name, tags in parts.items():
        verts = dom.boundary_vertices(tags)
        out[name] = BoneSurface(dom.vertex_operator(verts).apply(zero),
                                dom.boundary_triangles(verts, tags))
    return out


def shell_mask(volume: Volume, bone: BoneSurface) -> np.ndarray:
    """Voxels (the volume's shape, bool) within `SHELL_MM` of the bone surface along its
    normals: the surface subdivided to the voxel size, stepped along its vertex normals."""
    from meshes.surface import subdivide, vertex_normals

    points, tris = bone.points, bone.tris
    if len(tris) == 0:
        raise MeshError("no bone surface to register on")
    h = float(volume.spacing.min())
    while np.linalg.norm(points[tris] - points[np.roll(tris, 1, axis=1)], axis=2).max() > h:
        points, tris = subdivide(points, tris)
    n = vertex_normals(points, tris)
    mask = np.zeros(volume.array.shape, dtype=bool)
    shape = np.array(volume.array.shape)
    for s in np.arange(SHELL_MM[0], SHELL_MM[1] + 1e-9, h / 2):
        ijk = np.rint((points + s * n - volume.origin) / volume.spacing).astype(int)
        ijk = ijk[((ijk >= 0) & (ijk < shape)).all(axis=1)]
        mask[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return mask


def _image(array: np.ndarray, spacing, origin):
    """A SimpleITK image of an (nx, ny, nz) array on an axis-aligned grid (our frame)."""
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.ascontiguousarray(array.transpose(2, 1, 0)))
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(o) for o in origin])
    return image


def _box(volume: Volume, lo, hi) -> tuple:
    """Index slices (3) of the voxels whose centres lie in [lo, hi] mm (clamped)."""
    a = np.floor((np.asarray(lo) - volume.origin) / volume.spacing).astype(int)
    b = np.ceil((np.asarray(hi) - volume.origin) / volume.spacing).astype(int) + 1
    shape = np.array(volume.array.shape)
    a, b = np.clip(a, 0, shape), np.clip(b, 0, shape)
    if np.any(b <= a):
        raise MeshError(f"the post-operative CT {volume.name} does not reach the bone to "
                        "register on: is it the same patient's head?")
    return tuple(slice(i, j) for i, j in zip(a, b))


def in_view(volume: Volume) -> np.ndarray:
    """Voxels (bool, the volume's shape) inside the scanner's field of view (`FOV_PAD_HU`),
    one voxel in from its edge: a point there interpolates no padding."""
    from scipy import ndimage

    return ndimage.binary_erosion(volume.array > FOV_PAD_HU, border_value=1)


def _near_metal(volume: Volume, box) -> np.ndarray:
    """Voxels of ``volume[box]`` (bool) within `METAL_MARGIN_MM` of metal
    (`meshes.metal.METAL_HU`): plates, screws, brackets and their blur, which one scan has
    and the other has not."""
    from scipy import ndimage

    from meshes.metal import METAL_HU

    metal = volume.array[box] >= METAL_HU
    if not metal.any():
        return metal
    r = np.ceil(METAL_MARGIN_MM / volume.spacing).astype(int)
    return ndimage.maximum_filter(metal, size=tuple(2 * r + 1))   # a box, axis by axis


def register_volumes(fixed: Volume, moving: Volume, mask: np.ndarray,
                     initial: np.ndarray | None = None) -> np.ndarray:
    """The rigid 4×4 T (mm, our frame) with ``moving`` at T x like ``fixed`` at x, over the
    ``mask`` (fixed's shape, bool) voxels: SimpleITK, mean squares, `SHRINK` resolutions,
    regular-step gradient descent (module constants), from ``initial`` (default identity)."""
    import SimpleITK as sitk
    from scipy import ndimage

    T0 = np.eye(4) if initial is None else np.asarray(initial, float)
    ijk = np.argwhere(mask)
    if len(ijk) == 0:
        raise MeshError("no voxel to register on")
    x = fixed.origin + ijk * fixed.spacing
    lo, hi = x.min(axis=0) - MARGIN_MM, x.max(axis=0) + MARGIN_MM
    box = _box(fixed, lo, hi)
    origin = fixed.origin + fixed.spacing * np.array([s.start for s in box])
    f = _image(fixed.array[box].astype(np.float32), fixed.spacing, origin)
    usable = mask[box] & (fixed.array[box] > FOV_PAD_HU) & ~_near_metal(fixed, box)
    m_img = _image(usable.astype(np.uint8), fixed.spacing, origin)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])]) @ T0[:3, :3].T + T0[:3, 3]
    mbox = _box(moving, corners.min(axis=0) - SEARCH_MM, corners.max(axis=0) + SEARCH_MM)
    m_origin = moving.origin + moving.spacing * np.array([s.start for s in mbox])
    values = moving.array[mbox].astype(np.float32)
    pad = values <= FOV_PAD_HU
    if pad.any():   # the nearest value seen: no edge at the view's rim when smoothed
        near = ndimage.distance_transform_edt(pad, return_distances=False, return_indices=True)
        values = values[tuple(near)]
    m = _image(values, moving.spacing, m_origin)
    m_fov = _image((in_view(moving)[mbox] & ~_near_metal(moving, mbox)).astype(np.uint8),
                   moving.spacing, m_origin)
    c = x.mean(axis=0)
    tx = sitk.Euler3DTransform()
    tx.SetCenter(c.tolist())
    tx.SetMatrix(T0[:3, :3].ravel().tolist())
    tx.SetTranslation((T0[:3, :3] @ c + T0[:3, 3] - c).tolist())
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(ITK_THREADS)   # the metric's too
    reg = sitk.ImageRegistrationMethod()
    reg.SetNumberOfThreads(ITK_THREADS)
    reg.SetMetricAsMeanSquares()
    reg.SetMetricFixedMask(m_img)
    reg.SetMetricMovingMask(m_fov)
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(min(1.0, SAMPLES / len(ijk)), SEED)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(STEP_MM, MIN_STEP_MM, ITERATIONS)
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(SHRINK))
    reg.SetSmoothingSigmasPerLevel(list(SIGMAS_MM))
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    reg.SetInitialTransform(tx, inPlace=True)
    reg.Execute(f, m)
    T = np.eye(4)
    T[:3, :3] = np.array(tx.GetMatrix()).reshape(3, 3)
    T[:3, 3] = np.array(tx.GetTranslation()) + c - T[:3, :3] @ c
    return T


def _sample(volume: Volume, x: np.ndarray, fill: float | None = None) -> np.ndarray:
    """Values (K,) at points x (K, 3) mm, trilinear; ``fill`` beyond the grid (default: the
    volume's minimum, air)."""
    from scipy import ndimage

    fill = float(volume.array.min()) if fill is None else fill
    ijk = ((np.asarray(x, float) - volume.origin) / volume.spacing).T
    return ndimage.map_coordinates(volume.array.astype(np.float32), ijk, order=1, cval=fill)


def _iso_surface(volume: Volume, level: float, lo, hi) -> tuple:
    """(points (K, 3) mm, triangles) of the volume's iso-surface at ``level`` in the box
    [lo, hi] mm (marching cubes); empty where the box does not cross the level."""
    from skimage.measure import marching_cubes

    box = _box(volume, lo, hi)
    values = volume.array[box].astype(np.float32)
    if not values.min() < level < values.max():
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=int)
    verts, faces, _, _ = marching_cubes(values, level, spacing=tuple(volume.spacing))
    return verts + volume.origin + volume.spacing * np.array([s.start for s in box]), faces


def bone_residual(pre: Volume, post: Volume, bone: BoneSurface, mask: np.ndarray,
                  T: np.ndarray) -> float:
    """RMS distance (mm) from the pre-operative CT's bone iso-surface in the bone's shell
    ``mask`` (`shell_mask`; at most `RESIDUAL_POINTS` points, those within `RESIDUAL_NEAR_MM`
    of the bone's facets), moved by T (4×4, pre -> post), to the post-operative CT's at the
    same HU: the median HU at the bone surface's vertices. How well the two bone surfaces
    meet after a registration; inf where they do not cross."""
    from scipy import ndimage

    from meshes.surface import apply, closest_points

    level = float(np.median(_sample(pre, bone.points[np.unique(bone.tris)])))
    ijk = np.argwhere(mask)
    x0 = pre.origin + ijk * pre.spacing
    x, _ = _iso_surface(pre, level, x0.min(axis=0), x0.max(axis=0))
    x = x[dataclasses.replace(pre, array=mask).at(x)]
    x = x[::max(1, len(x) // RESIDUAL_POINTS)]
    x = x[closest_points(x, bone.points, bone.tris)[0] <= RESIDUAL_NEAR_MM]
    moved = apply(T, x)
    seen = ndimage.binary_erosion(in_view(post), iterations=2, border_value=1)
    moved = moved[dataclasses.replace(post, array=seen).at(moved)]   # off its view: unknown
    if len(moved) == 0:
        return float("inf")
    points, tris = _iso_surface(post, level, moved.min(axis=0) - 3.0, moved.max(axis=0) + 3.0)
    if len(tris) == 0:
        return float("inf")
    d = closest_points(moved, points, tris)[0]
    return float(np.sqrt(np.mean(d ** 2)))


def skin_surface(volume: Volume, skin_hu: float, lo, hi) -> tuple:
    """(points (K, 3) mm, triangles (T, 3) facing out) of the skin of a CT inside the box
    [lo, hi] mm, open at its faces: the outer surface of the pipeline's body
    (`meshes.segment.body_mask`, the air inside the head filled as `meshes.segment.fill_axial`
    fills it) at ``skin_hu``, by marching cubes on the HU."""
    from meshes.segment import body_mask, fill_axial

    body = body_mask(volume, skin_hu)
    filled = fill_axial(body)
    f = volume.array.astype(np.float32)
    f[filled & ~body] = skin_hu + 1000.0   # the air inside the head: inside the skin
    f[~filled & (volume.array > skin_hu)] = skin_hu - 1000.0   # the table, the headrest
    points, tris = _iso_surface(dataclasses.replace(volume, array=f), skin_hu, lo, hi)
    return points, tris[:, ::-1]   # scikit-image's face inward


def register_ct(pre: Volume, post: Volume, bones: dict, frame, landmarks: dict):
    """The post-operative CT registered to the pre-operative one on the stable bone (module
    docstring): `inverse.validation.Registration` (``transform``: post -> scene frame,
    4×4; ``overlap``: the share of that bone inside the post-operative CT; ``n_points``: its
    shell's voxels). `MeshError` with one line where it fails."""
    from inverse.validation import OVERLAP_MIN, STABLE_ABOVE_MM, Registration, stable_mask
    from meshes.surface import apply

    fixed = bones["fixed"]
    moving = np.concatenate([b.points for k, b in bones.items() if k != "fixed"])
    stable = fixed.subset(stable_mask(fixed.points, moving, frame, landmarks))
    if len(stable.tris) == 0:
        raise MeshError(f"no fixed bone of the scene lies {STABLE_ABOVE_MM:g} mm above the "
                        "moving bone to register the post-operative CT on")
    mask = shell_mask(pre, stable)
    T = register_volumes(pre, post, mask)
    x = apply(T, stable.points[np.unique(stable.tris)])
    last = post.origin + post.spacing * (np.array(post.array.shape) - 1)
    overlap = float(((x >= post.origin) & (x <= last)).all(axis=1).mean())
    if overlap < OVERLAP_MIN:
        raise MeshError(f"the post-operative CT holds {overlap:.0%} of the bone surgery does "
                        f"not move (at least {OVERLAP_MIN:.0%} needed): another field of view, "
                        "or another patient")
    residual = bone_residual(pre, post, stable, mask, T)
    _not_mirrored(pre, post, stable, mask, residual, frame)
    residual = _checked(residual, "the bone surgery does not move")
    return Registration(np.linalg.inv(T), residual, overlap, int(mask.sum()),
                        fit_condition(stable))


def mirrored(volume: Volume, x_plane: float) -> Volume:
    """The volume mirrored left-right about the plane x = ``x_plane`` (mm)."""
    n = volume.array.shape[0]
    origin = volume.origin.copy()
    origin[0] = 2 * x_plane - volume.origin[0] - (n - 1) * volume.spacing[0]
    return dataclasses.replace(volume, array=volume.array[::-1], origin=origin,
                               name=f"{volume.name} mirrored")


def _not_mirrored(pre, post, stable, mask, residual: float, frame) -> None:
    """`MeshError` when the post-operative CT mirrored left-right (about the scanner's
    sagittal plane through the head frame's origin) fits the stable bone better than itself
    by `MIRROR_RATIO`: a flipped scan (a wrong orientation in its header), which a rigid
    registration cannot undo and a nearly symmetric skull fits within `RESIDUAL_MAX_MM`. A
    mirror image that does not register (a head yawed far in the scanner) says nothing."""
    flipped = mirrored(post, float(frame.origin[0]))
    try:
        T = register_volumes(pre, flipped, mask)
        other = bone_residual(pre, flipped, stable, mask, T)
    except MeshError:
        return
    if other <= RESIDUAL_MAX_MM and other < MIRROR_RATIO * residual:
        raise MeshError(f"the post-operative CT {post.name} is mirrored left-right: its mirror "
                        f"image fits the bone surgery does not move better ({other:.2f} against "
                        f"{residual:.2f} mm RMS); check its orientation (the header's "
                        "direction cosines)")


def fit_condition(bone: BoneSurface) -> float:
    """How well a bone surface determines a rigid fit to it: the condition number (the
    square root of the largest over the smallest eigenvalue) of the 6x6 normal matrix of a
    point-to-surface fit, sum over its triangles of area J^T J with J = [n, (x - c) x n / r]
    (n the normal, c the centroid, r the RMS radius: rotations measured as displacements).
    1 for a sphere's, infinite for a plane's or a cylinder's, whose fit slides."""
    x = bone.points[bone.tris]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area = np.linalg.norm(n, axis=1)
    keep = area > 0
    n, area, mid = n[keep] / area[keep, None], area[keep], x[keep].mean(axis=1)
    c = np.average(mid, axis=0, weights=area)
    r = np.sqrt(np.average(((mid - c) ** 2).sum(axis=1), weights=area))
    J = np.hstack([n, np.cross(mid - c, n) / r])
    w = np.linalg.eigvalsh((J * area[:, None]).T @ J)
    return float(np.sqrt(w[-1] / w[0])) if w[0] > 0 else float("inf")


def _checked(residual: float, what: str) -> float:
    if not residual <= RESIDUAL_MAX_MM:
        raise MeshError(f"the post-operative CT does not fit {what}: residual {residual:.2f} "
                        f"mm RMS (at most {RESIDUAL_MAX_MM:g}): another patient, or a "
                        "registration that failed")
    return residual


def measure_bone(pre: Volume, post: Volume, bones: dict, registration) -> dict:
    """{segment: (motion 4×4 in the scene's frame, residual mm, `fit_condition`)}: each
    segment's bone shell registered from the stable registration (module docstring).
    `MeshError` where one fails."""
    T_stable = np.linalg.inv(registration.transform)   # scene -> post
    out = {}
    for name, bone in bones.items():
        if name == "fixed":
            continue
        mask = shell_mask(pre, bone)
        T = register_volumes(pre, post, mask, T_stable)
        residual = _checked(bone_residual(pre, post, bone, mask, T), f"the {name}'s bone")
        out[name] = (registration.transform @ T, residual, fit_condition(bone))
    return out


def _beyond_skin(G: np.ndarray, points: np.ndarray, u: np.ndarray, skin: np.ndarray,
                 reach: float) -> tuple:
    """(nodes (K,), displacements (K, 3) mm): the points of G (N, 3) outside the skin
    (triangles ``skin`` (T, 3) into ``points`` (P, 3), facing out) within ``reach`` mm of
    it, not beside its rim, and the displacement u (P, 3) at each one's closest point on
    the skin."""
    from scipy.spatial import cKDTree

    from meshes.surface import SurfaceQuery, barycentric, normals_at

    dist, _ = cKDTree(points[np.unique(skin)]).query(G, distance_upper_bound=reach)
    near = np.flatnonzero(np.isfinite(dist))
    surface = SurfaceQuery(points, skin)
    _, q, tri = surface.closest(G[near])
    out = ((np.einsum("ij,ij->i", G[near] - q, normals_at(points, skin, tri, q)) > 0)
           & ~surface.on_rim(q))   # beyond its open rim: inside, or past the view
    w = barycentric(points, skin, tri[out], q[out])
    return near[out], np.einsum("kv,kvi->ki", w, u[skin[tri[out]]])


def synthetic_postop(pre: Volume, cuts, points: np.ndarray, u: np.ndarray, motions: dict,
                     misplace: np.ndarray, noise_hu: float, seed: int = 0,
                     skin_hu: float | None = None, bone_hu: float | None = None,
                     skin: np.ndarray | None = None) -> Volume:
    """A post-operative CT made from ``pre`` with a known truth: the tissue displaced by u
    (N, 3) mm given at the mesh's vertices ``points`` (N, 3) (linear between them; outside
    the ``skin`` (triangles (T, 3) into ``points``, facing out), where given, its closest
    point's; the nearest vertex's beyond, none `WARP_MARGIN_MM` beyond them); the bone and
    the air it encloses (the sinuses, the nasal cavity: `meshes.segment.labels_from_ct` at
    the thresholds, default the pipeline's) fixed, or moved by its segment's motion
    {segment: 4×4} where the osteotomies ``cuts`` (`meshes.osteotomy`) put it in one; then
    misplaced by ``misplace`` (4×4: scene -> post-operative CT) on the grid that holds it,
    in one trilinear resampling (`FOV_PAD_HU` beyond the pre-operative view), and noised
    (Gaussian, SD ``noise_hu``)."""
    import dataclasses as dc

    from scipy import ndimage
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import cKDTree

    from meshes.anatomy import FIXED
    from meshes.segment import BONE_HU, SKIN_HU, fill_axial, labels_from_ct

    lo, hi = points.min(axis=0) - WARP_MARGIN_MM, points.max(axis=0) + WARP_MARGIN_MM
    # the forward displacement on a coarse grid, its inverse by fixed-point iteration
    axes = [np.arange(lo[a], hi[a] + WARP_GRID_MM, WARP_GRID_MM) for a in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    U = LinearNDInterpolator(points, u)(G)
    far = np.isnan(U[:, 0])
    U[far] = u[cKDTree(points).query(G[far])[1]]
    if skin is not None:   # beyond the skin: its closest point's, not a blend across the air
        beyond, U[beyond] = _beyond_skin(G, points, u, skin, WARP_MARGIN_MM)
    U = U.reshape(*(len(a) for a in axes), 3)

    def on_grid(field, x):   # a (g, g, g, 3) field at points x (K, 3), trilinear
        ijk = ((x - lo) / WARP_GRID_MM).T
        return np.stack([ndimage.map_coordinates(field[..., k], ijk, order=1, mode="nearest")
                         for k in range(3)], axis=1)

    x = G.copy()
    for _ in range(INVERSE_ITERATIONS):
        x = G - on_grid(U, x)
    B = (x - G).reshape(U.shape)   # post position -> pre position, minus the post position
    # the post-operative grid: the pre-operative one's, misplaced
    s, n = pre.spacing, np.array(pre.array.shape)
    corners = pre.origin + np.array([[i, j, k] for i in (0, 1) for j in (0, 1)
                                     for k in (0, 1)]) * (n - 1) * s
    moved = corners @ misplace[:3, :3].T + misplace[:3, 3]
    origin = moved.min(axis=0)
    shape = np.ceil((moved.max(axis=0) - origin) / s).astype(int) + 1
    idx = np.stack(np.meshgrid(*(np.arange(k) for k in shape), indexing="ij"), axis=-1)
    inv = np.linalg.inv(misplace)
    z = (origin + idx.reshape(-1, 3) * s) @ inv[:3, :3].T + inv[:3, 3]   # the scene's frame
    src = z.copy()
    inside = ((z >= lo) & (z <= hi)).all(axis=1)
    src[inside] += on_grid(B, z[inside])
    # the bone and the air inside it: fixed where it is, each segment by its motion
    body, bone = labels_from_ct(pre, SKIN_HU if skin_hu is None else skin_hu,
                                BONE_HU if bone_hu is None else bone_hu)
    rigid = bone | fill_axial(body) & ~body
    tags = np.zeros(pre.array.shape, dtype=np.int32)
    flat = dc.replace(cuts, band_mm=0.0, split_mm=0.0)
    tags[rigid] = flat.classify(pre.origin + np.argwhere(rigid) * s)

    def at(volume, x):   # the nearest voxel's value; 0 beyond the grid
        k = np.rint((x - pre.origin) / s).astype(int)
        ok = ((k >= 0) & (k < n)).all(axis=1)
        out = np.zeros(len(x), dtype=volume.dtype)
        out[ok] = volume[k[ok, 0], k[ok, 1], k[ok, 2]]
        return out

    fixed = at(tags, z) == FIXED
    src[fixed] = z[fixed]
    for name, tag in cuts.segments().items():
        if name in motions:
            T_inv = np.linalg.inv(motions[name])
            mine = z @ T_inv[:3, :3].T + T_inv[:3, 3]
            hit = at(ndimage.binary_dilation(tags == tag), mine)   # with its edge
            src[hit] = mine[hit]
    values = _sample(pre, src, fill=-3024.0)   # beyond the pre-operative view: padding
    noisy = values + np.random.default_rng(seed).normal(0.0, noise_hu, len(values))
    return Volume(np.rint(noisy).astype(np.int16).reshape(tuple(shape)), s.copy(), origin,
                  f"{pre.name}, operated")


def simulated_postop(scene, p: np.ndarray, pre: Volume, cuts, misplace: np.ndarray,
                     noise_hu: float, seed: int = 0) -> Volume:
    """`synthetic_postop` of a CT scene (`inverse.scene.Scene` made by ``ct_scene.py`` from
    ``pre`` with the osteotomies ``cuts``, `meshes.osteotomy.Osteotomies`): its outcome at p
    (P,), which the scene is left at. Collective; every rank gets the volume."""
    from meshes.plane import Plane

    dom = scene.domain
    every = dom.vertex_operator(np.arange(dom.n_vertices))
    X = every.apply(np.zeros_like(scene.eq.u_eq.array))
    scene.solve(p)
    u = every.apply(scene.eq.u_eq.array) - X
    frame = scene.head_frame
    cuts = cuts.with_midsagittal(Plane(tuple(frame.origin), tuple(frame.rotation[:, 0])))
    hu = dom.thresholds or {}
    verts = dom.boundary_vertices()
    return synthetic_postop(pre, cuts, X, u, scene.transforms(p), misplace, noise_hu, seed,
                            hu.get("skin_hu"), hu.get("bone_hu"),
                            verts[dom.boundary_triangles(verts)])
