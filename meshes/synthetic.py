"""A parametric, anatomically plausible lower face built with gmsh (OpenCASCADE).

Bone and skin are unions of ellipsoids. The skin primitives are the bone primitives grown by a
soft-tissue thickness, plus nose, lips and cheeks. The soft tissue is (skin ∩ face mask) − bone:
a hollow shell whose inner surface is bone and outer surface is skin; the face mask cuts it
behind the tragion (y = -12 mm) and above the nasion (z = 50 mm), and those cut faces are the
"rim", held fixed like the skull.

The bone surface is split by three surgical planes (rest geometry):

* LeFort I cut at ``z = Z_LEFORT``; the maxilla below it is split at the midline (two segments);
* occlusal plane at ``z = Z_OCCLUSAL`` (+ the case's vertical mandible offset);
* BSSO cut at ``y = Y_BSSO``: the mandible anterior to it is the distal (moving) segment.

Bone within ``BAND_MM / 2`` of any cut is left free (elevated periosteum): a moving segment that
directly borders fixed bone makes the Jacobian indefinite (DESIGN.md, measured). Behind the BSSO
cut the free bone reaches ``SPLIT_MM`` back: the sagittal split's overlap, where the buccal plate
of the proximal segment and the distal segment slide along each other. With only ``BAND_MM / 2``
there, a 6 mm setback (4.7 mm lateral) crushed the tissue over the split (det F 0.09, 26
factorisations from rest on coarse; 10 mm with 3 mm lateral failed); with 15 mm: det F 0.59
and 2 factorisations (10 mm: 20). Like the cut bands, the zone spans
every height, so it also frees bone above the occlusal plane behind the cut (upper ramus and
cheek: ~2100 mm² on coarse); confining it to the ramus is open.
Cases differ in the position and yaw of the mandible (and a little of the maxilla).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from pathlib import Path

import numpy as np

from meshes.anatomy import (
    RIM,
    SKIN,
    Anatomy,
    Landmark,
    boundary_facets,
    intersect_rays,
    signed_volumes,
)
from meshes.errors import InputError, MeshError
from meshes.osteotomy import BAND_MM, SEGMENT_TAGS, SPLIT_MM, Osteotomies
from meshes.plane import axis_plane
from meshes.teeth import CROWN_MM, VESTIBULE_MM, tag_teeth
from meshes.tissue import FAT_HU, SKIN_MM, tissue_fractions

log = logging.getLogger(__name__)

GENERATOR_VERSION = 5   # 4: the teeth label (`meshes.teeth`); 5: tissue classes
Z_LEFORT, Z_OCCLUSAL, Y_BSSO = -15.0, -38.0, 20.0
#: Z_LEFORT: the LeFort I cut runs below the piriform rim, 4 mm above subnasale (z = -19),
#: so the nose sits on bone that does not move. With the cut at -6 mm (through the nasal
#: base) a 5 mm LeFort I advance brought the nasal tip 0.42 of it forward and 0.69 up
#: (published: 0.13-0.33 forward, little elevation); at -15 mm: 0.20 forward, 0.36 up,
#: subnasale 0.57, upper lip 0.62 (class1, coarse; BENCHMARKS.md, plausibility). At -18 mm
#: subnasale fell to 0.48, below its published 0.5-0.9.
Y_MASK, Z_MASK = -12.0, 50.0
#: The synthetic heads' tissue is glued to their teeth unless a scene says otherwise (the
#: paper's model, which these heads are compared with): their soft-to-hard ratios differ by
#: at most 0.03 between the two contacts, all inside the published ranges either way
#: (class1 coarse, 5 mm LeFort I: subnasale 0.57 glued, 0.53 sliding; nasal tip 0.20 and
#: 0.18 forward; BENCHMARKS.md, plausibility; docs/decisions.md).
SYNTHETIC_CONTACT = "glued"
#: The synthetic heads' material unless a scene says otherwise: the paper's homogeneous one
#: (docs/decisions.md, "Tissues"); their tissue classes serve ``--material tissues``.
SYNTHETIC_MATERIAL = "homogeneous"
#: Lean tissue (`meshes.tissue`) of the synthetic heads: a layer this thick (mm) on the bone,
#: where the muscles of mastication and expression lie (masseter, buccinator, mentalis), and
#: the lips (orbicularis oris) and the nose (its cartilage reads as lean tissue on a CT). The
#: rest under the skin is fat: the subcutaneous fat and the cheeks' buccal fat.
MUSCLE_MM = 4.0
#: Target edge length (mm) per resolution; vertex counts are measured in BENCHMARKS.md.
RESOLUTIONS = {"tiny": 8.0, "coarse": 5.5, "medium": 4.0, "paper": 2.3, "fine": 1.4}


@dataclasses.dataclass(frozen=True)
class Case:
    """A malocclusion preset: mandible offset (mm) and yaw (degrees), maxilla offset (mm)."""

    description: str
    mandible_shift: tuple = (0.0, 0.0, 0.0)
    mandible_yaw_deg: float = 0.0
    maxilla_shift: tuple = (0.0, 0.0, 0.0)


CASES = {
    "class1": Case("neutral occlusion"),
    "class2": Case("Angle class II: retruded mandible", (0.0, -7.0, 2.0)),
    "class3": Case("Angle class III: prognathic mandible, slightly retruded maxilla",
                   (0.0, 7.0, -2.0), 0.0, (0.0, -2.0, 0.0)),
    "class3-asym": Case("class III, chin deviated to the right (mandible shifted and yawed)",
                        (4.0, 6.0, -2.0), 6.0, (0.0, -2.0, 0.0)),
}
MANDIBLE_PIVOT = np.array([0.0, 0.0, -40.0])  # yaw axis of the malocclusion: between condyles


@dataclasses.dataclass(frozen=True)
class Ellipsoid:
    """Ellipsoid with centre c (mm), semi-axes r (mm) and rotation R (3x3, local -> world)."""

    c: np.ndarray
    r: np.ndarray
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))

    def grown(self, t: float) -> "Ellipsoid":
        return Ellipsoid(self.c, self.r + t, self.R)

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Approximate signed distance (K,) of points p (K, 3): < 0 inside."""
        q = (p - self.c) @ self.R / self.r
        return (np.linalg.norm(q, axis=1) - 1.0) * self.r.min()


