"""The `Anatomy` dataclass: a tetrahedral soft-tissue mesh with tags, segments and landmarks.

Everything downstream (``fem``, ``inverse``) consumes an `Anatomy`. It is plain numpy data held
on one rank; ``fem.domain`` distributes it. Lengths are in mm, frame x = patient's left,
y = anterior, z = superior, mid-sagittal plane x = 0.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

from meshes.errors import MeshError
from meshes.frame import HeadFrame

#: Facet tag values of the boundary roles. Segment tags are ``SEGMENT_TAG0 + i``; the teeth
#: of a segment (its facets where the tissue may slide, `fem.equilibrium`) are tagged
#: ``segment tag + TEETH_OFFSET``.
SKIN, FIXED, FREE_BONE, RIM = 1, 2, 3, 4
SEGMENT_TAG0 = 11
TEETH_OFFSET = 20
ROLE_NAMES = {SKIN: "skin", FIXED: "fixed", FREE_BONE: "free_bone", RIM: "rim"}
#: An anatomy's default material (`fem.material`): per-cell tissues or the paper's single one.
MATERIALS = ("tissues", "homogeneous")
#: Facets held by a Dirichlet condition (u = 0).
DIRICHLET_TAGS = (FIXED, RIM)
#: Landmarks every built-in case provides (issue 3, DESIGN.md naming).
STANDARD_LANDMARKS = ("N", "Prn", "Sn", "Ls", "Li", "Pg", "Me", "T_L", "T_R")
#: Relative tolerance on tet volumes, against the mean volume, below which a cell is degenerate.
DEGENERATE_VOLUME_RTOL = 1e-10
#: Shape quality (`tet_quality`, 1 = regular) below which a valid cell is reported as a sliver.
#: The built-in meshes stay above 0.01.
SLIVER_QUALITY = 1e-3


@dataclasses.dataclass
class Landmark:
    """A point on the skin: a skin facet (3 vertex indices) and barycentric weights (3,)."""

    facet: np.ndarray
    weights: np.ndarray

    def position(self, points: np.ndarray) -> np.ndarray:
        """Position (3,) mm, given vertex positions ``points`` (N, 3)."""
        return self.weights @ points[self.facet]


@dataclasses.dataclass
class Anatomy:
    """A soft-tissue tet mesh between bone (inside) and skin (outside).

    Attributes:
        points: (N, 3) vertex positions, mm.
        cells: (M, 4) vertex indices of positively oriented tetrahedra.
        facets: (F, 3) vertex indices of tagged boundary facets.
        facet_tags: (F,) tag per facet: SKIN, FIXED, FREE_BONE, RIM, a segment tag or a
            segment's teeth tag (segment tag + `TEETH_OFFSET`).
        segments: segment name -> facet tag (e.g. ``{"mandible": 11}``); its teeth, if it
            has any, are tagged ``11 + TEETH_OFFSET``.
        pivots: segment name -> (3,) pivot of its rigid motions, mm.
        landmarks: landmark name -> `Landmark` on a skin facet.
        name: case name or source file, for reports.
        occlusion: optional (4, 4) motion of the mandible relative to the maxilla that
            brings the teeth into the final occlusion (`inverse.treatment`), scene frame.
        head_frame: optional `meshes.frame.HeadFrame` (head frame -> scene frame); None:
            the scene's frame is the head's (the synthetic heads).
        contact: how its tissue holds to its teeth unless a scene says otherwise,
            "sliding" or "glued" (`inverse.scene.Scene`; the synthetic heads: glued,
            docs/decisions.md).
        tissues: optional (M, 3) fraction of each cell that is skin, fat and lean tissue
            (`meshes.tissue.TISSUES`), rows summing to 1; None: unknown.
        material: its material unless a scene says otherwise, "tissues" (needs
            ``tissues``) or "homogeneous" (the paper's single material).
        thresholds: a CT scene's segmentation, ``{"skin_hu": HU, "bone_hu": HU}`` (None
            for a label map's), which a post-operative CT of it is read with
            (`inverse.postop`); None for other scenes.
        voxel_mm: (3,) the voxel size (mm) of the CT or label map the mesh was made from:
            its surfaces follow the voxels' staircase (`meshes.landmarks.staircase_mm`);
            None for a mesh not made from voxels.
    """

    points: np.ndarray
    cells: np.ndarray
    facets: np.ndarray
    facet_tags: np.ndarray
    segments: dict[str, int]
    pivots: dict[str, np.ndarray]
    landmarks: dict[str, Landmark]
    name: str = "anatomy"
    occlusion: np.ndarray | None = None
    head_frame: HeadFrame | None = None
    contact: str = "sliding"
    tissues: np.ndarray | None = None
    material: str = "homogeneous"
    thresholds: dict | None = None
    voxel_mm: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def n_cells(self) -> int:
        return len(self.cells)

    def landmark_positions(self, names=None) -> dict[str, np.ndarray]:
        """Rest positions {name: (3,)} mm of the named landmarks (all if None)."""
        names = list(self.landmarks) if names is None else names
        return {n: self.landmarks[n].position(self.points) for n in names}

    def segment_vertices(self, name: str) -> np.ndarray:
        """Sorted vertex indices on the facets of segment ``name``, its teeth included."""
        return np.unique(self.facets[np.isin(self.facet_tags,
                                             segment_tags(self.segments[name]))])

    @property
    def teeth_tags(self) -> list[int]:
        """The teeth tags of the segments that have teeth."""
        return [t + TEETH_OFFSET for t in self.segments.values()
                if np.any(self.facet_tags == t + TEETH_OFFSET)]

    # ------------------------------------------------------------------ validation
    def validate(self) -> "Anatomy":
        """Check geometry, tags and landmarks; orient cells positively. Raises `MeshError`."""
        p, c = np.asarray(self.points, float), np.asarray(self.cells)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
            raise MeshError(f"points must be an (N>=4, 3) array, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise MeshError(f"{np.sum(~np.isfinite(p).all(1))} vertices have NaN/inf coordinates")
        if c.ndim != 2 or c.shape[1] != 4 or len(c) == 0:
            raise MeshError(f"cells must be tetrahedra, an (M, 4) array; got shape {c.shape}")
        if c.min() < 0 or c.max() >= len(p):
            raise MeshError("cells index vertices that do not exist")
        if np.any(np.sort(c, axis=1)[:, 1:] == np.sort(c, axis=1)[:, :-1]):
            raise MeshError("some cells repeat a vertex")
        if len(np.unique(np.sort(c, axis=1), axis=0)) != len(c):
            raise MeshError("the mesh has duplicate cells")
        vol = signed_volumes(p, c)
        tiny = np.abs(vol) <= DEGENERATE_VOLUME_RTOL * np.abs(vol).mean()
        if tiny.any():
            raise MeshError(f"{tiny.sum()} degenerate (zero-volume) tetrahedra, e.g. cell "
                            f"{np.flatnonzero(tiny)[0]}; repair or remesh the input")
        neg = vol < 0
        if neg.any() and not neg.all():
            raise MeshError(f"{min(neg.sum(), (~neg).sum())} of {len(c)} tetrahedra are inverted "
                            f"relative to the others, e.g. cell "
                            f"{np.flatnonzero(neg if neg.sum() < len(c) / 2 else ~neg)[0]}")
        if neg.all():
            c = c[:, [0, 2, 1, 3]]
        parts = np.bincount(facet_components(c))
        if len(parts) > 1:
            raise MeshError(f"the mesh falls apart into {len(parts)} pieces joined only at edges "
                            f"or vertices (the largest has {parts.max()} of {len(c)} cells): "
                            "such hinges are mechanisms, and dolfinx cannot ghost them; keep the "
                            "largest piece")
        q = tet_quality(p, c)
        if q.min() < SLIVER_QUALITY:
            warnings.warn(f"{np.sum(q < SLIVER_QUALITY)} sliver tetrahedra (shape quality < "
                          f"{SLIVER_QUALITY:g}; worst {q.min():.1e} at cell {q.argmin()}): K is "
                          "ill-conditioned there and Newton may need shifts; remesh if the "
                          "solve fails", stacklevel=2)
        self.points, self.cells = p, c.astype(np.int64)
        self._validate_tags()
        self.validate_landmarks()
        self._validate_tissues()
        if self.voxel_mm is not None:
            try:
                v = np.asarray(self.voxel_mm, float)
            except (TypeError, ValueError):
                v = np.empty(0)
            if v.shape != (3,) or not np.all(np.isfinite(v) & (v > 0)):
                raise MeshError(f"voxel_mm must be 3 positive sizes (mm), got {self.voxel_mm!r}")
            self.voxel_mm = v
        return self

    def _validate_tags(self):
        f = np.asarray(self.facets, dtype=np.int64)
        t = np.asarray(self.facet_tags, dtype=np.int32)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) != len(t):
            raise MeshError(f"facets must be (F, 3) with one tag each; got {f.shape}, {t.shape}")
        n = len(self.points)
        off = np.flatnonzero(~np.isin(_facet_keys(np.sort(f, axis=1), n),
                                      _facet_keys(boundary_facets(self.cells), n)))
        if len(off):
            raise MeshError(f"{len(off)} tagged facets are not on the mesh boundary, "
                            f"e.g. vertices {f[off[0]].tolist()}")
        need = {"skin": SKIN, "fixed bone (Dirichlet)": FIXED}
        for what, tag in need.items():
            if not np.any(t == tag):
                raise MeshError(f"no facets tagged {what} (tag {tag}); the mesh needs tags for "
                                "skin, fixed bone and at least one active segment")
        if not self.segments:
            raise MeshError("no active bone segment is defined")
        if self.contact not in ("sliding", "glued"):
            raise MeshError(f"contact must be 'sliding' or 'glued', got {self.contact!r}")
        known = set(ROLE_NAMES) | {x for tag in self.segments.values()
                                   for x in segment_tags(tag)}
        unknown = sorted(set(np.unique(t).tolist()) - known)
        if unknown:
            raise MeshError(f"facet tag(s) {unknown} are neither a role {sorted(ROLE_NAMES)} "
                            "nor a segment's (or its teeth's)")
        for name, tag in self.segments.items():
            if not np.any(np.isin(t, segment_tags(tag))):
                raise MeshError(f"segment {name!r} (tag {tag}) has no facets")
            if name not in self.pivots:
                self.pivots[name] = self.points[self.segment_vertices(name)].mean(axis=0)
        fixed = np.unique(f[np.isin(t, DIRICHLET_TAGS)])
        for name in self.segments:
            both = np.intersect1d(fixed, self.segment_vertices(name))
            if len(both):
                raise MeshError(f"segment {name!r} shares {len(both)} vertices with fixed bone; "
                                "leave a free band of bone between them")
        self.facets, self.facet_tags = f, t

    def validate_landmarks(self) -> "Anatomy":
        """Check the landmarks alone (each on a skin facet, its weights barycentric), where
        only they changed since `validate` (which takes 0.5 s on Cranium's 184 k cells).
        Raises `MeshError`."""
        skin = {tuple(r) for r in np.sort(self.facets[self.facet_tags == SKIN], axis=1)}
        for name, lm in self.landmarks.items():
            w = np.asarray(lm.weights, float)
            if w.shape != (3,) or not np.all(np.isfinite(w)) or np.any(w < -1e-9) \
                    or abs(w.sum() - 1) > 1e-9:
                raise MeshError(f"landmark {name!r}: barycentric weights {w} must be >= 0, sum 1")
            if tuple(np.sort(lm.facet)) not in skin:
                raise MeshError(f"landmark {name!r} is off the skin: its facet "
                                f"{np.asarray(lm.facet).tolist()} is not a skin facet")
        return self

    def _validate_tissues(self):
        if self.material not in MATERIALS:
            raise MeshError(f"material must be one of {list(MATERIALS)}, got {self.material!r}")
        if self.tissues is None:
            if self.material == "tissues":
                raise MeshError("material 'tissues' needs the cells' tissue fractions")
            return
        f = np.asarray(self.tissues, dtype=float)
        if f.shape != (self.n_cells, 3) or not np.all(np.isfinite(f)) or f.min() < 0 \
                or np.abs(f.sum(axis=1) - 1).max() > 1e-6:
            raise MeshError(f"tissue fractions must be ({self.n_cells}, 3), >= 0, each row "
                            f"summing to 1; got shape {f.shape}")
        self.tissues = f

    # ------------------------------------------------------------------ storage
    def save(self, path: str | Path) -> None:
        """Write to ``path`` (.npz) atomically."""
        meta = {"segments": self.segments, "name": self.name,
                "occlusion": None if self.occlusion is None else
                np.asarray(self.occlusion).tolist(),
                "head_frame": None if self.head_frame is None else self.head_frame.report(),
                "contact": self.contact, "material": self.material,
                "thresholds": self.thresholds,
                "voxel_mm": None if self.voxel_mm is None else np.asarray(self.voxel_mm).tolist(),
                "pivots": {k: np.asarray(v).tolist() for k, v in self.pivots.items()},
                "landmarks": {k: [np.asarray(v.facet).tolist(), np.asarray(v.weights).tolist()]
                              for k, v in self.landmarks.items()}}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.part")
        with os.fdopen(fd, "wb") as fh:
            extra = {} if self.tissues is None else {"tissues": self.tissues}
            np.savez(fh, points=self.points, cells=self.cells, facets=self.facets,
                     facet_tags=self.facet_tags, meta=json.dumps(meta), **extra)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> "Anatomy":
        """Read an anatomy written by `save`; raises `MeshError` if unreadable."""
        try:
            with np.load(path) as d:
                meta = json.loads(str(d["meta"]))
                return cls(points=d["points"], cells=d["cells"], facets=d["facets"],
                           facet_tags=d["facet_tags"], segments=meta["segments"],
                           pivots={k: np.array(v) for k, v in meta["pivots"].items()},
                           landmarks={k: Landmark(np.array(f), np.array(w))
                                      for k, (f, w) in meta["landmarks"].items()},
                           name=meta["name"],
                           occlusion=None if meta.get("occlusion") is None else
                           np.array(meta["occlusion"], dtype=float),
                           head_frame=HeadFrame.from_report(meta.get("head_frame")),
                           contact=meta.get("contact", "sliding"),
                           tissues=d["tissues"] if "tissues" in d else None,
                           material=meta.get("material", "homogeneous"),
                           thresholds=meta.get("thresholds"),
                           voxel_mm=meta.get("voxel_mm"))
        except (OSError, KeyError, ValueError) as e:
            raise MeshError(f"cannot read anatomy file {path}: {e}") from e


def segment_tags(tag: int) -> tuple[int, int]:
    """The facet tags of a segment whose tag is ``tag``: (its bone, its teeth)."""
    return tag, tag + TEETH_OFFSET


def signed_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed volumes (M,) mm^3 of tetrahedra ``cells`` (M, 4) over ``points`` (N, 3)."""
    a = points[cells[:, 1:]] - points[cells[:, :1]]
    return np.linalg.det(a) / 6.0


def tet_quality(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Shape quality (M,) of tetrahedra: 12 (3|V|)^(2/3) / Σ edge², 1 for a regular tet,
    -> 0 for slivers and flat cells."""
    x = points[cells]
    edges = [x[:, i] - x[:, j] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]
    l2 = sum(np.einsum("ij,ij->i", e, e) for e in edges)
    return 12.0 * (3.0 * np.abs(signed_volumes(points, cells))) ** (2.0 / 3.0) / l2


#: Local vertices of a tetrahedron's four faces, face i opposite vertex i.
TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
#: Vertex indices up to this fit three to an int64 facet key (`_facet_keys`).
MAX_VERTICES = 2 ** 21 - 1


def _facet_keys(triples: np.ndarray, n: int) -> np.ndarray:
    """One int64 (K,) per sorted vertex triple (K, 3) of a mesh with n vertices."""
    if n > MAX_VERTICES:
        raise MeshError(f"{n} vertices: at most {MAX_VERTICES} are supported")
    t = np.asarray(triples, dtype=np.int64)
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def facet_components(cells: np.ndarray) -> np.ndarray:
    """Component label (M,) of each cell, cells being connected through shared facets (a
    cluster joined to the rest only at an edge or a vertex is a component of its own)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = np.sort(cells[:, TET_FACES].reshape(-1, 3), axis=1)
    _, face = np.unique(_facet_keys(faces, int(cells.max()) + 1), return_inverse=True)
    cell = np.repeat(np.arange(len(cells)), 4)
    inc = sp.csr_matrix((np.ones(len(face)), (cell, face)), shape=(len(cells), face.max() + 1))
    return connected_components(inc @ inc.T, directed=False)[1]


def boundary_facets(cells: np.ndarray) -> np.ndarray:
    """Sorted vertex triples (B, 3) of facets that belong to exactly one tetrahedron, in
    lexicographic order."""
    faces = np.sort(cells[:, TET_FACES].reshape(-1, 3), axis=1)
    n = int(cells.max()) + 1
    uniq, count = np.unique(_facet_keys(faces, n), return_counts=True)
    keys = uniq[count == 1]
    return np.stack([keys // (n * n), keys // n % n, keys % n], axis=1)


def intersect_rays(points: np.ndarray, tris: np.ndarray, origin, direction):
    """Farthest hit of a ray with triangles (Moller-Trumbore).

    Args:
        points: (N, 3) vertices; tris: (T, 3) triangle vertex indices.
        origin, direction: (3,) ray start and direction.

    Returns:
        (triangle index, barycentric weights (3,)) of the hit farthest along the ray,
        or None when the ray misses.
    """
    o, d = np.asarray(origin, float), np.asarray(direction, float)
    v0, v1, v2 = (points[tris[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    pv = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - v0
    u = np.einsum("ij,ij->i", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = (qv @ d) * inv
    t = np.einsum("ij,ij->i", e2, qv) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not hit.any():
        return None
    i = np.flatnonzero(hit)[np.argmax(t[hit])]
    return int(i), np.array([1 - u[i] - v[i], u[i], v[i]])
