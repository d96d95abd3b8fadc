"""Triangle surfaces: face scans read from files, exact closest points.

Serves the validation against a patient's outcome (`inverse.validation`,
`meshes.registration`) and the tissues' skin depth (`meshes.tissue`). A surface is points
(N, 3) mm and triangles (T, 3), oriented outward (a face scan's camera side, the skin's air
side).
"""

from __future__ import annotations

import numpy as np

from meshes.errors import MeshError

#: Face-scan formats (3dMD cameras and photogrammetry write these), read by meshio.
SCAN_SUFFIXES = (".stl", ".obj", ".ply")
#: Candidate triangles per query point: the nearest by centroid (`closest_points`).
CANDIDATES = 8


def read_surface(path) -> tuple:
    """(points (N, 3), triangles (T, 3)) of a surface file (`SCAN_SUFFIXES`), mm. `MeshError`
    with one line for an unreadable file or one without triangles."""
    import meshio

    path = str(path)
    if not path.lower().endswith(SCAN_SUFFIXES):
        raise MeshError(f"{path}: a face scan must be one of {', '.join(SCAN_SUFFIXES)}")
    try:
        mesh = meshio.read(path)
    except Exception as e:   # meshio raises many kinds for a bad file
        raise MeshError(f"cannot read the surface {path}: {str(e).splitlines()[0]}") from None
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    tris = np.concatenate(tris) if tris else np.empty((0, 3), dtype=np.int64)
    if len(tris) == 0:
        raise MeshError(f"{path} has no triangles: a face scan needs its faces, not points "
                        "only")
    points = np.asarray(mesh.points, float).reshape(len(mesh.points), -1)[:, :3]
    if not np.all(np.isfinite(points)):
        raise MeshError(f"{path} has points that are not finite numbers")
    return points, tris.astype(np.int64)


def write_surface(path, points: np.ndarray, tris: np.ndarray, point_data=None) -> None:
    """A surface to ``path`` (any meshio format: .ply, .stl, .xdmf ...)."""
    import meshio

    meshio.write(str(path), meshio.Mesh(points, [("triangle", np.asarray(tris, np.int32))],
                                        point_data=point_data or {}))   # PLY: 32-bit