def _rot(axis, deg):
    """Rotation matrix about a unit axis by deg degrees."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.deg2rad(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def case_occlusion(case: Case) -> np.ndarray:
    """The final occlusion of a case (4×4): the mandible's motion relative to the maxilla
    that undoes the malocclusion, ``M_maxilla M_mandible⁻¹`` (M: the case's displacement of
    each jaw from the neutral head), known exactly."""
    M_mand, M_max = np.eye(4), np.eye(4)
    R = _rot((0, 0, 1), case.mandible_yaw_deg)
    M_mand[:3, :3] = R
    M_mand[:3, 3] = MANDIBLE_PIVOT - R @ MANDIBLE_PIVOT + case.mandible_shift
    M_max[:3, 3] = case.maxilla_shift
    return M_max @ np.linalg.inv(M_mand)


def _primitives(case: Case):
    """(bone ellipsoids with tissue thickness, extra skin ellipsoids, mandible transform)."""
    E = lambda c, r, R=np.eye(3): Ellipsoid(np.array(c, float), np.array(r, float), R)  # noqa
    Ry = _rot((0, 0, 1), case.mandible_yaw_deg)
    mand = lambda c: MANDIBLE_PIVOT + Ry @ (np.array(c) - MANDIBLE_PIVOT) + case.mandible_shift  # noqa
    maxi = lambda c: np.array(c) + case.maxilla_shift  # noqa
    bone = [(E((0, 0, 25), (68, 88, 75)), 6.0),                      # cranium and midface
            (E(maxi((0, 52, -20)), (30, 33, 17)), 14.0),             # maxilla
            # the body is nearly round in plan view: yaw moves its centre only (a yawed
            # BSpline ellipsoid here breaks OCC's boolean fuse; the volume check catches that)
            (E(mand((0, 40, -55)), (46, 42, 17)), 12.0),         # mandible body
            (E(mand((0, 78, -64)), (13, 7, 11), Ry), 10.0),          # chin
            (E((46, 8, -25), (8, 14, 30)), 16.0),                    # rami (stay put)
            (E((-46, 8, -25), (8, 14, 30)), 16.0)]
    skin = [E((0, 100, 8), (10, 12, 26), _rot((1, 0, 0), -20)),      # nasal dorsum
            E((0, 112, -8), (9, 8, 8)),                              # nose tip
            E(maxi((0, 91, -31)), (24, 10, 8)),                      # upper lip
            E(mand((0, 89, -45)), (22, 10, 7), Ry),                  # lower lip
            E((42, 48, -12), (22, 25, 25)), E((-42, 48, -12), (22, 25, 25))]  # cheeks
    return bone, skin, mand, Ry


def _distances(case: Case, points: np.ndarray):
    """Approximate signed distances (skin (K,), bone (K,)) of points (K, 3) to the case's
    skin and bone primitives: < 0 inside."""
    bone, extra, _, _ = _primitives(case)
    d_skin = np.min([e.grown(t).distance(points) for e, t in bone]
                    + [e.distance(points) for e in extra], axis=0)
    return d_skin, np.min([e.distance(points) for e, _ in bone], axis=0)


def _is_fat(case: Case, x: np.ndarray) -> np.ndarray:
    """(K,) bool: points x (K, 3) mm in the case's fat (`MUSCLE_MM`)."""
    bone, extra, _, _ = _primitives(case)
    d_bone = np.min([e.distance(x) for e, _ in bone], axis=0)
    lean = (d_bone < MUSCLE_MM) | np.any([e.distance(x) < 0 for e in extra[:4]], axis=0)
    return ~lean


