"""The head's own frame: x to the patient's left, y anterior, z superior.

Every clinical construction is defined in it (the profile landmarks, the treatment's axes,
the targets' rules, the soft-to-hard ratios, the pictures' views), so that an answer does not
depend on how the patient lay in the scanner. Files and reports keep their points in the
scene's frame (the CT's, which 3D Slicer shows) and carry the head frame as a 4×4 ``H``
(head frame -> scene frame): ``x_scene = H[:3, :3] x_head + H[:3, 3]``; its columns are the
head's axes and origin in the scene's frame. For the synthetic heads ``H`` is the identity.

**Given** (a scene file's ``"frame"``):

* clinical points ``{"porion_L", "porion_R", "orbitale_L", "nasion"}`` (mm, scene frame), in
  the file or in a 3D Slicer markups file it names. The Frankfort horizontal (FH) is the
  plane through both porions and the left orbitale; the mid-sagittal plane (MSP) is
  perpendicular to it through the nasion and the porions' midpoint, which is the origin
  (the 3-D cephalometric reference frame of Swennen, Schutyser and Hausamen,
  *Three-Dimensional Cephalometry*, Springer 2006, ch. 5, with the FH of the Frankfort
  agreement of 1884: porion and orbitale);
* two planes ``{"midsagittal": {"point", "normal"}, "horizontal": {"point", "normal"}}``
  (the FH's normal made perpendicular to the MSP's; the origin is the MSP's point moved onto
  both planes);
* ``{"matrix": 4×4}`` or a bare 4×4: ``H`` itself.

**Estimated** (no ``"frame"``), on the whole CT before the crop (`estimate`):

* the MSP is the bone's plane of symmetry (`symmetry_plane`: the bone surface registered with
  its mirror image, distances capped, so that an asymmetric jaw does not pull the plane);
* the FH passes through the porions (the tops of the bony ear canals) and the left orbitale
  (the lowest point of the infraorbital rim; the right one where the left is not found),
  found on the CT where it holds them (`frankfort_points`; a synthetic head with canals and
  orbits: within 0.6 degrees of its true frame, tilted up to 10 degrees about each axis;
  Cranium tilted so: within 0.5 degrees of its untilted frame, tilted). Otherwise (no ear
  canals in the field of view, 3.2 mm voxels that lose the thin tympanic bone as headsq's
  do, a label map) the scan's axial plane stands for it (z is the scanner's z made
  perpendicular to the MSP), with a warning: a head pitched in the scanner then keeps its
  pitch; give the clinical points.

The scene file's ``midsagittal`` osteotomy plane is a cut plane only; without one the cut is
the frame's MSP.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from meshes.errors import MeshError

log = logging.getLogger(__name__)

#: The clinical points of a given frame (module docstring).
POINTS = ("porion_L", "porion_R", "orbitale_L", "nasion")
#: Points closer than this (mm), or a triangle of them thinner than this, define no plane.
DEGENERATE_MM = 1.0
#: The MSP and the FH are perpendicular by definition; planes closer than this to parallel
#: (degrees between them) are refused as a mistake rather than silently made perpendicular.
MIN_PLANE_ANGLE_DEG = 45.0
#: The symmetry plane (`symmetry_plane`): at most this many bone surface points (a
#: deterministic stride); mirror distances are capped at SYMMETRY_CAP_MM, so that what is not
#: symmetric (an asymmetric chin, a filling's streak, a crop that cuts one side) pulls no
#: further than that (headsq's 3.2 mm voxels: the plane moved 0.4 degrees between caps of 3
#: and 6 mm, 0.03 between 6 and 10); the plane is searched from the starts (yaw, roll of its
#: normal, degrees from the scanner's x) on every k-th point (about SYMMETRY_START_POINTS),
#: and the best start refined on all, to 1e-4 rad (Cranium: 241 evaluations, where 1e-6 took
#: 450 for a normal 0.006 degrees away).
SYMMETRY_POINTS = 30000
SYMMETRY_CAP_MM = 6.0
SYMMETRY_START_POINTS = 3000
SYMMETRY_STARTS_DEG = ((0.0, 0.0), (-12.0, 0.0), (12.0, 0.0), (0.0, -12.0), (0.0, 12.0))


@dataclasses.dataclass(frozen=True)
class HeadFrame:
    """The head frame (module docstring).

    Attributes:
        matrix: (4, 4) head frame -> scene frame, rigid.
        sources: how each part was obtained: ``{"midsagittal": ..., "horizontal": ...}``,
            each "given", "estimated" or "assumed".
        points: the clinical points it was built from ``{name: (3,)}`` mm, scene frame
            (given, or found on the CT: `frankfort_points`).
    """

    matrix: np.ndarray
    sources: dict = dataclasses.field(default_factory=lambda: {"midsagittal": "given",
                                                               "horizontal": "given"})
    points: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def identity(cls) -> "HeadFrame":
        return cls(np.eye(4))

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3): columns the head's left, anterior and superior axes in the scene's frame."""
        return self.matrix[:3, :3]

    @property
    def origin(self) -> np.ndarray:
        return self.matrix[:3, 3]

    def to_head(self, x) -> np.ndarray:
        """Points (..., 3) mm from the scene's frame to the head's."""
        return (np.asarray(x, float) - self.origin) @ self.rotation

    def to_scene(self, x) -> np.ndarray:
        """Points (..., 3) mm from the head's frame to the scene's."""
        return np.asarray(x, float) @ self.rotation.T + self.origin

    def tilt_deg(self) -> dict:
        """The head's rotation from the scanner's axes as the treatment's angles (degrees):
        ``R = Rz(yaw) Ry(roll) Rx(pitch)``; pitch > 0: the face turned up, roll > 0: the left
        side down, yaw > 0: the face turned to the patient's right."""
        R = self.rotation
        roll = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
        return {"pitch_deg": float(np.degrees(np.arctan2(R[2, 1], R[2, 2]))),
                "roll_deg": float(np.degrees(roll)),
                "yaw_deg": float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))}

    @classmethod
    def from_report(cls, report) -> "HeadFrame | None":
        """The frame of `report`'s keys (a sidecar's or a saved anatomy's); None without
        ``head_frame``. `MeshError` for a 4×4 that is not rigid."""
        if not report or report.get("head_frame") is None:
            return None
        frame = from_matrix(report["head_frame"], "head_frame")
        sources = report.get("head_frame_sources")
        points = report.get("head_frame_points")
        return cls(frame.matrix, dict(sources) if isinstance(sources, dict) else frame.sources,
                   dict(points) if isinstance(points, dict) else {})

    def report(self) -> dict:
        """Report keys: ``head_frame`` (4×4), ``head_tilt_deg``, ``head_frame_sources`` and
        ``head_frame_points``."""
        return {"head_frame": self.matrix.tolist(), "head_tilt_deg": self.tilt_deg(),
                "head_frame_sources": dict(self.sources),
                "head_frame_points": {k: np.asarray(v, float).tolist()
                                      for k, v in self.points.items()}}