def triangle_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Unit normals (T, 3) of the triangles, by their winding."""
    n = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) at the vertices: the area-weighted mean of their triangles'."""
    n = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])
    corner = tris.ravel()   # bincount, not np.add.at (1.5 s of a CT validation's 28 s)
    out = np.stack([np.bincount(corner, np.repeat(n[:, d], 3), len(points)) for d in range(3)],
                   axis=1)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def closest_on_triangles(p, a, b, c) -> np.ndarray:
    """The closest points (..., 3) to points p on triangles (a, b, c), all (..., 3): the
    projection where it falls inside the triangle, else the nearest point of its edges."""
    n = np.cross(b - a, c - a)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    h = np.einsum("...i,...i->...", p - a, n)
    q = p - h[..., None] * n
    inside = np.ones(h.shape, dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("...i,...i->...", np.cross(v - u, q - u), n) >= 0
    best, dist = q, np.full(h.shape, np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        d = v - u
        t = np.einsum("...i,...i->...", p - u, d) / np.maximum(
            np.einsum("...i,...i->...", d, d), 1e-300)
        e = u + np.clip(t, 0.0, 1.0)[..., None] * d
        de = np.linalg.norm(p - e, axis=-1)
        closer = ~inside & (de < dist)
        best = np.where(closer[..., None], e, best)
        dist = np.where(closer, de, dist)
    return best


def normals_at(points: np.ndarray, tris: np.ndarray, tri: np.ndarray,
               q: np.ndarray) -> np.ndarray:
    """Unit normals (K, 3) of the surface at points q (K, 3) on its triangles ``tri`` (K,):
    the vertex normals (`vertex_normals`) interpolated at q's barycentric coordinates, a
    field continuous across edges (a point on an edge has one normal, whichever triangle
    holds it)."""
    vn = vertex_normals(points, tris)[tris[tri]]   # (K, 3 vertices, 3)
    out = np.einsum("kv,kvi->ki", barycentric(points, tris, tri, q), vn)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def barycentric(points: np.ndarray, tris: np.ndarray, tri: np.ndarray,
                q: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (K, 3), clipped to [0, 1], of points q (K, 3) on the
    triangles ``tri`` (K,) of the surface (``points``, ``tris``)."""
    a, b, c = (points[tris[tri, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    area = np.maximum(np.einsum("ij,ij->i", n, n), 1e-300)
    w = np.stack([np.einsum("ij,ij->i", np.cross(c - b, q - b), n),
                  np.einsum("ij,ij->i", np.cross(a - c, q - c), n),
                  np.einsum("ij,ij->i", np.cross(b - a, q - a), n)], axis=1) / area[:, None]
    return np.clip(w, 0.0, 1.0)


class SurfaceQuery:
    """A triangle surface (``points`` (P, 3), ``tris`` (T, 3)) with its search trees built
    once, for queries repeated against it (an ICP's every iteration): the closest points
    (`closest`) and whether they lie on its open rim (`on_rim`). Built per call, the rim's
    edges (a sort of every edge) took 6.5 s of Cranium's 122 ICP iterations onto a face
    scan at paper, the centroids' tree 1.5 s."""

    def __init__(self, points: np.ndarray, tris: np.ndarray):
        from scipy.spatial import cKDTree

        self.points, self.tris = points, tris
        self._centroids = cKDTree(points[tris].mean(axis=1))
        self._rim = None

    def closest(self, query: np.ndarray) -> tuple:
        """(distance (K,), closest point (K, 3), triangle (K,)) from each query (K, 3) to the
        surface, among the `CANDIDATES` triangles nearest by centroid (exact where the
        triangles are about as large as the distances between their centroids)."""
        points, tris = self.points, self.tris
        k = min(CANDIDATES, len(tris))
        _, cand = self._centroids.query(query, k=k)
        cand = np.asarray(cand).reshape(len(query), k)
        a, b, c = (points[tris[cand, i]] for i in range(3))
        q = closest_on_triangles(query[:, None, :], a, b, c)
        d = np.linalg.norm(q - query[:, None, :], axis=2)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(query))
        return d[rows, j], q[rows, j], cand[rows, j]

    def on_rim(self, q: np.ndarray, tol: float = 1e-6) -> np.ndarray:
        """Whether each closest point q (K, 3) lies on the surface's open rim (within
        ``tol`` mm): a query beyond what a cropped scan holds."""
        from scipy.spatial import cKDTree

        if self._rim is None:
            rim = boundary_edges(self.tris)
            u, v = self.points[rim[:, 0]], self.points[rim[:, 1]]
            length = float(np.linalg.norm(v - u, axis=1).max()) if len(rim) else 0.0
            self._rim = (u, v, length, cKDTree((u + v) / 2) if len(rim) else None)
        u, v, length, tree = self._rim
        out = np.zeros(len(q), dtype=bool)
        if tree is None:
            return out
        for i, cand in enumerate(tree.query_ball_point(q, length / 2 + tol)):
            if cand:
                d = v[cand] - u[cand]
                t = np.clip(np.einsum("ij,ij->i", q[i] - u[cand], d)
                            / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
                out[i] = np.linalg.norm(u[cand] + t[:, None] * d - q[i], axis=1).min() <= tol
        return out


def closest_points(query: np.ndarray, points: np.ndarray, tris: np.ndarray) -> tuple:
    """`SurfaceQuery.closest` on the surface (points, tris), once."""
    return SurfaceQuery(points, tris).closest(query)


def unique_edges(tris: np.ndarray, **unique) -> tuple:
    """(edges (E, 2) sorted, each (a, b) with a < b, in lexicographic order, then what
    ``np.unique``'s options ``unique`` ask for) of the triangles' edges ab, bc, ca (3T,
    in that order). One int64 key per edge: np.unique(axis=0) sorts rows as records, 10x
    slower."""
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    n = int(e.max()) + 1 if len(e) else 1
    out = np.unique(e[:, 0].astype(np.int64) * n + e[:, 1], **unique)
    keys, rest = (out[0], out[1:]) if isinstance(out, tuple) else (out, ())
    return (np.c_[keys // n, keys % n], *rest)


def boundary_edges(tris: np.ndarray) -> np.ndarray:
    """Edges (E, 2) that belong to one triangle only: the open rims of a surface."""
    uniq, count = unique_edges(tris, return_counts=True)
    return uniq[count == 1]


def apply(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points (K, 3) moved by the 4×4 T."""
    return x @ T[:3, :3].T + T[:3, 3]


def subdivide(points: np.ndarray, tris: np.ndarray) -> tuple:
    """(points, triangles): each triangle into four at its edges' midpoints (the same
    surface, other vertices and triangles)."""
    edges, inv = unique_edges(tris, return_inverse=True)
    a, b, c = tris.T
    ab, bc, ca = len(points) + inv.reshape(3, -1)   # the midpoints of edges ab, bc, ca
    return (np.vstack([points, points[edges].mean(axis=1)]),
            np.vstack([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]]))


def synthetic_scan(points: np.ndarray, tris: np.ndarray, noise_mm: float, misplace: np.ndarray,
                   keep=None, seed: int = 0) -> tuple:
    """(points, triangles) of a face scan made from a skin surface, as a camera would give it
    (tests and benchmarks of the validation): subdivided once (other vertices), noised along
    its normals (Gaussian, SD ``noise_mm``), cropped to the vertices where ``keep(points,
    triangles)`` (a callable giving (N,) bool; None: all), misplaced by the 4×4 ``misplace``."""
    pts, tris = subdivide(points, tris)
    rng = np.random.default_rng(seed)
    pts = pts + rng.normal(0.0, noise_mm, (len(pts), 1)) * vertex_normals(pts, tris)
    if keep is not None:
        tris = tris[keep(pts, tris)[tris].all(axis=1)]
    used = np.unique(tris)
    index = np.full(len(pts), -1)
    index[used] = np.arange(len(used))
    return apply(misplace, pts[used]), index[tris]

