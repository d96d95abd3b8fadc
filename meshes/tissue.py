"""Tissue classes per cell: the share of each tet that is skin, fat or lean tissue.

The soft tissue between bone and skin is not one material. Each cell gets the fraction of
its volume in each class of `TISSUES` (`fem.material.Tissues` turns them into moduli):

* **skin**: within `SKIN_MM` of the skin surface (the epidermis and dermis), by the exact
  distance to the mesh's own skin triangles;
* **fat**: below it, where the CT reads at most `FAT_HU` (adipose tissue: -190 to -30 HU);
* **muscle**: the rest, above `FAT_HU` (skeletal muscle: -29 to +150 HU; also the glands,
  mucosa and the nose's cartilage, which read alike: "lean tissue").

A cell's fractions are those of `SAMPLES`, ten points spread inside it. A skin layer
thinner than the cells keeps its share of each cell that it crosses, and so its membrane
stiffness E·t on any mesh (`fem.material.Tissues`). The samples' depth under the skin is
interpolated from the cell's vertices (exact under a flat skin; on headsq at paper size the
same class as the exact depth at 99.2 % of the samples, in 0.4 s instead of 17 s).

Sources: fat and muscle HU windows, Mitsiopoulos et al. 1998 (J Appl Physiol 85:115), the
windows of CT body-composition analysis; skin thickness on the face 1.5-2.5 mm (epidermis
and dermis; Ha et al. 2005, Plast Reconstr Surg 115:1769, measured it site by site).

A CT's noise (10-20 HU in soft tissue) is far below the 130 HU between fat (about -100) and
muscle (about +40): a sample flips class only at a boundary. A CBCT's (40 HU and more) is
not: such a scan is smoothed first (`FAT_NOISE_HU`). Metal streaks alternate bright and dark
bands through the tissue; their samples take the class of their HU, so a streaked region is
a mix of the two by area (measured on headsq, BENCHMARKS.md, ct).
"""

from __future__ import annotations

import numpy as np

from meshes.errors import MeshError

#: The tissue classes, in the order of the fraction columns.
TISSUES = ("skin", "fat", "muscle")
#: Thickness (mm) of the skin layer (module docstring).
SKIN_MM = 2.0
#: HU at or below which soft tissue is fat (module docstring).
FAT_HU = -30.0
#: A scan whose soft tissue is noisier than this (HU, `meshes.intensity`) is read for fat
#: after a Gaussian of FAT_SMOOTH_VOXELS: Cranium with 43 HU of correlated noise (a CBCT's)
#: put fat's share at 0.22 against 0.16 without noise; smoothed, at 0.15.
FAT_NOISE_HU = 20.0
FAT_SMOOTH_VOXELS = 1.0
#: Barycentric coordinates (10, 4) of the sample points inside a tet: the interior points of
#: the order-6 lattice, (a, b, c, d) / 6 with a, b, c, d >= 1.
SAMPLES = np.array([(a, b, c, 6 - a - b - c) for a in range(1, 4) for b in range(1, 4)
                    for c in range(1, 4) if a + b + c <= 5], dtype=float) / 6.0
#: Candidate skin triangles (nearest centroids) searched per sample point.
_CANDIDATES = 8
#: Query points per batch of exact distances (bounds the memory: ~50 MB per array).
_CHUNK = 100_000


def cell_samples(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Sample points (M, 10, 3) mm inside the tets ``cells`` (M, 4) over ``points`` (N, 3)."""
    return np.einsum("sv,mvx->msx", SAMPLES, points[cells])


def surface_depth(query: np.ndarray, points: np.ndarray, tris: np.ndarray,
                  within: float) -> np.ndarray:
    """Distance (K,) mm from ``query`` (K, 3) to the surface of triangles ``tris`` (T, 3) over
    ``points``; exact below ``within``, and some value at least ``within`` beyond it."""
    from scipy.spatial import cKDTree

    from meshes.surface import closest_on_triangles

    verts = np.unique(tris)
    edge = max(np.linalg.norm(points[tris] - points[np.roll(tris, 1, axis=1)], axis=2).max(),
               1e-9)
    near, _ = cKDTree(points[verts]).query(query)
    out = np.maximum(near - edge, within)   # a surface point is within an edge of a vertex
    todo = np.flatnonzero(near - edge < within)
    k = min(_CANDIDATES, len(tris))
    tree = cKDTree(points[tris].mean(axis=1))
    for part in np.array_split(todo, max(1, len(todo) // _CHUNK)):
        _, cand = tree.query(query[part], k=k)
        cand = cand.reshape(len(part), k)
        a, b, c = (points[tris[cand, i]] for i in range(3))
        q = query[part, None, :]
        d = np.linalg.norm(closest_on_triangles(q, a, b, c) - q, axis=2).min(axis=1)
        out[part] = np.minimum(d, near[part])
    return out


def tissue_fractions(points: np.ndarray, cells: np.ndarray, skin: np.ndarray,
                     is_fat) -> np.ndarray:
    """Fractions (M, 3) of each cell in `TISSUES` (rows sum to 1).

    Args:
        points, cells: the tet mesh (mm); skin: (S, 3) its skin triangles.
        is_fat: sample points (K, 3) mm -> (K,) bool: fat (else lean tissue), below the
            skin layer. E.g. ``lambda x: volume.at(x) <= FAT_HU`` on a CT.
    """
    if len(skin) == 0:
        raise MeshError("the mesh has no skin facets to measure the skin layer from")
    x = cell_samples(points, cells).reshape(-1, 3)
    depth = surface_depth(points, points, skin, SKIN_MM)   # at the vertices: `SAMPLES`
    in_skin = (depth[cells] @ SAMPLES.T).reshape(-1) < SKIN_MM
    fat = np.zeros(len(x), dtype=bool)
    fat[~in_skin] = np.asarray(is_fat(x[~in_skin]), dtype=bool)
    classes = np.stack([in_skin, fat, ~in_skin & ~fat], axis=1).reshape(len(cells), -1, 3)
    return classes.mean(axis=1)


def ct_fat(volume, noise_hu: float | None = None):
    """``is_fat`` of a CT (`meshes.volume.Volume`, HU) at points (K, 3) mm: its nearest
    voxel's HU, after a Gaussian of `FAT_SMOOTH_VOXELS` where the soft tissue's noise
    ``noise_hu`` exceeds `FAT_NOISE_HU`."""
    if noise_hu is not None and noise_hu > FAT_NOISE_HU:
        import dataclasses

        from scipy import ndimage

        volume = dataclasses.replace(volume, array=ndimage.gaussian_filter(
            volume.array.astype(np.float32), FAT_SMOOTH_VOXELS))
    return lambda x: np.asarray(volume.at(x), dtype=float) <= FAT_HU


def tissue_report(anatomy) -> dict | None:
    """{class: volume fraction of the whole tissue} of an anatomy with tissue classes."""
    from meshes.anatomy import signed_volumes

    if anatomy.tissues is None:
        return None
    vol = np.abs(signed_volumes(anatomy.points, anatomy.cells))
    share = vol @ anatomy.tissues / vol.sum()
    return {name: round(float(s), 4) for name, s in zip(TISSUES, share)}