def _unit(v, what: str) -> np.ndarray:
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-9:
        raise MeshError(f"{what} is undefined (a zero vector)")
    return np.asarray(v, float) / n


def from_axes(left, up, origin, sources: dict) -> HeadFrame:
    """A frame from the MSP's normal ``left`` (3,) and the FH's normal ``up`` (3,) (scene
    frame; made perpendicular, ``up`` adjusted) and ``origin`` (3,) mm. `MeshError` when the
    two planes are closer than `MIN_PLANE_ANGLE_DEG` to parallel."""
    x, z = _unit(left, "the mid-sagittal plane's normal"), _unit(up, "the horizontal's normal")
    angle = np.degrees(np.arccos(min(abs(float(x @ z)), 1.0)))
    if angle < MIN_PLANE_ANGLE_DEG:
        raise MeshError(f"the mid-sagittal plane is {angle:.1f} degrees from parallel to the "
                        f"Frankfort horizontal; they must be near perpendicular (at least "
                        f"{MIN_PLANE_ANGLE_DEG:g} degrees apart): check the frame's points")
    z = _unit(z - (z @ x) * x, "the horizontal's normal")
    H = np.eye(4)
    H[:3, 0], H[:3, 1], H[:3, 2], H[:3, 3] = x, np.cross(z, x), z, origin
    return HeadFrame(H, dict(sources))


