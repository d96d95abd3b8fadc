"""Distribute an `Anatomy` over MPI ranks as a dolfinx mesh with facet tags and nodal maps.

`Domain` is what the solvers use: the mesh, facet tags, the Lagrange vector space (P1, or P2
for the element-order study), the rest coordinates of its nodes, and `PointOperator`, the
sparse map from nodal displacements to landmark points.

A node (dof block) is named by a pair of original vertex indices: ``(i, i)`` for vertex i,
``(i, j)``, i < j, for the midpoint of edge ij (P2).
"""

from __future__ import annotations

from mpi4py import MPI

import dataclasses

import dolfinx
import numpy as np
import ufl

from fem import compat
from meshes.anatomy import DIRICHLET_TAGS, Landmark
from meshes.errors import InputError


@dataclasses.dataclass
class Domain:
    """A distributed soft-tissue mesh.

    Attributes:
        mesh: dolfinx mesh (mm); facet_tags: MeshTags on facets (meshes.anatomy tag values).
        V: Lagrange vector space of degree ``degree`` (1 or 2); X: (n_local_nodes, 3) rest
        coordinates of V's dof blocks (mm), owned first, then ghosts. node_key:
        (n_local_nodes, 2) the vertex pair naming each dof block (module docstring).
        input_index: (n_local_nodes,) original vertex index of each dof block, -1 on edges.
        node_of_block: (n_local_nodes,) geometry node of each dof block, -1 on edges.
        segments, pivots, landmarks, name, n_vertices, n_cells, occlusion, head_frame,
        contact, material, thresholds, voxel_mm: as in `Anatomy`.
        tissues: (n_local_cells, 3) tissue fractions of the local cells (ghosts included,
            dolfinx's local order; `meshes.tissue.TISSUES`), or None.
    """

    mesh: object
    facet_tags: object
    V: object
    X: np.ndarray
    node_key: np.ndarray
    node_of_block: np.ndarray
    segments: dict
    pivots: dict
    landmarks: dict
    name: str
    n_vertices: int
    n_cells: int
    occlusion: np.ndarray | None = None
    head_frame: object = None   # meshes.frame.HeadFrame or None
    contact: str = "sliding"
    material: str = "homogeneous"
    tissues: np.ndarray | None = None
    thresholds: dict | None = None
    voxel_mm: np.ndarray | None = None

    @property
    def degree(self) -> int:
        return compat.degree(self.V)

    @property
    def input_index(self) -> np.ndarray:
        """(n_local_nodes,) original vertex index of each dof block, -1 on edge midpoints."""
        i, j = self.node_key.T
        return np.where(i == j, i, -1)

    @property
    def comm(self) -> MPI.Comm:
        return self.mesh.comm

    @property
    def n_dofs(self) -> int:
        """Global number of displacement dofs."""
        return self.V.dofmap.index_map.size_global * self.V.dofmap.index_map_bs

    @property
    def n_owned(self) -> int:
        """Number of dof blocks (nodes) owned by this rank."""
        return self.V.dofmap.index_map.size_local

    def facet_blocks(self, tags) -> np.ndarray:
        """Local dof blocks (nodes) on facets with any of the given tags."""
        facets = self.facet_tags.indices[np.isin(self.facet_tags.values, list(tags))]
        return dolfinx.fem.locate_dofs_topological(self.V, self.mesh.topology.dim - 1, facets)

    @property
    def teeth_tags(self) -> list[int]:
        """The teeth tags (`meshes.anatomy.TEETH_OFFSET`) of the segments that have teeth on
        any rank. Collective."""
        from meshes.anatomy import segment_tags

        tags = [segment_tags(t)[1] for t in self.segments.values()]
        mine = np.array([np.sum(self.facet_tags.values == t) for t in tags], dtype=np.int64)
        found = self.comm.allreduce(mine, op=MPI.SUM)
        return [t for t, f in zip(tags, found) if f > 0]

    def dirichlet_bcs(self):
        """Homogeneous Dirichlet conditions on fixed bone and rim."""
        blocks = self.facet_blocks(DIRICHLET_TAGS)
        zero = np.zeros(3, dtype=dolfinx.default_scalar_type
                        if hasattr(dolfinx, "default_scalar_type") else np.float64)
        return [dolfinx.fem.dirichletbc(zero, blocks, self.V)]

    def point_operator(self, names) -> "PointOperator":
        """Landmark operator for the named landmarks (in that order)."""
        return PointOperator.build(self, [self.landmarks[n] for n in names])

    def boundary_vertices(self, tags=None) -> np.ndarray:
        """Sorted original indices (K,) of all vertices on facets with ``tags`` (default: the
        skin), the same on every rank. Collective."""
        from meshes.anatomy import SKIN

        mine = self.input_index[self.facet_blocks([SKIN] if tags is None else tags)]
        mine = mine[mine >= 0]   # vertices, not edge midpoints
        return np.unique(np.concatenate(self.comm.allgather(mine)))

    def boundary_triangles(self, vertices: np.ndarray, tags=None) -> np.ndarray:
        """Triangles (F, 3) of the facets with ``tags`` (default: the skin) as positions in
        ``vertices`` (from `boundary_vertices` of the same tags). Collective."""
        from meshes.anatomy import SKIN

        tri, _ = self.tagged_triangles([SKIN] if tags is None else tags)
        return np.searchsorted(vertices, tri)

    def tagged_triangles(self, tags=None) -> tuple[np.ndarray, np.ndarray]:
        """The tagged facets with ``tags`` (default: all): triangles (F, 3) as original vertex
        indices, oriented out of the tissue, and their tags (F,); sorted, the same on every
        rank whatever the partition. Collective."""
        keep = (np.ones(len(self.facet_tags.values), bool) if tags is None
                else np.isin(self.facet_tags.values, list(tags)))
        nodes = _outward(self.mesh, self.facet_tags.indices[keep])
        glob = np.asarray(self.mesh.geometry.input_global_indices, dtype=np.int64)[nodes]
        tri = np.concatenate(self.comm.allgather(glob.reshape(-1, 3)))
        tag = np.concatenate(self.comm.allgather(self.facet_tags.values[keep]))
        start = tri.argmin(axis=1)   # the same on any ranks: the lowest vertex first
        tri = tri[np.arange(len(tri))[:, None], (start[:, None] + np.arange(3)) % 3]
        tri, first = np.unique(tri, axis=0, return_index=True)   # ghosts, gathered twice
        return tri, tag[first]

    def vertex_array(self, block_values: np.ndarray, k: int = 3,
                     root: int = 0) -> np.ndarray | None:
        """Values at the mesh's vertices (n_vertices, k) in the original order, on ``root``
        (None elsewhere), from per-dof-block values (n_local_nodes or n_owned, k), or their
        flat array: a Function's or a PETSc vector's (P2 edge midpoints are dropped).
        Collective."""
        vals = np.asarray(block_values).reshape(-1, k)[:self.n_owned]
        index = self.input_index[:self.n_owned]
        return _on_root(self.comm, index[index >= 0], vals[index >= 0], self.n_vertices, root)

    def cell_array(self, cell_values: np.ndarray | None = None,
                   root: int = 0) -> np.ndarray | None:
        """Values of the cells (n_cells, k) in the original order, on ``root`` (None
        elsewhere), from per-local-cell values (n_local_cells, k); by default the cells'
        original vertex indices (n_cells, 4). Collective."""
        n = self.mesh.topology.index_map(3).size_local
        if cell_values is None:
            nodes = compat.cell_nodes(self.mesh)[:n]
            cell_values = np.asarray(self.mesh.geometry.input_global_indices,
                                     dtype=np.int64)[nodes]
        vals = np.asarray(cell_values)[:n].reshape(n, -1)
        index = np.asarray(self.mesh.topology.original_cell_index, dtype=np.int64)[:n]
        return _on_root(self.comm, index, vals, self.n_cells, root)

    def vertex_operator(self, vertices) -> "PointOperator":
        """Point operator for mesh vertices given by original index (K,)."""
        return PointOperator.build(self, [Landmark((v, v, v), (1.0, 0.0, 0.0))
                                          for v in vertices])

    def owned_blocks(self, pairs: np.ndarray) -> np.ndarray:
        """Owned dof block (K,) of each node named by a vertex pair (K, 2) (module
        docstring), or -1 where this rank does not own it."""
        code = np.array([self.n_vertices, 1], dtype=np.int64)
        key = self.node_key[:self.n_owned] @ code   # node_key rows are sorted
        want = np.sort(np.asarray(pairs, dtype=np.int64), axis=1) @ code
        if not len(key):
            return np.full(len(want), -1)
        order = np.argsort(key)
        j = order[np.minimum(np.searchsorted(key, want, sorter=order), len(key) - 1)]
        return np.where(key[j] == want, j, -1)

    def ds(self):
        return ufl.Measure("ds", domain=self.mesh, subdomain_data=self.facet_tags)


