"""From a CT volume to a simulation-ready `Anatomy` (the paper's data pipeline, appendix).

Stages, each with the well-kept library for it:

1. **read** (`meshes.volume`: SimpleITK, or the InVesalius project reader), the values put on
   HU by the histogram's classes (`meshes.intensity`) and metal's streaks taken out
   (`meshes.metal`);
2. **segment** (`meshes.segment`: thresholds or a label map; scipy.ndimage) inside the crop;
3. **mesh** the soft tissue with CGAL Mesh_3 (``pygalmesh.generate_from_array`` on the tissue
   label), sized per resolution (`CGAL_SIZING`);
4. **classify** each boundary facet by the label just outside it: skin (air), bone, crop
   (held: `RIM`) or free (air inside the head, a free crop face: no tag, traction-free); bone
   facets by the osteotomy planes (`meshes.osteotomy`), once the bone's vertices are slid
   onto the free bands' edges (`snap_to_edges`), and the segments' teeth and
   vestibule by HU (`meshes.teeth`); then the flaps the cut's free band leaves hanging go
   (`drop_flaps`);
5. **landmarks** on the mid-sagittal profile and at the ears (`meshes.landmarks`), built in
   the head frame (`meshes.frame`: given by the scene file's ``frame``, or estimated on the
   whole CT before the crop), or from a file;
6. **tissues**: each cell's share of skin, fat and lean tissue (`meshes.tissue`: by HU, or
   by a label map's ``"fat"`` label), the skin layer under the face's skin, not a cavity's
   lining (`LINING_MM`).

The scene file (JSON, mm in the scene's frame: the CT's patient frame with x left, y anterior,
z superior) holds the osteotomy planes and optionally ``frame`` (`meshes.frame`), ``crop``
(``{"min": [x, y, z], "max": [x, y, z], "free": ["-z"]}``; default: the whole field of view,
every face held),
``skin_hu``, ``bone_hu`` (HU, after the scan is put on HU), ``calibration`` (``"auto"``: a
CBCT's gray values to HU by its histogram's classes, `meshes.intensity`; ``"none"``: the values
as they are), ``labels`` (a label map's values, ``{"tissue": 1, "bone": 2}``) and
``occlusion`` (4×4 or a .tfm, the final occlusion). A plane may come from a 3D Slicer markups
file (`meshes.osteotomy.resolve_plane_files`). The result is deterministic (CGAL's seed is
fixed) and cached under `meshes.synthetic.cache_dir` by the input's content, the options and
the pipeline's source.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from meshes import segment as seg
from meshes.anatomy import (
    DIRICHLET_TAGS,
    FIXED,
    FREE_BONE,
    RIM,
    SKIN,
    TET_FACES,
    Anatomy,
    _facet_keys,
    facet_components,
    signed_volumes,
    tet_quality,
)
from meshes.errors import MeshError
from meshes.frame import estimate_on_scan, from_spec
from meshes.intensity import read_ct
from meshes.landmarks import skin_landmarks, staircase_mm
from meshes.metal import METAL_HU, reduce_metal
from meshes.osteotomy import Osteotomies, resolve_plane_files
from meshes.plane import Plane
from meshes.surface import unique_edges
from meshes.synthetic import RESOLUTIONS, cache_dir
from meshes.teeth import TEETH_HU, ct_teeth, tag_teeth
from meshes.tissue import FAT_HU, ct_fat, tissue_fractions, tissue_report
from meshes.volume import Volume, read_volume

log = logging.getLogger(__name__)

#: A CT scene's size unless asked: the coarsest whose every landmark's motion lies within
#: 0.1 mm of ``fine``'s on both example CTs under a 5 mm advance (BENCHMARKS.md, "Accuracy:
#: mesh convergence on the CTs": paper 0.04-0.09 mm, medium 0.26-0.28, coarse 0.33-0.92).
DEFAULT_RESOLUTION = "paper"
#: CGAL Mesh_3 criteria as multiples of the resolution's edge length h (`RESOLUTIONS`): cell
#: circumradius and surface Delaunay-ball radius 1.3 h, which puts a CT face at the synthetic
#: heads' vertex counts (headsq, paper: 40.2 k vertices; 0.6 h gave 27 k at coarse), facet
#: distance 0.3 h (a sphere of radius 40 mm from 1 mm voxels at 0.2 mm: area within 0.6 %,
#: vertices within 0.2 mm of the radius), radius-edge ratio 3. CGAL's sliver perturbation is
#: off: it stops on a clock, so the same CT gave other meshes under load (a loaded and an idle
#: run differed); without it the mesh is the same bit for bit, and the worst tet quality falls
#: from 0.17-0.21 to 0.06-0.075 (Cranium, synthetic CT), far above `SLIVER_QUALITY`.
CGAL_SIZING = {"cell": 1.3, "facet_distance": 0.3, "radius_edge": 3.0}
#: Voxels of empty image added on every side when CGAL meshes nothing: its initial points
#: (rays from the image's centre) then give a surface it refines. The synthetic head CT
#: tilted (-10, 5, -7) degrees and cropped to its face box: 14 points and no tetrahedra with
#: seeds 1 to 3 and with its largest tissue component alone; 3469 points once padded by 10
#: (or by 20 on one side). Other images mesh as they did, unpadded.
CGAL_RETRY_PAD = 10
#: The mid-sagittal plane in the head frame's own coordinates (`meshes.frame`).
HEAD_MIDSAGITTAL = Plane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
#: The worst shape quality (`meshes.anatomy.tet_quality`) a vertex's move onto a cut's band
#: edge (`snap_to_edges`) may leave its cells: the meshes' own worst, 0.06-0.075 (above).
SNAP_QUALITY = 0.05
#: A skin facet this deep (mm) under the face's envelope (`meshes.segment.envelope_depth`)
#: lines a cavity open to the air around the head (the nasal cavity, an ear canal): mucosa,
#: not dermis, so the skin layer (`meshes.tissue.SKIN_MM`) is measured from the others. On
#: it Cranium's Sn moved up to 0.32 mm with the head on the voxel grid (docs/decisions.md);
#: 5, 6 and 8 mm (with the envelope closed by 5, 12 and 8 mm) gave the same within 0.01.
LINING_MM = 6.0
#: Sampling distances outside a facet, in voxels along its normal, to read the label there.
SAMPLE_VOXELS = (0.75, 1.5, 2.25)
#: A facet within this many voxels of a crop face's label boundary, facing out of it, is on
#: the crop face.
CROP_FACE_VOXELS = 0.75


@contextlib.contextmanager
def _quiet():
    """CGAL prints its progress on the standard streams even with verbose=False: send fds 1
    and 2 to /dev/null meanwhile (its errors still arrive as Python exceptions)."""
    import ctypes
    import sys

    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        libc.fflush(None)   # C++ streams are synced with stdio: flush them into /dev/null
        for fd, copy in zip((1, 2), saved):
            os.dup2(copy, fd)
            os.close(copy)


def _digest(path: Path) -> str:
    h = hashlib.sha1()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        h.update(f.name.encode())
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def _code_digest() -> str:
    """The pipeline's own source: a cached scene is rebuilt when the code that made it
    changes (the synthetic heads bump `GENERATOR_VERSION` by hand; here no hand is needed)."""
    import importlib

    h = hashlib.sha1()
    for name in ("anatomy", "frame", "intensity", "landmarks", "metal", "osteotomy", "plane",
                 "segment", "teeth", "tissue", "volume"):
        h.update(Path(importlib.import_module(f"meshes.{name}").__file__).read_bytes())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()


def read_scene_file(path) -> dict:
    """The scene file's JSON (see the module docstring)."""
    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise MeshError(f"cannot read the osteotomy file {path}: {e}") from None
    if not isinstance(spec, dict):
        raise MeshError(f"{path}: expected a JSON object")
    return resolve_plane_files(spec, Path(path).parent)