def _teeth(case: Case, mid: np.ndarray) -> np.ndarray:
    """(F,) bool: facet midpoints ``mid`` (F, 3) within a crown height
    (`meshes.teeth.CROWN_MM`) of their jaw's occlusal edge (the maxilla's lowest and the
    mandible body's highest point), where the dental arches stand."""
    bone = _primitives(case)[0]
    edge = {"maxilla": bone[1][0].c[2] - bone[1][0].r[2],
            "mandible": bone[2][0].c[2] + bone[2][0].r[2]}
    return ((mid[:, 2] <= edge["maxilla"] + CROWN_MM["maxilla"]) &
            (mid[:, 2] >= edge["mandible"] - CROWN_MM["mandible"]))


def _landmark_rays(case: Case):
    """name -> (origin, direction): the landmark is the outermost skin hit of the ray."""
    _, _, mand, Ry = _primitives(case)
    fwd = Ry @ np.array([0, 1.0, 0])
    return {"N": ((0, 0, 40), (0, 1, 0)), "Prn": ((0, 0, -8), (0, 1, 0)),
            "Sn": ((0, 0, -19), (0, 1, 0)), "Ls": (np.add((0, 0, -31), case.maxilla_shift),
                                                   (0, 1, 0)),
            "Li": (mand((0, 0, -45)), fwd), "Pg": (mand((0, 40, -64)), fwd),
            "Me": (mand((0, 72, -55)), (0, 0, -1)),
            "T_L": ((0, 0, 10), (1, 0, 0)), "T_R": ((0, 0, 10), (-1, 0, 0))}