@dataclasses.dataclass
class PointOperator:
    """Sparse map L from nodal displacement u to points ``L(X + u)``, (Nt, 3) mm.

    Each point is a weighted sum of the nodes of its skin triangle (the Lagrange basis of
    the domain's degree at its barycentric coordinates). Terms are held on the rank that owns
    the node; results are summed over ranks.
    """

    comm: MPI.Comm
    n_points: int
    point: np.ndarray    # (K,) point index of each local term
    block: np.ndarray    # (K,) owned dof block
    weight: np.ndarray   # (K,) barycentric weight
    X: np.ndarray        # (K, 3) rest position of the block

    @classmethod
    def build(cls, domain: Domain, landmarks: list[Landmark]) -> "PointOperator":
        facet = np.array([lm.facet for lm in landmarks], dtype=np.int64).reshape(-1, 3)
        lam = np.array([lm.weights for lm in landmarks], dtype=float).reshape(-1, 3)
        pairs, weight = _lagrange_terms(facet, lam, domain.degree)
        point = np.repeat(np.arange(len(landmarks), dtype=np.int32), weight.shape[1])
        block = domain.owned_blocks(pairs.reshape(-1, 2))
        mine = (block >= 0) & (weight.ravel() != 0)
        block = block[mine].astype(np.int32)
        return cls(domain.comm, len(landmarks), point[mine], block, weight.ravel()[mine],
                   domain.X[block])

    def apply(self, u_array: np.ndarray, offset: bool = True) -> np.ndarray:
        """Points (Nt, 3) mm, ``L(X + u)``, from a local blocked displacement array (ghosts
        optional); with ``offset=False`` the linear part ``L u`` only. Collective."""
        local = np.zeros((self.n_points, 3))
        vals = u_array.reshape(-1, 3)[self.block] + (self.X if offset else 0.0)
        np.add.at(local, self.point, self.weight[:, None] * vals)
        return self.comm.allreduce(local, op=MPI.SUM)

    def transpose_add(self, g: np.ndarray, out_array: np.ndarray) -> None:
        """out += L^T g, for g (Nt, 3), into a local blocked array (owned part)."""
        o = out_array.reshape(-1, 3)
        np.add.at(o, self.block, self.weight[:, None] * g[self.point])