def parse_scene_file(path):
    """(spec, `Osteotomies`, `meshes.frame.HeadFrame` or None) of a scene file, checked
    whole: `MeshError` with one line for a bad plane or frame."""
    spec = read_scene_file(path)
    cuts = Osteotomies.from_dict(spec, str(path))
    frame = None if spec.get("frame") is None else from_spec(spec["frame"], path)
    return spec, cuts, frame


def _crop_box(spec, volume: Volume):
    crop = spec.get("crop") or {}
    lo = np.asarray(crop.get("min", volume.origin), float)
    hi = np.asarray(crop.get("max", volume.origin + volume.spacing * (np.array(
        volume.array.shape) - 1)), float)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(np.r_[lo, hi])) \
            or np.any(hi <= lo):
        raise MeshError(f"crop: expected min < max, each [x, y, z] mm; got {crop!r}")
    return lo, hi, tuple(crop.get("free", ()))


def _mesh(labels: np.ndarray, volume: Volume, h: float):
    """CGAL tets of the tissue label: points (N, 3) mm in the scene's frame, cells (M, 4).
    Where CGAL meshes nothing, it is asked again with the image padded (`CGAL_RETRY_PAD`)."""
    try:
        import pygalmesh
    except ImportError:
        raise MeshError("a CT scene needs pygalmesh (CGAL's mesher), which is not installed: "
                        "Debian's python3-pygalmesh, or `pip install pygalmesh` with "
                        "libcgal-dev and libeigen3-dev") from None

    tissue = (labels == seg.TISSUE).astype(np.uint8)
    for pad in (0, CGAL_RETRY_PAD):
        with _quiet():
            m = pygalmesh.generate_from_array(
                np.pad(tissue, pad), tuple(float(s) for s in volume.spacing),
                max_cell_circumradius=CGAL_SIZING["cell"] * h,
                max_radius_surface_delaunay_ball=CGAL_SIZING["cell"] * h,
                max_facet_distance=CGAL_SIZING["facet_distance"] * h,
                max_circumradius_edge_ratio=CGAL_SIZING["radius_edge"], perturb=False,
                verbose=False, seed=1)
        cells = np.asarray(m.get_cells_type("tetra"), dtype=np.int64)
        if len(cells):
            break
    if len(cells) == 0:
        raise MeshError(f"CGAL produced no tetrahedra from the tissue of {volume.name}")
    # CGAL leaves a few clusters hanging at an edge or a vertex where the tissue is thin
    # (Cranium coarse: 27 of them, 92 of 18 592 cells)
    cells, source = _bulk(cells)
    points = np.asarray(m.points, float)[source]
    # voxel i of the labels (padded by one voxel of crop) sits at i * spacing in CGAL's frame
    return points + volume.origin - volume.spacing * (1 + pad), cells