def from_points(points: dict, where: str = "frame") -> HeadFrame:
    """The frame of the clinical points ``{porion_L, porion_R, orbitale_L, nasion}`` (mm,
    scene frame; module docstring). `MeshError` for a missing point, points that coincide or
    are collinear, or a nasion on the FH."""
    missing = [k for k in POINTS if k not in points]
    if missing:
        raise MeshError(f"{where}: the frame's points need {list(POINTS)}; missing {missing}")
    p = {}
    for k in POINTS:
        v = np.asarray(points[k], dtype=float) if _is_numbers(points[k]) else None
        if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
            raise MeshError(f"{where}: {k} must be 3 finite numbers [x, y, z] mm, got "
                            f"{points[k]!r}")
        p[k] = v
    names = list(POINTS)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if np.linalg.norm(p[a] - p[b]) < DEGENERATE_MM:
                raise MeshError(f"{where}: {a} and {b} coincide (closer than {DEGENERATE_MM:g}"
                                " mm); the frame needs four distinct points")
    po_l, po_r, orb = p["porion_L"], p["porion_R"], p["orbitale_L"]
    normal = np.cross(po_r - po_l, orb - po_l)
    base = np.linalg.norm(po_r - po_l)
    if np.linalg.norm(normal) / base < DEGENERATE_MM:   # the height of orbitale over Po-Po
        raise MeshError(f"{where}: porion_L, porion_R and orbitale_L are collinear: they "
                        "define no Frankfort horizontal")
    origin = (po_l + po_r) / 2
    up = _unit(normal, "the Frankfort horizontal's normal")
    height = float(up @ (p["nasion"] - origin))
    if abs(height) < DEGENERATE_MM:
        raise MeshError(f"{where}: the nasion lies on the Frankfort horizontal: the points "
                        "give no up direction")
    up = up * np.sign(height)   # the nasion is above the FH
    fwd = p["nasion"] - origin
    fwd = fwd - (fwd @ up) * up     # the MSP holds up and the origin-to-nasion direction
    if np.linalg.norm(fwd) < DEGENERATE_MM:
        raise MeshError(f"{where}: the nasion lies straight above the porions' midpoint, so "
                        "it gives the mid-sagittal plane no forward direction")
    left = np.cross(fwd, up)
    left *= np.sign(left @ (po_l - po_r))
    if abs(_unit(left, "MSP") @ (po_l - po_r)) < DEGENERATE_MM:
        raise MeshError(f"{where}: porion_L and porion_R lie in the mid-sagittal plane: the "
                        "mid-sagittal plane is parallel to the Frankfort horizontal's "
                        "left-right line")
    frame = from_axes(left, up, origin, {"midsagittal": "given", "horizontal": "given"})
    return dataclasses.replace(frame, points=p)


def _is_numbers(v) -> bool:
    try:
        np.asarray(v, dtype=float)
        return True
    except (TypeError, ValueError):
        return False


def from_matrix(matrix, where: str = "frame") -> HeadFrame:
    """A frame from a 4×4 (head frame -> scene frame); `MeshError` unless it is a rotation and
    a translation."""
    from meshes.errors import InputError
    from meshes.transforms import rigid

    try:
        H = rigid(matrix, f"{where}: the head frame's 4x4")
    except InputError as e:
        raise MeshError(str(e)) from None
    return HeadFrame(H.copy())


