"""Distribute an `Anatomy` over MPI ranks as a dolfinx mesh with facet tags and P1 maps.

`Domain` is what the solvers use: the mesh, facet tags, the P1 vector space, per-vertex rest
coordinates, and `PointOperator`, the sparse map from nodal displacements to landmark points.
"""

from __future__ import annotations

from mpi4py import MPI

import dataclasses

import dolfinx
import numpy as np
import ufl
from dolfinx import cpp as _cpp

from fem import compat
from meshes.anatomy import DIRICHLET_TAGS, Landmark


@dataclasses.dataclass
class Domain:
    """A distributed soft-tissue mesh.

    Attributes:
        mesh: dolfinx mesh (mm); facet_tags: MeshTags on facets (meshes.anatomy tag values).
        V: P1 vector space; X: (n_local_nodes, 3) rest coordinates of V's dof blocks (mm),
        owned first, then ghosts. input_index: (n_local_nodes,) original vertex index of each
        dof block. node_of_block: (n_local_nodes,) geometry node of each dof block.
        segments, pivots, landmarks, name, n_vertices, n_cells: as in `Anatomy`.
    """

    mesh: object
    facet_tags: object
    V: object
    X: np.ndarray
    input_index: np.ndarray
    node_of_block: np.ndarray
    segments: dict
    pivots: dict
    landmarks: dict
    name: str
    n_vertices: int
    n_cells: int

    @property
    def comm(self) -> MPI.Comm:
        return self.mesh.comm

    @property
    def n_owned(self) -> int:
        """Number of dof blocks (vertices) owned by this rank."""
        return self.V.dofmap.index_map.size_local

    def facet_blocks(self, tags) -> np.ndarray:
        """Local dof blocks (vertices) on facets with any of the given tags."""
        facets = self.facet_tags.indices[np.isin(self.facet_tags.values, list(tags))]
        return dolfinx.fem.locate_dofs_topological(self.V, self.mesh.topology.dim - 1, facets)

    def dirichlet_bcs(self):
        """Homogeneous Dirichlet conditions on fixed bone and rim."""
        blocks = self.facet_blocks(DIRICHLET_TAGS)
        zero = np.zeros(3, dtype=dolfinx.default_scalar_type
                        if hasattr(dolfinx, "default_scalar_type") else np.float64)
        return [dolfinx.fem.dirichletbc(zero, blocks, self.V)]

    def point_operator(self, names) -> "PointOperator":
        """Landmark operator for the named landmarks (in that order)."""
        return PointOperator.build(self, [self.landmarks[n] for n in names])

    def skin_vertices(self) -> np.ndarray:
        """Sorted original indices (K,) of all skin vertices, the same on every rank."""
        from meshes.anatomy import SKIN

        mine = self.input_index[self.facet_blocks([SKIN])]
        return np.unique(np.concatenate(self.comm.allgather(mine)))

    def skin_triangles(self, vertices: np.ndarray) -> np.ndarray:
        """Skin triangles (F, 3) as positions in ``vertices`` (from `skin_vertices`)."""
        from meshes.anatomy import SKIN

        facets = self.facet_tags.indices[self.facet_tags.values == SKIN]
        nodes = _cpp.mesh.entities_to_geometry(compat.cpp_mesh(self.mesh), 2, facets, False)
        glob = np.asarray(self.mesh.geometry.input_global_indices, dtype=np.int64)[nodes]
        tri = np.unique(np.sort(np.concatenate(self.comm.allgather(glob.reshape(-1, 3))),
                                axis=1), axis=0)
        return np.searchsorted(vertices, tri)

    def vertex_operator(self, vertices) -> "PointOperator":
        """Point operator for mesh vertices given by original index (K,)."""
        return PointOperator.build(self, [Landmark((v, v, v), (1.0, 0.0, 0.0))
                                          for v in vertices])

    def ds(self):
        return ufl.Measure("ds", domain=self.mesh, subdomain_data=self.facet_tags)