def _bulk(cells: np.ndarray):
    """(cells, source) of the facet-connected bulk of ``cells``, pinched vertices split
    (`split_pinched_vertices`)."""
    part = facet_components(cells)
    return split_pinched_vertices(cells[part == np.bincount(part).argmax()])


def drop_flaps(points: np.ndarray, cells: np.ndarray, facets: np.ndarray, tags: np.ndarray):
    """(points, cells, facets, tags) without the flaps the cut's free band leaves hanging:
    cells whose four vertices all lie on free inner surfaces (tag 0: air inside the head, a
    free crop face; `FREE_BONE`: the band), at least one on the band, none on the skin, and
    at most two also on held bone (a held vertex or edge is a hinge, not a hold); e.g. the
    sinus lining over the band, one cell thick between the sinus's air and the freed bone.
    Then the facet-connected bulk (`_bulk`), and again until none is left. ``facets``,
    ``tags``: the whole boundary (B, 3), (B,); the new one keeps each facet's tag, and a
    facet the flaps uncovered is free (0).

    A flap is nearly a mechanism. Cranium, 5 mm LeFort I advance, 2 ranks: at fine,
    quasi-Newton's first search directions were 300-860 mm there, K indefinite at its
    iterates, 141 iterations and 15 factorisations (356 s); without its flaps (0.55 % of
    the cells), 26 and 1 (31 s); at medium and paper, 14 and 22 iterations became 9; the
    landmarks' motion within 0.015 mm. Not kept (docs/decisions.md): flaps away from the band
    too (Sn 0.06 mm off at paper), or only cells touching no held bone at all (a hinged
    remnant then took medium to 60 iterations).
    """
    def on(facet_mask):   # (N,) vertices on these boundary facets (the current ones)
        v = np.zeros(len(points), dtype=bool)
        v[facets[facet_mask]] = True
        return v

    while True:   # dropping flaps may uncover more (Cranium fine: 2 rounds)
        inner = np.isin(tags, (0, FREE_BONE))
        held = on(~np.isin(tags, (0, FREE_BONE, SKIN)))[cells].sum(axis=1)
        flap = on(inner)[cells].all(axis=1) & ~on(tags == SKIN)[cells].any(axis=1) & \
            (held < 3) & on(tags == FREE_BONE)[cells].any(axis=1)
        if not flap.any():
            return points, cells, facets, tags
        n = len(points)
        cells, source = _bulk(cells[~flap])
        points = points[source]
        new, _ = _boundary(cells, points)
        old = _facet_keys(np.sort(facets, axis=1), n)   # each new facet by its old vertices
        order = np.argsort(old)
        keys = _facet_keys(np.sort(source[new], axis=1), n)
        at = np.minimum(np.searchsorted(old[order], keys), len(order) - 1)
        kept = old[order][at] == keys
        facets, tags = new, np.where(kept, tags[order][at], 0).astype(tags.dtype)