def _outward(mesh, facets: np.ndarray) -> np.ndarray:
    """The geometry nodes (n, 3) of the local facets ``facets`` (n,), ordered so that their
    normal points out of their (first) cell: out of the tissue on the boundary."""
    nodes = np.array(compat.facet_nodes(mesh, facets), dtype=np.int64).reshape(-1, 3)
    f2c = mesh.topology.connectivity(mesh.topology.dim - 1, mesh.topology.dim)
    cell = compat.cell_nodes(mesh)[f2c.array[f2c.offsets[facets]]]
    x = mesh.geometry.x[:, :3]
    a, b, c = (x[nodes[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), x[cell].mean(axis=1) - a) > 0
    nodes[inward] = nodes[inward][:, [0, 2, 1]]
    return nodes


def _on_root(comm: MPI.Comm, index: np.ndarray, values: np.ndarray, n: int, root: int):
    """The rows ``values`` (K, k) each rank holds at ``index`` (K,), placed in one (n, k)
    array on ``root``; None elsewhere."""
    parts = comm.gather((index, values), root=root)
    if comm.rank != root:
        return None
    out = np.zeros((n, values.shape[1]), dtype=values.dtype)
    for i, v in parts:
        out[i] = v
    return out


#: Edges of the reference tetrahedron (basix order): the P2 edge dofs follow the vertices.
_EDGES = [(2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1)]


def _lagrange_terms(facet: np.ndarray, lam: np.ndarray, degree: int):
    """Nodes (Nt, m, 2) as vertex pairs and weights (Nt, m) of points with barycentric
    coordinates ``lam`` (Nt, 3) on triangles ``facet`` (Nt, 3): the Lagrange basis."""
    if degree == 1:
        return np.stack([facet, facet], axis=-1), lam
    a, b = [0, 0, 1], [1, 2, 2]   # the triangle's edges
    pairs = np.concatenate([np.stack([facet, facet], -1),
                            np.stack([facet[:, a], facet[:, b]], -1)], axis=1)
    weights = np.concatenate([lam * (2 * lam - 1), 4 * lam[:, a] * lam[:, b]], axis=1)
    return pairs, weights


def create_domain(source, comm: MPI.Comm = MPI.COMM_WORLD, root: int = 0,
                  degree: int = 1) -> Domain:
    """Distribute an anatomy over ``comm``.

    Args:
        source: an `Anatomy`, or a callable returning one, evaluated and validated on ``root``
            only (other ranks may pass None). An error there is raised on every rank.
        degree: of the Lagrange displacement, 1 or 2.
    """
    if degree not in (1, 2):
        raise InputError(f"element degree must be 1 or 2, got {degree!r}")
    meta = None
    cells, x = np.empty((0, 4), dtype=np.int64), np.empty((0, 3))
    facets, values = np.empty((0, 3), dtype=np.int64), np.empty(0, dtype=np.int32)
    if comm.rank == root:
        try:
            anatomy = source() if callable(source) else source
            anatomy.validate()
            meta = dict(segments=anatomy.segments, pivots=anatomy.pivots,
                        landmarks=anatomy.landmarks, name=anatomy.name,
                        n_vertices=anatomy.n_vertices, n_cells=anatomy.n_cells,
                        occlusion=anatomy.occlusion, head_frame=anatomy.head_frame,
                        contact=anatomy.contact, material=anatomy.material,
                        thresholds=anatomy.thresholds, voxel_mm=anatomy.voxel_mm)
            cells, x = anatomy.cells, anatomy.points
            facets, values = anatomy.facets, anatomy.facet_tags
        except Exception as e:  # re-raised on every rank below
            meta = e
    meta = comm.bcast(meta, root=root)
    if isinstance(meta, Exception):
        raise meta
    tissues = comm.bcast(anatomy.tissues if comm.rank == root else None, root=root)
    mesh = compat.create_mesh(comm, cells, x)
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, 0)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ft = compat.facet_tags(mesh, facets, values)
    V = compat.vector_space(mesh, degree)
    # the first 4 dofs of a cell are its vertices, in the geometry's order; P2 edges follow
    gdofs = compat.cell_nodes(mesh)
    vdofs = compat.cell_dofs(V.dofmap.list)
    ends = np.array([(k, k) for k in range(4)] + _EDGES[:vdofs.shape[1] - 4])
    n_blocks = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
    node_of_block = np.full(n_blocks, -1, dtype=np.int64)
    node_of_block[vdofs[:, :4].ravel()] = gdofs.ravel()
    vertex = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[gdofs]
    node_key = np.empty((n_blocks, 2), dtype=np.int64)
    node_key[vdofs.ravel()] = np.sort(vertex[:, ends], axis=2).reshape(-1, 2)
    X = np.empty((n_blocks, 3))
    X[vdofs.ravel()] = mesh.geometry.x[:, :3][gdofs][:, ends].mean(axis=2).reshape(-1, 3)
    if tissues is not None:
        tissues = tissues[np.asarray(mesh.topology.original_cell_index)]
    return Domain(mesh, ft, V, X, node_key, node_of_block, tissues=tissues, **meta)
