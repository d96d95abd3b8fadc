"""Real anatomy from files.

Two paths, both ending in a validated `Anatomy`:

1. ``load_tet_mesh(path)``: a tetrahedral mesh in any meshio format with a JSON sidecar
   (``path + ".json"`` by default)::

       {"facet_data": "tag",                     # name of the triangle cell-data array
        "roles": {"skin": 1, "fixed": 2, "free_bone": 3, "rim": 4},   # file values
        "segments": {"mandible": 11, "maxilla_L": 12, "maxilla_R": 13},
        "teeth": {"mandible": 31},               # optional: a segment's facets where the
                                                 # tissue slides (`meshes.teeth`)
        "contact": "sliding",                    # optional: or "glued", the default of
                                                 # scenes on this mesh
        "tissue_data": ["skin", "fat", "muscle"], # optional: the tetra cell-data arrays of
                                                 # each cell's tissue fractions
                                                 # (`meshes.tissue.TISSUES`, rows sum to 1)
        "material": "tissues",                   # optional: or "homogeneous" (the default)
        "pivots": {"mandible": [0, 55, -60]},     # optional, mm; default segment centroid
        "occlusion": [[4x4]] or "occlusion.tfm", # optional: the final occlusion, the
                                                 # mandible's motion relative to the maxilla
        "head_frame": [[4x4]],                   # optional: head frame -> this file's frame
                                                 # (`meshes.frame`); default the identity;
                                                 # with "head_frame_sources" and
                                                 # "head_frame_points" (read back) and
                                                 # "head_tilt_deg" (written, not read)
        "ct_thresholds": {"skin_hu": -400, "bone_hu": 226},  # optional: a CT scene's
                                                 # segmentation (`inverse.postop`)
        "ct_voxel_mm": [0.96, 0.96, 1.5],        # optional: the voxels the mesh was made
                                                 # from (`meshes.landmarks.staircase_mm`)
        "landmarks": {"Pg": [0, 101.7, -66], "Li": {"facet": [i, j, k], "weights": [a, b, c]}}}

   A landmark given as a point is projected onto the nearest skin facet; it must lie within
   ``LANDMARK_TOL_MM`` of the skin.

2. ``tetrahedralise(skin_file, bone_file, regions, landmarks, h)``: two closed triangulated
   surfaces (STL/OBJ/PLY/...; skin outside, bone inside) are meshed into tets with gmsh, keeping
   the surface triangles. Bone triangles get roles from ``regions``: an ordered list of
   ``{"role": name, "box": [[x0, y0, z0], [x1, y1, z1]]}``; the first box containing a triangle's
   midpoint wins; unmatched bone triangles are fixed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from meshes.anatomy import (
    FIXED,
    FREE_BONE,
    RIM,
    SEGMENT_TAG0,
    SKIN,
    Anatomy,
    Landmark,
    boundary_facets,
    segment_tags,
)
from meshes.errors import MeshError
from meshes.tissue import TISSUES

LANDMARK_TOL_MM = 0.5
ROLE_TAGS = {"skin": SKIN, "fixed": FIXED, "free_bone": FREE_BONE, "rim": RIM}


def _read(path):
    import meshio

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist or is not a file")
    try:
        return meshio.read(path)
    except (Exception, SystemExit) as e:  # meshio raises many types, even SystemExit
        raise MeshError(f"cannot read mesh {path}: {type(e).__name__}: {e}") from None


def closest_point_on_triangles(points, tris, q):
    """Nearest point to q (3,) on triangles ``tris`` (T, 3) over ``points`` (N, 3).

    Projects q on each triangle's plane and clamps the barycentric coordinates into the
    triangle (exact when the projection falls inside, which is the case for points on the
    surface). Returns (triangle index, barycentric weights (3,), distance mm).
    """
    a, b, c = (points[tris[:, i]] for i in range(3))
    e1, e2, r = b - a, c - a, q - a
    d11, d12, d22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    r1, r2 = np.einsum("ij,ij->i", r, e1), np.einsum("ij,ij->i", r, e2)
    den = d11 * d22 - d12 ** 2
    ok = den > 0
    den = np.where(ok, den, 1.0)
    v, w = (d22 * r1 - d12 * r2) / den, (d11 * r2 - d12 * r1) / den
    bary = np.clip(np.stack([1 - v - w, v, w], axis=1), 0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    proj = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    dist = np.where(ok, np.linalg.norm(proj - q, axis=1), np.inf)
    i = int(np.argmin(dist))
    return i, bary[i], float(dist[i])


def project_landmarks(spec: dict, points, facets, tags, tol: float = LANDMARK_TOL_MM) -> dict:
    """Landmarks {name: `Landmark`} from ``{name: [x, y, z] | {"facet", "weights"}}``: a point
    goes to the nearest skin facet and must lie within ``tol`` mm of the skin."""
    skin = np.flatnonzero(tags == SKIN)
    out = {}
    for name, val in spec.items():
        if isinstance(val, dict):
            out[name] = Landmark(np.asarray(val["facet"], dtype=np.int64),
                                 np.asarray(val["weights"], dtype=float))
            continue
        q = np.asarray(val, dtype=float)
        if q.shape != (3,) or not np.all(np.isfinite(q)):
            raise MeshError(f"landmark {name!r}: expected a finite point [x, y, z], got {val}")
        i, w, d = closest_point_on_triangles(points, facets[skin], q)
        if d > tol:
            raise MeshError(f"landmark {name!r} at {q.tolist()} is off the skin: the nearest "
                            f"skin point is {d:.2f} mm away (tolerance {tol:g} mm)")
        out[name] = Landmark(facets[skin[i]], w)
    return out


def attach_landmarks(anatomy: Anatomy, spec: dict, tol: float = LANDMARK_TOL_MM) -> Anatomy:
    """Add (or replace) landmarks of ``anatomy`` from points (`project_landmarks`)."""
    anatomy.landmarks.update(project_landmarks(spec, anatomy.points, anatomy.facets,
                                               anatomy.facet_tags, tol))
    return anatomy.validate()


def read_occlusion(value, sidecar: Path):
    """A scene file's occlusion: None, a 4×4, or a JSON/ITK file relative to the file."""
    from meshes.transforms import read_transform

    if value is None:
        return None
    if isinstance(value, str):
        value = sidecar.parent / value
    return read_transform(value, f"the occlusion in {sidecar}")