def _gmsh_tissue(case: Case, h: float):
    """Mesh the soft tissue with gmsh; returns points (N, 3) and tets (M, 4)."""
    from meshes._gmsh import gmsh_session

    bone, skin_extra, _, _ = _primitives(case)
    with gmsh_session(["-noenv"]) as gmsh:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)  # deterministic
        occ = gmsh.model.occ

        def add(e: Ellipsoid):
            s = occ.addSphere(0, 0, 0, 1.0)
            occ.dilate([(3, s)], 0, 0, 0, *e.r)
            ang = np.arccos(np.clip((np.trace(e.R) - 1) / 2, -1, 1))
            if ang > 1e-12:
                ax = np.array([e.R[2, 1] - e.R[1, 2], e.R[0, 2] - e.R[2, 0], e.R[1, 0] - e.R[0, 1]])
                occ.rotate([(3, s)], 0, 0, 0, *ax, ang)
            occ.translate([(3, s)], *e.c)
            return (3, s)

        skin = [add(b.grown(t)) for b, t in bone] + [add(e) for e in skin_extra]
        bones = [add(b) for b, _ in bone]
        skin_u, _ = occ.fuse(skin[:1], skin[1:])
        bone_u, _ = occ.fuse(bones[:1], bones[1:])
        box = occ.addBox(-150, Y_MASK, -200, 300, 300, 200 + Z_MASK)
        mask, _ = occ.intersect(skin_u, [(3, box)])
        occ.cut(mask, bone_u)
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * h)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay: deterministic
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        tags, x, _ = gmsh.model.mesh.getNodes()
        _, conn = gmsh.model.mesh.getElementsByType(4)
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    cells = index[conn.astype(np.int64)].reshape(-1, 4)
    used = np.unique(cells)  # drop nodes of lower-dimensional entities not in any tet
    remap = -np.ones(len(tags), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return x.reshape(-1, 3)[used], remap[cells]


def case_osteotomies(case: Case) -> Osteotomies:
    """The surgical planes of a case (rest geometry), as `meshes.osteotomy` classifies them."""
    bsso = axis_plane(1, Y_BSSO)
    return Osteotomies(midsagittal=axis_plane(0, 0.0), lefort1=axis_plane(2, Z_LEFORT),
                       occlusal=axis_plane(2, Z_OCCLUSAL + case.mandible_shift[2]),
                       ramus_L=bsso, ramus_R=bsso, band_mm=BAND_MM, split_mm=SPLIT_MM)


def build(case_name: str, resolution: str) -> Anatomy:
    """Generate (no cache) the synthetic anatomy for a case and resolution."""
    case, h = _check(case_name, resolution)
    points, cells = _gmsh_tissue(case, h)
    facets = boundary_facets(cells)
    mid = points[facets].mean(axis=1)
    d_skin, d_bone = _distances(case, mid)
    tags = np.full(len(facets), SKIN, dtype=np.int32)
    is_bone = np.abs(d_bone) < np.abs(d_skin)
    tags[is_bone] = case_osteotomies(case).classify(mid[is_bone])
    rim = (np.abs(mid[:, 1] - Y_MASK) < 1e-6) | (np.abs(mid[:, 2] - Z_MASK) < 1e-6)
    tags[rim] = RIM
    segments = dict(SEGMENT_TAGS)
    tags = tag_teeth(points, facets, tags, segments, _teeth(case, mid))
    skin_idx = np.flatnonzero(tags == SKIN)
    landmarks = {}
    for name, (o, d) in _landmark_rays(case).items():
        hit = intersect_rays(points, facets[skin_idx], o, d)
        if hit is None:
            raise MeshError(f"landmark {name} ray missed the skin of case {case_name}")
        landmarks[name] = Landmark(facets[skin_idx[hit[0]]], hit[1])
    _check_volume(case, points, cells, case_name)
    tissues = tissue_fractions(points, cells, facets[tags == SKIN], lambda x: _is_fat(case, x))
    anatomy = Anatomy(points, cells, facets, tags, segments, {}, landmarks,
                      name=f"{case_name}/{resolution}", occlusion=case_occlusion(case),
                      contact=SYNTHETIC_CONTACT, tissues=tissues, material=SYNTHETIC_MATERIAL)
    anatomy.validate()
    # pivots: the centroid of each segment's rest bone vertices
    anatomy.pivots = {s: points[anatomy.segment_vertices(s)].mean(axis=0) for s in segments}
    return anatomy


def _check_volume(case: Case, points, cells, case_name: str, grid_mm: float = 2.0):
    """Compare the meshed volume with the implicit (skin ∩ mask) − bone sampled on a grid.

    OpenCASCADE booleans on BSpline ellipsoids can silently drop a primitive; this catches it.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    axes = [np.arange(a + grid_mm / 2, b, grid_mm) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d_skin, d_bone = _distances(case, g)
    inside_skin, inside_bone = d_skin < 0, d_bone < 0
    in_mask = (g[:, 1] > Y_MASK) & (g[:, 2] < Z_MASK)
    expected = np.sum(inside_skin & ~inside_bone & in_mask) * grid_mm ** 3
    meshed = np.abs(signed_volumes(points, cells)).sum()
    if abs(meshed - expected) > 0.05 * expected:
        raise MeshError(f"gmsh produced {meshed:.0f} mm^3 of tissue for case {case_name}, "
                        f"expected {expected:.0f} mm^3: a boolean operation failed")


def _check(case_name: str, resolution: str):
    if case_name not in CASES:
        raise InputError(f"unknown case {case_name!r}; choose one of {sorted(CASES)}")
    if resolution not in RESOLUTIONS:
        raise InputError(f"unknown resolution {resolution!r}; choose one of {list(RESOLUTIONS)}")
    return CASES[case_name], RESOLUTIONS[resolution]


def cache_dir() -> Path:
    """Folder of cached meshes: ``$ORTHODIFF_CACHE`` or ``~/.cache/orthodiff``."""
    return Path(os.environ.get("ORTHODIFF_CACHE", Path.home() / ".cache" / "orthodiff"))


def _gmsh_identity() -> str:
    """A digest of gmsh's Python API file (it names the version), read, not imported:
    importing Debian's gmsh costs 0.26 s, which a cached mesh need not pay."""
    import importlib.util

    return hashlib.sha1(Path(importlib.util.find_spec("gmsh").origin).read_bytes()).hexdigest()


def synthetic_head(case_name: str = "class3-asym", resolution: str = "coarse") -> Anatomy:
    """The synthetic anatomy of a case at a resolution, from the disk cache when present."""
    case, h = _check(case_name, resolution)
    # gmsh's too: Debian's 4.8 and PyPI's 4.15 mesh a case differently
    key = hashlib.sha1(repr((GENERATOR_VERSION, _gmsh_identity(), case, h, Z_LEFORT, Z_OCCLUSAL,
                             Y_BSSO, BAND_MM, SPLIT_MM, CROWN_MM, VESTIBULE_MM, MUSCLE_MM,
                             SKIN_MM, FAT_HU)).encode()).hexdigest()[:12]
    path = cache_dir() / f"{case_name}-{resolution}-{key}.npz"
    if path.exists():
        try:
            anatomy = Anatomy.load(path)
            anatomy.occlusion = case_occlusion(case)   # from the case, not the cache
            anatomy.contact, anatomy.material = SYNTHETIC_CONTACT, SYNTHETIC_MATERIAL
            return anatomy
        except MeshError:
            log.warning("cached mesh %s is unreadable; regenerating", path)
    log.info("generating %s/%s (h = %.1f mm) into %s", case_name, resolution, h, path)
    anatomy = build(case_name, resolution)
    anatomy.save(path)
    return anatomy


#: HU of the voxelised synthetic head (`synthetic_ct`): air, lean tissue, fat, cortical bone.
CT_HU = {"air": -1000, "tissue": 40, "fat": -100, "bone": 1000}


def synthetic_ct(case_name: str, voxel_mm: float = 1.0, margin_mm: float = 6.0):
    """The synthetic head of a case as a CT (`meshes.volume.Volume`, HU): the primitives'
    skin and bone sampled at voxel centres, the whole head (no face mask: the mask's planes
    are the crop of `synthetic_scene_file`). For testing the CT pipeline against the anatomy the
    head is built from."""
    from meshes.volume import Volume

    lo = np.array([-95.0, Y_MASK - margin_mm, -95.0])
    hi = np.array([95.0, 135.0, Z_MASK + margin_mm])
    axes = [np.arange(a, b + voxel_mm / 2, voxel_mm) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d_skin, d_bone = _distances(CASES[case_name], g)
    soft = np.where(_is_fat(CASES[case_name], g), CT_HU["fat"], CT_HU["tissue"])
    hu = np.where(d_bone < 0, CT_HU["bone"], np.where(d_skin < 0, soft, CT_HU["air"]))
    shape = tuple(len(a) for a in axes)
    return Volume(hu.reshape(shape).astype(np.int16), np.full(3, voxel_mm), lo,
                  f"{case_name} voxelised at {voxel_mm:g} mm")


def synthetic_scene_file(case_name: str) -> dict:
    """The CT pipeline's scene file for `synthetic_ct`: the case's osteotomy planes, and the
    face mask as the crop (its back and top faces held, as the synthetic rim)."""
    cuts = case_osteotomies(CASES[case_name])
    plane = lambda p: {"point": list(p.point), "normal": list(p.normal)}  # noqa: E731
    spec = {k: plane(getattr(cuts, k)) for k in ("midsagittal", "lefort1", "occlusal",
                                                 "ramus_L", "ramus_R")}
    spec.update(band_mm=cuts.band_mm, split_mm=cuts.split_mm,
                crop={"min": [-200.0, Y_MASK, -200.0], "max": [200.0, 200.0, Z_MASK]})
    return spec