def from_spec(spec, scene_file) -> HeadFrame:
    """The frame a scene file's ``"frame"`` value gives: clinical points, a Slicer markups
    file of them (path relative to the scene file), two planes, ``{"matrix": 4×4}`` or a 4×4
    (module docstring)."""
    where = f"{scene_file}: frame"
    if isinstance(spec, str):
        from meshes.markups import read_landmark_file

        return from_points(read_landmark_file(Path(scene_file).parent / spec), where)
    if isinstance(spec, dict) and "matrix" in spec:
        return from_matrix(spec["matrix"], where)
    if isinstance(spec, dict) and {"midsagittal", "horizontal"} & set(spec):
        from meshes.plane import Plane

        if set(spec) != {"midsagittal", "horizontal"}:
            raise MeshError(f"{where}: give both planes 'midsagittal' and 'horizontal', and "
                            "nothing else")
        msp, fh = (Plane.of(f"frame {k}", spec[k]) for k in ("midsagittal", "horizontal"))
        n, u = np.asarray(msp.normal), np.asarray(fh.normal)
        origin = np.asarray(msp.point) - fh.distance(msp.point) * u
        origin = origin - float(msp.distance(origin)) * n
        return from_axes(n if n[0] >= 0 else -n, u if u[2] >= 0 else -u, origin,
                         {"midsagittal": "given", "horizontal": "given"})
    if isinstance(spec, dict):
        unknown = sorted(set(spec) - set(POINTS))
        if unknown:
            raise MeshError(f"{where}: unknown key(s) {unknown}; give the points {list(POINTS)}"
                            ", {\"matrix\": 4x4} or a 3D Slicer markups file")
        return from_points(spec, where)
    if isinstance(spec, list):
        return from_matrix(spec, where)
    raise MeshError(f"{where}: expected the points {list(POINTS)}, {{\"matrix\": 4x4}}, a 4x4 "
                    f"or a markups file name; got {spec!r}")


def _normal(angles) -> np.ndarray:
    """The unit normal (3,) at (yaw, roll) radians from +x: Rz(yaw) Ry(roll) applied to x."""
    a, b = angles
    return np.array([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), -np.sin(b)])