def _head_frame(spec: dict, sidecar: Path):
    from meshes.frame import HeadFrame

    try:
        return HeadFrame.from_report(spec)
    except MeshError as e:
        raise MeshError(f"{sidecar}: {e}") from None


def load_tet_mesh(path, sidecar=None) -> Anatomy:
    """A tetrahedral mesh (meshio format) with a JSON sidecar naming tags and landmarks."""
    mesh = _read(path)
    sidecar = Path(sidecar) if sidecar else Path(str(path) + ".json")
    try:
        spec = json.loads(sidecar.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise MeshError(f"cannot read the JSON sidecar {sidecar}: {e}") from None
    tets = [c.data for c in mesh.cells if c.type == "tetra"]
    if not tets:
        raise MeshError(f"{path} holds no tetrahedra (cell types: "
                        f"{[c.type for c in mesh.cells]}); only tetrahedral meshes are supported")
    key = spec.get("facet_data", "tag")
    tris, vals = [], []
    for i, c in enumerate(mesh.cells):
        if c.type == "triangle":
            if key not in mesh.cell_data:
                raise MeshError(f"{path}: no triangle cell data {key!r} holding facet tags")
            tris.append(c.data)
            vals.append(np.asarray(mesh.cell_data[key][i]).reshape(-1))
    if not tris:
        raise MeshError(f"{path} has no tagged triangles: skin, fixed bone and segments "
                        "must be marked")
    file_tags = np.concatenate(vals)
    tags = np.zeros(len(file_tags), dtype=np.int32)
    segments = {}
    for role, value in spec.get("roles", {}).items():
        if role not in ROLE_TAGS:
            raise MeshError(f"unknown role {role!r} in {sidecar}; roles: {list(ROLE_TAGS)}")
        tags[file_tags == value] = ROLE_TAGS[role]
    for j, (name, value) in enumerate(spec.get("segments", {}).items()):
        segments[name] = SEGMENT_TAG0 + j
        tags[file_tags == value] = SEGMENT_TAG0 + j
    for name, value in spec.get("teeth", {}).items():
        if name not in segments:
            raise MeshError(f"teeth of {name!r} in {sidecar}, which is not a segment "
                            f"({list(segments)})")
        tags[file_tags == value] = segment_tags(segments[name])[1]
    facets = np.concatenate(tris).astype(np.int64)
    keep = tags != 0
    facets, tags = facets[keep], tags[keep]
    points = np.asarray(mesh.points, dtype=float)
    anatomy = Anatomy(points, np.concatenate(tets).astype(np.int64), facets, tags, segments,
                      {k: np.asarray(v, float) for k, v in spec.get("pivots", {}).items()},
                      {}, name=Path(path).name,
                      occlusion=read_occlusion(spec.get("occlusion"), sidecar),
                      head_frame=_head_frame(spec, sidecar),
                      contact=spec.get("contact", "sliding"),
                      tissues=_tissues(mesh, spec.get("tissue_data"), path),
                      material=spec.get("material", "homogeneous"),
                      thresholds=spec.get("ct_thresholds"),
                      voxel_mm=spec.get("ct_voxel_mm"))
    anatomy.validate()
    anatomy.landmarks = project_landmarks(spec.get("landmarks", {}), points, facets, tags)
    return anatomy.validate_landmarks()


def _tissues(mesh, names, path):
    """(M, 3) tissue fractions from the tetra cell-data arrays ``names``, or None."""
    if names is None:
        return None
    if not isinstance(names, list) or len(names) != len(TISSUES):
        raise MeshError(f"{path}: tissue_data must name {len(TISSUES)} cell-data arrays, "
                        f"the fractions of {list(TISSUES)}")
    cols = []
    for name in names:
        if name not in mesh.cell_data:
            raise MeshError(f"{path}: no cell data {name!r} (tissue_data)")
        cols.append(np.concatenate([np.asarray(a, float).reshape(-1) for a, c in
                                    zip(mesh.cell_data[name], mesh.cells) if c.type == "tetra"]))
    return np.stack(cols, axis=1)


def tetrahedralise(skin_file, bone_file, regions: list, landmarks: dict,
                   h: float | None = None) -> Anatomy:
    """Mesh the volume between a closed skin surface and a closed bone surface inside it."""
    surfaces = []
    for f in (skin_file, bone_file):
        m = _read(f)
        tri = [c.data for c in m.cells if c.type == "triangle"]
        if not tri:
            raise MeshError(f"{f} holds no triangles")
        surfaces.append((np.asarray(m.points, float), np.concatenate(tri).astype(np.int64)))
    points, cells = _gmsh_between(surfaces, h)
    facets = boundary_facets(cells)
    n_skin = len(surfaces[0][0])
    tags = np.where(facets.max(axis=1) < n_skin, SKIN, FIXED).astype(np.int32)
    mid = points[facets].mean(axis=1)
    segments = {}
    bone = np.flatnonzero(tags == FIXED)
    assigned = np.zeros(len(bone), dtype=bool)
    for r in regions:
        role = r["role"]
        if role in ROLE_TAGS:
            tag = ROLE_TAGS[role]
        else:
            tag = segments.setdefault(role, SEGMENT_TAG0 + len(segments))
        lo, hi = np.asarray(r["box"], float)
        inside = np.all((mid[bone] >= lo) & (mid[bone] <= hi), axis=1) & ~assigned
        tags[bone[inside]] = tag
        assigned |= inside
    anatomy = Anatomy(points, cells, facets, tags, segments, {}, {}, name=Path(skin_file).name)
    anatomy.validate()
    anatomy.landmarks = project_landmarks(landmarks, points, facets, tags)
    return anatomy.validate_landmarks()


def _gmsh_between(surfaces, h):
    """Tets between discrete surfaces [(points, tris) outer, (points, tris) inner]; the
    surface triangles are kept as they are. Returns points (outer first) and cells."""
    from meshes._gmsh import gmsh_session

    try:
        with gmsh_session() as gmsh:
            gmsh.option.setNumber("General.Terminal", 0)
            offset, loops, all_pts = 0, [], []
            for k, (pts, tris) in enumerate(surfaces, start=1):
                gmsh.model.addDiscreteEntity(2, k)
                tags = np.arange(1, len(pts) + 1) + offset
                gmsh.model.mesh.addNodes(2, k, tags, pts.ravel())
                gmsh.model.mesh.addElementsByType(k, 2, [], (tris + 1 + offset).ravel())
                loops.append(gmsh.model.geo.addSurfaceLoop([k]))
                offset += len(pts)
                all_pts.append(pts)
            gmsh.model.geo.addVolume(loops)
            gmsh.model.geo.synchronize()
            if h:
                gmsh.option.setNumber("Mesh.MeshSizeMax", h)
            gmsh.model.mesh.generate(3)
            ntags, x, _ = gmsh.model.mesh.getNodes()
            _, conn = gmsh.model.mesh.getElementsByType(4)
    except Exception as e:
        raise MeshError(f"gmsh could not mesh the volume between the surfaces: {e}") from None

    index = np.zeros(int(ntags.max()) + 1, dtype=np.int64)
    index[ntags.astype(np.int64)] = np.arange(len(ntags))
    order = np.argsort(ntags)  # keep input surface vertex numbering first
    points = x.reshape(-1, 3)[order]
    index[ntags[order].astype(np.int64)] = np.arange(len(ntags))
    if len(conn) == 0:
        raise MeshError("gmsh produced no tetrahedra between the surfaces")
    return points, index[conn.astype(np.int64)].reshape(-1, 4)


def write_tet_mesh(anatomy: Anatomy, path) -> list:
    """Write ``anatomy`` as a tet mesh (any meshio format by suffix; ``.vtu`` opens in
    ParaView) with its JSON sidecar ``path + ".json"``, which `load_tet_mesh` reads back
    exactly (tags as they are, landmarks as facet and weights). Returns the two paths."""
    import meshio

    path = Path(path)
    data = {"tag": [np.zeros(anatomy.n_cells, dtype=np.int32),
                    anatomy.facet_tags.astype(np.int32)]}
    if anatomy.tissues is not None:   # per tet; the triangles' 0 is no fraction
        data.update({name: [anatomy.tissues[:, k], np.zeros(len(anatomy.facets))]
                     for k, name in enumerate(TISSUES)})
    mesh = meshio.Mesh(anatomy.points, [("tetra", anatomy.cells), ("triangle", anatomy.facets)],
                       cell_data=data)
    mesh.write(path)
    sidecar = Path(str(path) + ".json")
    teeth = {n: segment_tags(t)[1] for n, t in anatomy.segments.items()
             if segment_tags(t)[1] in anatomy.teeth_tags}
    spec = {"facet_data": "tag", "roles": dict(ROLE_TAGS), "segments": anatomy.segments,
            "teeth": teeth, "contact": anatomy.contact, "material": anatomy.material,
            "pivots": {k: np.asarray(v).tolist() for k, v in anatomy.pivots.items()},
            "landmarks": {k: {"facet": np.asarray(v.facet).tolist(),
                              "weights": np.asarray(v.weights).tolist()}
                          for k, v in anatomy.landmarks.items()}}
    if anatomy.tissues is not None:
        spec["tissue_data"] = list(TISSUES)
    if anatomy.occlusion is not None:
        spec["occlusion"] = np.asarray(anatomy.occlusion).tolist()
    if anatomy.head_frame is not None:
        spec.update(anatomy.head_frame.report())
    if anatomy.thresholds is not None:
        spec["ct_thresholds"] = anatomy.thresholds
    if anatomy.voxel_mm is not None:
        spec["ct_voxel_mm"] = np.asarray(anatomy.voxel_mm).tolist()
    sidecar.write_text(json.dumps(spec, indent=1) + "\n")
    return [path, sidecar]