def split_pinched_vertices(cells: np.ndarray):
    """(cells, source): every vertex whose cells form several fans (groups joined through
    facets at that vertex) split into one vertex per fan, and unused vertices dropped;
    ``source`` (N',) is each new vertex's old index (its point: ``points[source]``). CGAL
    pinches thin tissue at single vertices (Cranium coarse: 220 of them), and so does
    `drop_flaps`; Debian's dolfinx 0.5.2 then deadlocks in ``create_connectivity(2, 0)`` on 2
    ranks (its shared-facet ghosting); a split vertex is two nodes at one place, which the
    mechanics allows."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = cells[:, TET_FACES].reshape(-1, 3)
    keys = _facet_keys(np.sort(faces, axis=1), int(cells.max()) + 1)
    order = np.argsort(keys, kind="stable")
    pair = np.flatnonzero(keys[order][1:] == keys[order][:-1])
    r1, r2 = order[pair], order[pair + 1]           # the two cells' rows of each inner facet
    c1, c2 = r1 // 4, r2 // 4
    verts = faces[r1]                                # (K, 3) vertices of each inner facet
    pos1 = np.argmax(cells[c1][:, :, None] == verts[:, None, :], axis=1)
    pos2 = np.argmax(cells[c2][:, :, None] == verts[:, None, :], axis=1)
    a, b = (c1[:, None] * 4 + pos1).ravel(), (c2[:, None] * 4 + pos2).ravel()
    n = cells.size   # one node per (cell, corner); corners joined through a shared facet
    graph = sp.csr_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, fan = connected_components(graph, directed=False)
    new, first = np.unique(fan, return_index=True)
    remap = np.empty(new.max() + 1, dtype=np.int64)
    remap[new] = np.arange(len(new))
    return remap[fan].reshape(cells.shape), cells.ravel()[first]


def _boundary(cells: np.ndarray, points: np.ndarray):
    """Boundary facets (B, 3) and their outward unit normals (B, 3)."""
    faces = cells[:, TET_FACES].reshape(-1, 3)
    opposite = cells.reshape(-1)
    keys = _facet_keys(np.sort(faces, axis=1), len(points))
    _, first, count = np.unique(keys, return_index=True, return_counts=True)
    b = first[count == 1]
    faces, opposite = faces[b], opposite[b]
    x = points[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n *= np.sign(np.einsum("ij,ij->i", n, x[:, 0] - points[opposite]))[:, None]
    return faces, n / np.linalg.norm(n, axis=1, keepdims=True)


def snap_to_edges(points: np.ndarray, cells: np.ndarray, boundary: np.ndarray, on: np.ndarray,
                  levels: list) -> np.ndarray:
    """Points (N, 3) with vertices of the boundary facets ``boundary[on]`` ((B, 3), (B,)
    bool) slid along their edges onto the level sets ``levels`` ((plane, d mm):
    `meshes.osteotomy.Osteotomies.edges`): where an edge crosses one, its end nearer the
    crossing moves there, or the other end where that move would turn a cell over or leave
    its shape quality below half its own or `SNAP_QUALITY`; a vertex on another boundary
    facet, or moved before, stays. A tag read at facet midpoints then changes along the cut's
    line, not along a ragged row of facets (docs/decisions.md: the LeFort I plane 0.5 mm
    higher on the same mesh moved Sn's predicted motion by 0.16 mm)."""
    points = points.copy()
    own = np.zeros(len(points), dtype=bool)
    own[boundary[on]] = True
    own[boundary[~on]] = False
    order = np.argsort(cells.ravel(), kind="stable")   # vertex -> its cells
    start = np.searchsorted(cells.ravel()[order], np.arange(len(points) + 1))
    moved = np.zeros(len(points), dtype=bool)
    facets = boundary[on]
    edges = unique_edges(facets)[0]
    for plane, level in levels:
        phi = plane.distance(points) - level
        for a, c in edges[phi[edges[:, 0]] * phi[edges[:, 1]] < 0]:
            if phi[a] * phi[c] >= 0:   # an end moved onto it already
                continue
            x = points[a] + phi[a] / (phi[a] - phi[c]) * (points[c] - points[a])
            for v in sorted((a, c), key=lambda j: abs(phi[j])):
                if not own[v] or moved[v]:
                    continue
                near = cells[order[start[v]:start[v + 1]] // 4]
                q0, vol0 = tet_quality(points, near).min(), signed_volumes(points, near)
                old = points[v].copy()
                points[v] = x
                if (signed_volumes(points, near) * vol0 > 0).all() and \
                        tet_quality(points, near).min() >= max(0.5 * q0, SNAP_QUALITY):
                    moved[v], phi[v] = True, 0.0
                    break
                points[v] = old
    return points


def _outside_label(labels: np.ndarray, volume: Volume, mid, normal) -> np.ndarray:
    """The label (B,) just outside each facet: the first non-tissue sample along its normal,
    else the most common non-tissue label around the facet's voxel."""
    origin = volume.origin - volume.spacing   # the padded array
    padded = Volume(labels, volume.spacing, origin)
    step = np.abs(normal) @ volume.spacing
    out = np.full(len(mid), 255, dtype=np.int32)
    shape = np.array(labels.shape)
    for k in SAMPLE_VOXELS:
        todo = out == 255
        lab = padded.at(mid[todo] + k * step[todo, None] * normal[todo]).astype(np.int32)
        sel = np.flatnonzero(todo)
        hit = lab != seg.TISSUE
        out[sel[hit]] = lab[hit]
    for i in np.flatnonzero(out == 255):
        ijk = np.clip(np.rint((mid[i] - origin) / volume.spacing).astype(int), 1, shape - 2)
        box = labels[ijk[0] - 1:ijk[0] + 2, ijk[1] - 1:ijk[1] + 2, ijk[2] - 1:ijk[2] + 2]
        vals = box[box != seg.TISSUE]
        out[i] = np.bincount(vals).argmax() if len(vals) else seg.OUTSIDE
    return out


def read_scan(ct_path, spec: dict) -> tuple:
    """(volume in HU, `meshes.intensity.Intensity`, metal report) of a CT or CBCT: its gray
    values put on HU as the scene file's ``calibration`` says, its metal's streaks out."""
    scan, intensity = read_ct(ct_path, spec.get("calibration", "auto"))
    scan, metal = reduce_metal(scan)
    return scan, intensity, metal


def build(ct_path, scene_file, resolution: str, labelmap: bool = False):
    """(Anatomy, info) from a CT (or label map) and a scene file; info has ``timings_s``
    per stage and ``min_quality``. No cache: see `ct_anatomy`."""
    if resolution not in RESOLUTIONS:
        raise MeshError(f"unknown resolution {resolution!r}; choose one of {list(RESOLUTIONS)}")
    spec, cuts, frame = parse_scene_file(scene_file)
    timings = {}
    t = time.perf_counter()
    is_map = labelmap or spec.get("labels") is not None
    intensity = metal = None
    if is_map:
        scan = read_volume(ct_path)
    else:
        scan, intensity, metal = read_scan(ct_path, spec)
    volume = scan.coarsened(labels=is_map)   # a CBCT's voxels averaged
    timings["read"] = time.perf_counter() - t

    bone_hu = None if is_map else float(spec.get("bone_hu", seg.BONE_HU))

    def masks(v):
        if is_map:
            return seg.labels_from_map(v, spec.get("labels"))
        return seg.labels_from_ct(v, float(spec.get("skin_hu", seg.SKIN_HU)), bone_hu)

    if frame is None:   # on the whole CT, before the crop
        t = time.perf_counter()
        frame = estimate_on_scan(scan, lambda v: masks(v)[1], bone_hu)
        timings["frame"] = time.perf_counter() - t
    del scan
    cuts = cuts.with_midsagittal(Plane(tuple(frame.origin), tuple(frame.rotation[:, 0])))
    t = time.perf_counter()
    lo, hi, free = _crop_box(spec, volume)
    volume = volume.crop(lo, hi)
    body, bone = masks(volume)
    labels = seg.label_volume(volume, body, bone, free)
    timings["segment"] = time.perf_counter() - t
    t = time.perf_counter()
    points, cells = _mesh(labels, volume, RESOLUTIONS[resolution])
    timings["mesh"] = time.perf_counter() - t
    t = time.perf_counter()
    facets, normals = _boundary(cells, points)
    mid = points[facets].mean(axis=1)
    outside = _outside_label(labels, volume, mid, normals)
    tags = np.zeros(len(facets), dtype=np.int32)   # 0: free surface, dropped below
    tags[outside == seg.OUTSIDE] = SKIN
    tags[outside == seg.CROP] = RIM
    on_face = _crop_faces(volume, mid, normals, free)
    tags[on_face == seg.CROP] = RIM
    tags[on_face == seg.CROP_FREE] = 0
    is_bone = outside == seg.BONE
    if not is_bone.any():
        raise MeshError(f"no bone surface under the tissue of {volume.name}")
    cuts.check_cuts(mid[is_bone])
    points = snap_to_edges(points, cells, facets, is_bone, cuts.edges())
    mid = points[facets].mean(axis=1)
    tags[is_bone] = cuts.classify(mid[is_bone])
    segments = cuts.segments()
    held = _held_faces(lo, hi, free)
    near_crop = np.zeros(len(facets), dtype=bool)
    for axis, value in held:   # bone at a held crop face is free, as at a cut
        near_crop |= np.abs(mid[:, axis] - value) < cuts.band_mm / 2
    moving = np.isin(tags, list(segments.values()))
    tags[moving & near_crop] = FREE_BONE
    _widen_bands(points, facets, tags, list(segments.values()), cuts.band_mm / 2)
    if not is_map:   # a label map has no HU to tell teeth by
        moving = np.isin(tags, list(segments.values()))
        teeth = np.zeros(len(facets), dtype=bool)
        teeth[moving] = ct_teeth(volume.at, mid[moving], normals[moving],
                                 float(volume.spacing.min()), cuts.occlusal)
        tags = tag_teeth(points, facets, tags, segments, teeth)
    points, cells, facets, tags = drop_flaps(points, cells, facets, tags)
    for name, tag in segments.items():
        if not np.any(tags == tag):
            raise MeshError(f"segment {name!r} has no facets: the osteotomy planes leave no "
                            "bone surface for it inside the crop")
    if not np.any(tags == FIXED):
        raise MeshError("no fixed bone is left: the cuts free all bone; the skull must hold")
    keep = tags != 0
    anatomy = Anatomy(points, cells, facets[keep], tags[keep], segments, {}, {},
                      name=f"{Path(ct_path).name}/{resolution}", head_frame=frame,
                      thresholds=None if is_map else {
                          "skin_hu": float(spec.get("skin_hu", seg.SKIN_HU)), "bone_hu": bone_hu},
                      voxel_mm=volume.spacing.copy())
    anatomy.validate()
    timings["classify"] = time.perf_counter() - t
    t = time.perf_counter()
    skin = anatomy.facets[anatomy.facet_tags == SKIN]
    rest = tags != SKIN   # the whole boundary but the skin: bone, free and crop faces
    notes = {}
    anatomy.landmarks = skin_landmarks(frame.to_head(anatomy.points), skin, HEAD_MIDSAGITTAL,
                                       (facets[rest], ~np.isin(tags[rest], (0, RIM))),
                                       staircase_mm(volume.spacing, frame), notes)
    anatomy.validate_landmarks()
    timings["landmarks"] = time.perf_counter() - t
    t = time.perf_counter()
    fat = _fat_rule(volume, spec.get("labels"), is_map,
                    None if intensity is None else intensity.noise_hu)
    if fat is not None:
        depth = seg.envelope_depth(Volume(labels, volume.spacing,   # the padded labels' grid
                                          volume.origin - volume.spacing))
        outer = depth.at(anatomy.points[skin].mean(axis=1)) <= LINING_MM
        anatomy.tissues = tissue_fractions(anatomy.points, anatomy.cells, skin[outer], fat)
        anatomy.material = "tissues"
    timings["tissues"] = time.perf_counter() - t
    info = {"timings_s": timings, "tissues": tissue_report(anatomy),
            "min_quality": float(tet_quality(anatomy.points, anatomy.cells).min()),
            "voxel_mm": volume.spacing.tolist(), "landmarks_left_out": notes,
            **frame.report()}
    if intensity is not None:
        given = tuple(k for k in ("skin_hu", "bone_hu") if k in spec)
        info["intensity"] = intensity.report({**anatomy.thresholds, "teeth_hu": TEETH_HU,
                                              "fat_hu": FAT_HU, "metal_hu": METAL_HU}, given)
        info["metal"] = metal
    return anatomy, info


def _fat_rule(volume: Volume, labels, is_map: bool, noise_hu: float | None = None):
    """``is_fat`` of `meshes.tissue.tissue_fractions`: by HU on a CT (`meshes.tissue.ct_fat`,
    its soft tissue's noise ``noise_hu``), by the ``"fat"`` label on a label map that names
    one; None where the scene cannot tell fat (a label map without it)."""
    if not is_map:
        return ct_fat(volume, noise_hu)
    if not labels or "fat" not in labels:
        return None
    values = np.atleast_1d(labels["fat"])
    return lambda x: np.isin(volume.at(x), values)


def _crop_faces(volume: Volume, mid, normals, free) -> np.ndarray:
    """`CROP` or `CROP_FREE` (B,) for facets that lie on a crop face and face out of it (the
    label boundary half a voxel beyond the last voxel centre, within `CROP_FACE_VOXELS`),
    else 255. CGAL rounds the edges of a crop face, where the samples outside a facet may
    reach past the crop's one-voxel padding into the air and call a cut face skin."""
    out = np.full(len(mid), 255, dtype=np.int32)
    last = volume.origin + volume.spacing * (np.array(volume.array.shape) - 1)
    for axis in range(3):
        h = volume.spacing[axis]
        for side, plane, sign in (("-", volume.origin[axis] - h / 2, -1.0),
                                  ("+", last[axis] + h / 2, 1.0)):
            hit = (np.abs(mid[:, axis] - plane) < CROP_FACE_VOXELS * h) & \
                (sign * normals[:, axis] > 0.5)
            out[hit] = seg.CROP_FREE if f"{side}{'xyz'[axis]}" in free else seg.CROP
    return out


def _widen_bands(points, facets, tags, segment_tags, gap_mm: float):
    """Free bone (in place) where a segment meets held bone or a held crop face: segment
    facets that share a vertex with one (a band narrower than a facet, on coarse meshes, must
    still part them), and segment and fixed-bone facets that face each other across less
    than ``gap_mm`` of tissue (a real skull folds: the LeFort I segment lies a few mm from the
    zygoma and the pterygoid plates, and the tissue between them was crushed to det F 0.44
    by a 2 mm advance of headsq's jaws at coarse)."""
    from scipy.spatial import cKDTree

    held = np.zeros(facets.max() + 1, dtype=bool)
    held[facets[np.isin(tags, DIRICHLET_TAGS)]] = True
    moving = np.isin(tags, segment_tags)
    tags[moving & held[facets].any(axis=1)] = FREE_BONE
    for a, b in ((np.isin(tags, segment_tags), np.isin(tags, DIRICHLET_TAGS)),
                 (tags == FIXED, np.isin(tags, segment_tags))):
        if a.any() and b.any():   # vertex to vertex: facets are larger than the gap
            tree = cKDTree(points[np.unique(facets[b])])
            d, _ = tree.query(points[facets[a]].reshape(-1, 3), distance_upper_bound=gap_mm)
            near = np.isfinite(d).reshape(-1, 3).any(axis=1)
            tags[np.flatnonzero(a)[near]] = FREE_BONE


def _held_faces(lo, hi, free):
    """(axis, coordinate) of the crop faces that are held."""
    out = []
    for axis in range(3):
        for side, value in (("-", lo[axis]), ("+", hi[axis])):
            if f"{side}{'xyz'[axis]}" not in free:
                out.append((axis, value))
    return out


def ct_anatomy(ct_path, scene_file, resolution: str = DEFAULT_RESOLUTION, labelmap: bool = False,
               landmarks=None):
    """(Anatomy, info): `build`, from the cache when the same input and options were meshed
    before (info then has ``cached: True`` and the original timings). ``landmarks``: a file
    (`meshes.markups.read_landmark_file`) whose points replace or add to the built ones."""
    from meshes.external import attach_landmarks, read_occlusion

    ct_path, scene_file = Path(ct_path), Path(scene_file)
    spec = parse_scene_file(scene_file)[0]   # its planes and frame before the CT
    if not ct_path.exists():
        raise MeshError(f"{ct_path} does not exist")
    key = hashlib.sha1(json.dumps([_code_digest(), _digest(ct_path), spec, resolution,
                                   labelmap], sort_keys=True).encode())
    path = cache_dir() / f"ct-{ct_path.stem}-{resolution}-{key.hexdigest()[:12]}.npz"
    info_path = path.with_suffix(".json")
    anatomy = None
    if path.exists() and info_path.exists():
        try:
            anatomy, info = Anatomy.load(path), json.loads(info_path.read_text())
            info["cached"] = True
        except (MeshError, OSError, json.JSONDecodeError):
            log.warning("cached CT scene %s is unreadable; rebuilding", path)
            anatomy = None
    if anatomy is None:
        anatomy, info = build(ct_path, scene_file, resolution, labelmap)
        anatomy.save(path)
        # a unique part file: two processes building the same scene (parallel test
        # workers, two users' runs) must not rename each other's
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".json.part")
        with os.fdopen(fd, "w") as fh:
            fh.write(json.dumps(info))
        os.replace(tmp, info_path)
        info["cached"] = False
    anatomy.occlusion = read_occlusion(spec.get("occlusion"), scene_file)
    if landmarks is not None:
        from meshes.markups import read_landmark_file

        tol = max(float(np.linalg.norm(info["voxel_mm"])), 0.5)
        attach_landmarks(anatomy, read_landmark_file(landmarks), tol)
    return anatomy, info