@dataclasses.dataclass
class PointOperator:
    """Sparse map L from nodal displacement u to points ``L(X + u)``, (Nt, 3) mm.

    Each point is a weighted sum of three vertices. Rows are held on the rank that owns
    the vertex; results are summed over ranks.
    """

    comm: MPI.Comm
    n_points: int
    point: np.ndarray    # (K,) point index of each local term
    block: np.ndarray    # (K,) owned dof block
    weight: np.ndarray   # (K,) barycentric weight
    X: np.ndarray        # (K, 3) rest position of the block

    @classmethod
    def build(cls, domain: Domain, landmarks: list[Landmark]) -> "PointOperator":
        owned = domain.input_index[:domain.n_owned]
        order = np.argsort(owned)
        facet = np.array([lm.facet for lm in landmarks], dtype=np.int64).reshape(-1)
        weight = np.array([lm.weights for lm in landmarks], dtype=float).reshape(-1)
        point = np.repeat(np.arange(len(landmarks), dtype=np.int32), 3)
        j = np.minimum(np.searchsorted(owned, facet, sorter=order), max(len(owned) - 1, 0))
        mine = (owned[order[j]] == facet) if len(owned) else np.zeros(len(facet), bool)
        block = order[j[mine]].astype(np.int32)
        return cls(domain.comm, len(landmarks), point[mine], block, weight[mine],
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


def create_domain(source, comm: MPI.Comm = MPI.COMM_WORLD, root: int = 0) -> Domain:
    """Distribute an anatomy over ``comm``.

    Args:
        source: an `Anatomy`, or a callable returning one, evaluated and validated on ``root``
            only (other ranks may pass None). An error there is raised on every rank.
    """
    meta = None
    cells, x = np.empty((0, 4), dtype=np.int64), np.empty((0, 3))
    facets, values = np.empty((0, 3), dtype=np.int64), np.empty(0, dtype=np.int32)
    if comm.rank == root:
        try:
            anatomy = source() if callable(source) else source
            anatomy.validate()
            meta = dict(segments=anatomy.segments, pivots=anatomy.pivots,
                        landmarks=anatomy.landmarks, name=anatomy.name,
                        n_vertices=anatomy.n_vertices, n_cells=anatomy.n_cells)
            cells, x = anatomy.cells, anatomy.points
            facets, values = anatomy.facets, anatomy.facet_tags
        except Exception as e:  # re-raised on every rank below
            meta = e
    meta = comm.bcast(meta, root=root)
    if isinstance(meta, Exception):
        raise meta
    domain = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.tetrahedron, 1))
    mesh = dolfinx.mesh.create_mesh(comm, cells, x, domain)
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, 0)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ents, vals = _cpp.io.distribute_entity_data(compat.cpp_mesh(mesh), tdim - 1, facets,
                                                values.astype(np.int32))
    adj = _cpp.graph.AdjacencyList_int32(ents)
    ft = dolfinx.mesh.meshtags_from_entities(mesh, tdim - 1, adj, vals.astype(np.int32))
    V = compat.vector_space(mesh)
    # P1: V's dofs and geometry nodes follow the same cell-local vertex order
    gdofs = mesh.geometry.dofmap.array.reshape(-1, 4)
    vdofs = V.dofmap.list.array.reshape(-1, 4)
    n_blocks = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
    node_of_block = np.empty(n_blocks, dtype=np.int64)
    node_of_block[vdofs.ravel()] = gdofs.ravel()
    X = mesh.geometry.x[node_of_block, :3].copy()
    input_index = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[node_of_block]
    return Domain(mesh, ft, V, X, input_index, node_of_block, **meta)


def node_values(domain: Domain, block_values: np.ndarray) -> np.ndarray:
    """Per-geometry-node array (n_nodes, 3) from per-dof-block values (n_blocks, 3)."""
    out = np.zeros((len(domain.mesh.geometry.x), 3))
    out[domain.node_of_block] = block_values.reshape(-1, 3)
    return out