def symmetry_plane(volume, bone: np.ndarray):
    """The bone's plane of symmetry: (normal (3,) towards +x, the bone's centre projected onto
    it (3,) mm, the RMS capped mirror distance mm). The bone mask ``bone`` on ``volume``'s
    grid is registered with its mirror image: the plane minimises the mean square distance
    from each bone surface point's mirror image to the bone surface (a Euclidean distance
    map, interpolated, capped at `SYMMETRY_CAP_MM`), over the normal's two angles and the
    plane's offset (Powell)."""
    from scipy import ndimage, optimize

    shell = bone & ~ndimage.binary_erosion(bone, ndimage.generate_binary_structure(3, 1))
    ijk = np.argwhere(shell)
    if len(ijk) < 100:
        raise MeshError(f"{volume.name}: too little bone ({len(ijk)} surface voxels) to find "
                        "its plane of symmetry; give the frame in the scene file")
    dist = ndimage.distance_transform_edt(~shell, sampling=volume.spacing)
    pts = volume.origin + ijk[::max(1, int(np.ceil(len(ijk) / SYMMETRY_POINTS)))] \
        * volume.spacing
    centre = pts.mean(axis=0)

    def cost(q, x):
        n = _normal(q[:2])
        mirror = x - 2.0 * ((x - centre) @ n - q[2])[:, None] * n
        d = ndimage.map_coordinates(dist, ((mirror - volume.origin) / volume.spacing).T,
                                    order=1, mode="nearest")
        return float(np.mean(np.minimum(d, SYMMETRY_CAP_MM) ** 2))

    few = pts[::max(1, len(pts) // SYMMETRY_START_POINTS)]
    starts = [optimize.minimize(cost, [*np.radians(s), 0.0], args=(few,), method="Powell",
                                options={"xtol": 1e-3, "ftol": 1e-6})
              for s in SYMMETRY_STARTS_DEG]
    best = min(starts, key=lambda r: r.fun)
    res = optimize.minimize(cost, best.x, args=(pts,), method="Powell",
                            options={"xtol": 1e-4, "ftol": 1e-8})   # 0.006 deg
    n = _normal(res.x[:2])
    point = centre + res.x[2] * n   # the bone's centre projected onto the plane
    return (n if n[0] >= 0 else -n), point, float(np.sqrt(res.fun))


#: The frame is found on voxels averaged to at least this (mm, `estimate_on_scan`): Cranium at
#: 0.4 mm (`bench.py ct`, 1 rank): on the 0.8 mm working grid the frame took 15.0 s of 32.9 s
#: and found porion_R 12 mm from the one on Cranium's own voxels; on 1.2 mm, 5.9 s and every
#: point within 1.8 mm (docs/decisions.md). Voxels of 0.6 mm or more are used as they are.
FRAME_VOXEL_MM = 1.2

#: Porion and orbitale on a CT (`frankfort_points`), mm and HU. Air below AIR_HU. The bony ear
#: canal: air open to the outside (connected to the scan's border) with bone within CANAL_WALL_MM
#: above, below, in front and behind, more than CANAL_MIN_OFFSET_MM from the MSP (the nostrils
#: and the mouth are nearer), at least CANAL_MIN_MM3 of it; the porion is the top of its lumen
#: within CANAL_LATERAL_MM of its lateral end (the bony meatus's rim: medially the canal opens
#: into the middle ear, which a CT does not part from it). headsq's 3.2 mm voxels lose the thin
#: tympanic bone: no canal is found there, and the FH is assumed.
AIR_HU = -400.0
CANAL_WALL_MM = 6.0
#: An edge (the canal's roof, the rim's top) is placed halfway between the HU on its two
#: sides, the far side read within this many voxels (`_roof`).
EDGE_VOXELS = 3
CANAL_MIN_OFFSET_MM = 25.0
CANAL_MIN_MM3 = 30.0
CANAL_LATERAL_MM = 4.0
#: The orbits: seen from the front, the bone's most anterior surface sinks by more than
#: ORBIT_DEPTH_MM into each orbital opening below its rim (a grey closing of that surface over
#: a disk ORBIT_CLOSING_MM across, wider than an orbit's ~35 mm opening, is the rim's level),
#: in parts of at least ORBIT_MIN_MM2, ORBIT_OFFSET_MM from the MSP, their centres
#: ORBIT_ABOVE_PORION_MM above the porions in the scan's axial frame (the orbits' centres lie
#: 15-30 mm above the FH, 80 mm in front of the porions: a head pitched 20 degrees moves them
#: 27 mm; the thin frontal bone above them, which the bone threshold also loses, lies 60 mm
#: and more above). The orbitale is the lowest top of the rim under the opening's lowest rows.
ORBIT_DEPTH_MM = 12.0
ORBIT_CLOSING_MM = 40.0
ORBIT_MIN_MM2 = 300.0
ORBIT_OFFSET_MM = (12.0, 55.0)
ORBIT_ABOVE_PORION_MM = (-20.0, 50.0)
#: Found points are refused (the FH assumed) when the porions' heights differ by more than
#: this, or the FH is tilted from the scan's axial plane by more than FH_MAX_TILT_DEG: a patient
#: is not scanned upside down, and such a plane means the search found something else.
PORION_LEVEL_MM = 10.0
FH_MAX_TILT_DEG = 30.0


def _roof(values, inside, k: int, z0: float, dz: float) -> float:
    """The top edge (mm) of the run of ``inside`` (K,) samples around index k of a column of
    ``values`` (K,) at z0 + i dz: where the values, from a sample wholly inside (one below the
    run's last, where the run has two), reach halfway to the value beyond the edge (the far
    side of the largest step within `EDGE_VOXELS`): sub-voxel, unbiased for any pair of HU
    levels."""
    while k + 1 < len(inside) and inside[k + 1]:
        k += 1
    k0 = k - 1 if k > 0 and inside[k - 1] else k
    v = np.asarray(values, float)[k0:k0 + EDGE_VOXELS + 2]
    if len(v) < 2:
        return z0 + dz * k
    far = int(np.argmax(np.abs(v[1:] - v[0]))) + 1
    level = (v[0] + v[far]) / 2
    j = int(np.argmax((v[1:far + 1] - level) * np.sign(v[far] - v[0]) >= 0)) + 1
    return z0 + dz * (k0 + j - 1 + (level - v[j - 1]) / (v[j] - v[j - 1]))


def frankfort_points(volume, frame: HeadFrame, bone_hu: float) -> dict:
    """``{porion_L, porion_R, orbitale_L, orbitale_R}`` (those found; mm, scene frame) on a CT
    in HU, with ``frame``'s MSP (the constants above say how). The CT is resampled on a grid
    along the frame's axes first."""
    from scipy import ndimage

    from meshes.volume import rotate_volume

    o = frame.origin
    h = rotate_volume(volume, frame.rotation.T, o, fill=-1000.0)   # grid axes: the head's
    hu, sp = h.array.astype(np.float32), h.spacing
    x, ys, zs = (h.centres(a) - o[a] for a in range(3))   # the grid in head coordinates
    bone = hu > bone_hu
    lab, _ = ndimage.label(hu < AIR_HU)
    faces = [lab[0], lab[-1], lab[:, 0], lab[:, -1], lab[:, :, 0], lab[:, :, -1]]
    border = np.unique(np.concatenate([f.ravel() for f in faces]))
    canal = np.isin(lab, border[border > 0])
    for axis in (1, 2):
        for sign in (1, -1):
            canal &= _near(bone, axis, sign, int(np.ceil(CANAL_WALL_MM / sp[axis])))
    out = {}
    for name, side in (("L", 1.0), ("R", -1.0)):
        parts, n = ndimage.label(canal & (side * x > CANAL_MIN_OFFSET_MM)[:, None, None])
        if n == 0:
            continue
        sizes = ndimage.sum(parts > 0, parts, np.arange(1, n + 1)) * np.prod(sp)
        if sizes.max() < CANAL_MIN_MM3:
            continue
        ijk = np.argwhere(parts == 1 + int(np.argmax(sizes)))
        d = side * x[ijk[:, 0]]
        rim = ijk[d >= d.max() - CANAL_LATERAL_MM]
        _, first = np.unique(rim[:, :2], axis=0, return_index=True)   # one per column
        cols = rim[first]
        roofs = [_roof(hu[i, j], hu[i, j] < AIR_HU, k, zs[0], sp[2]) for i, j, k in cols]
        i, j, _ = cols[int(np.argmax(roofs))]   # the highest point of its roof
        out[f"porion_{name}"] = frame.to_scene([x[i], ys[j], max(roofs)])
    if len(out) < 2:
        return out
    z_po = np.mean([frame.to_head(p)[2] for p in out.values()])
    has = bone.any(axis=1)
    front_j = bone.shape[1] - 1 - np.argmax(bone[:, ::-1, :], axis=1)
    front = np.where(has, ys[front_j], ys[0] - ORBIT_CLOSING_MM)   # (x, z) most anterior bone
    r = np.ceil(ORBIT_CLOSING_MM / 2 / sp[[0, 2]]).astype(int)
    g = np.mgrid[-r[0]:r[0] + 1, -r[1]:r[1] + 1]
    disk = (g[0] * sp[0]) ** 2 + (g[1] * sp[2]) ** 2 <= (ORBIT_CLOSING_MM / 2) ** 2
    deep = ndimage.grey_closing(front, footprint=disk) - front > ORBIT_DEPTH_MM
    height = zs - z_po   # above the porions
    for name, side in (("L", 1.0), ("R", -1.0)):
        lateral = (side * x >= ORBIT_OFFSET_MM[0]) & (side * x <= ORBIT_OFFSET_MM[1])
        parts, n = ndimage.label(deep & lateral[:, None])
        best, area = None, ORBIT_MIN_MM2
        for lbl in range(1, n + 1):
            ii, kk = np.nonzero(parts == lbl)
            a = len(ii) * sp[0] * sp[2]
            if a >= area and ORBIT_ABOVE_PORION_MM[0] <= height[kk].mean() \
                    <= ORBIT_ABOVE_PORION_MM[1]:
                best, area = (ii, kk), a
        if best is None:
            continue
        ii, kk = best
        low = kk.min()
        if low == 0:
            continue
        cols = np.unique(ii[kk <= low + 1])   # the opening's lowest rows: the rim below
        # one voxel behind the rim's front, where the rim is bone through
        behind = [(i, max(front_j[i, k] - 1, 0), k) for i in cols for k in [kk[ii == i].min() - 1]]
        rims = [_roof(hu[i, j], bone[i, j], k, zs[0], sp[2]) for i, j, k in behind]
        i, j, _ = behind[int(np.argmin(rims))]   # the rim's lowest point
        out[f"orbitale_{name}"] = frame.to_scene([x[i], ys[j], min(rims)])
    return out


def _near(mask: np.ndarray, axis: int, sign: int, n: int) -> np.ndarray:
    """Where ``mask`` holds within n voxels along ``axis`` in direction ``sign``."""
    out = np.zeros_like(mask)
    for k in range(1, n + 1):
        src, dst = [slice(None)] * 3, [slice(None)] * 3
        src[axis], dst[axis] = (slice(k, None), slice(None, -k)) if sign > 0 else \
            (slice(None, -k), slice(k, None))
        out[tuple(dst)] |= mask[tuple(src)]
    return out


def estimate_on_scan(volume, bone_of, bone_hu: float | None = None) -> HeadFrame:
    """`estimate` on a whole scan (`meshes.volume.Volume`) averaged to `FRAME_VOXEL_MM` (a
    label map: ``bone_hu`` None); ``bone_of(v)``: the bone mask of a volume v."""
    v = volume.coarsened(FRAME_VOXEL_MM, labels=bone_hu is None)
    return estimate(v, bone_of(v), bone_hu)


def estimate(volume, bone: np.ndarray, bone_hu: float | None = None) -> HeadFrame:
    """The frame of a CT (`meshes.volume.Volume`, the whole scan) with its bone mask: the MSP
    by symmetry; the FH through the porions and the left orbitale (the right where the left is
    not found) where ``bone_hu`` is given (a CT in HU) and `frankfort_points` finds them,
    else the scan's axial plane, with a warning that says so (module docstring)."""
    n, origin, rms = symmetry_plane(volume, bone)
    frame = from_axes(n, np.array([0.0, 0.0, 1.0]), origin,
                      {"midsagittal": "estimated", "horizontal": "assumed"})
    found = {} if bone_hu is None else frankfort_points(volume, frame, bone_hu)
    orb = found.get("orbitale_L", found.get("orbitale_R"))
    why = "no ear canals and orbits were found in the scan"
    if "porion_L" in found and "porion_R" in found and orb is not None:
        po_l, po_r = (frame.to_head(found[k]) for k in ("porion_L", "porion_R"))
        up = np.cross(found["porion_R"] - found["porion_L"], orb - found["porion_L"])
        up = _unit(up * np.sign(up[2]), "the Frankfort horizontal's normal")
        tilt = np.degrees(np.arccos(min(abs(float(up[2])), 1.0)))
        dz = abs(po_l[2] - po_r[2])
        if dz > PORION_LEVEL_MM or tilt > FH_MAX_TILT_DEG:
            why = (f"the porions and orbitale found are implausible (porions {dz:.1f} mm "
                   f"apart in height, the plane {tilt:.0f} degrees from axial)")
        else:
            mid = (found["porion_L"] + found["porion_R"]) / 2
            mid = mid - float((mid - origin) @ n) * n   # onto the MSP
            frame = from_axes(n, up, mid, {"midsagittal": "estimated",
                                           "horizontal": "estimated"})
            frame = dataclasses.replace(frame, points=found)
            log.info("%s: head frame estimated: the mid-sagittal plane by the bone's symmetry "
                     "(mirror distance %.2f mm), the Frankfort horizontal through porions and "
                     "orbitale found on the CT", volume.name, rms)
            return frame
    frame = dataclasses.replace(frame, points=found)
    log.warning("%s: no head frame given; the mid-sagittal plane is the bone's plane of "
                "symmetry (mirror distance %.2f mm), and the Frankfort horizontal is assumed to "
                "be the scan's axial plane (%s): a head pitched in the scanner keeps its pitch "
                "(give 'frame' in the scene file: porion_L, porion_R, orbitale_L, nasion)",
                volume.name, rms, why)
    return frame
