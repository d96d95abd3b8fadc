"""Rigid registration of a surface onto a surface (ICP).

Serves the validation against a patient's outcome (`inverse.validation`): a post-operative
face scan onto the scene's skin, on what surgery does not move.
"""

from __future__ import annotations

import numpy as np

from meshes.surface import SurfaceQuery, apply, triangle_normals

#: Surface ICP (`register_surface`): the correspondence cut-off (mm) of each stage, coarse to
#: fine (a scan placed within about the first of the face), the iterations per stage, and the
#: step (mm, at the face) under which a stage has converged.
ICP_CUTOFFS_MM = (20.0, 8.0, 3.0, 1.5)
ICP_ITERATIONS = 30
ICP_STEP_MM = 1e-4


def _plane_step(x: np.ndarray, q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The rigid 4×4 that best moves points x (K, 3) onto the planes through q (K, 3) with
    normals n (K, 3), linearised in the rotation (point to plane: Chen and Medioni 1992), the
    rotation then made exact (Rodrigues)."""
    c = x.mean(axis=0)
    A = np.c_[np.cross(x - c, n), n]
    b = np.einsum("ij,ij->i", q - x, n)
    w, t = np.split(np.linalg.lstsq(A, b, rcond=None)[0], 2)
    angle = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(angle, 1e-300)
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c + t - R @ c
    return T


def register_surface(x: np.ndarray, points: np.ndarray, tris: np.ndarray,
                     normals: np.ndarray | None = None) -> tuple:
    """Rigid ICP of points x (K, 3) onto the surface (points, tris): (T 4×4 with T x on the
    surface, distances (K,) after it, matched (K,) bool: within the last cut-off and not on
    the surface's rim). Point to plane (`_plane_step`: a smooth patch such as a forehead slides
    along itself, which point to point crawls through), trimmed at `ICP_CUTOFFS_MM`; the
    planes' normals are x's own (K, 3) where given, moved with them, else the surface's. A
    noisy surface's triangles tilt at random, a smooth model's do not: Cranium's skin onto a
    scan of it noised by 0.2 mm, 0.21-0.27 degrees and 0.36-0.45 mm off with the scan's
    normals, 0.10-0.15 and 0.17-0.33 with the skin's (coarse, three seeds)."""
    T = np.eye(4)
    faces, surface = triangle_normals(points, tris), SurfaceQuery(points, tris)
    for cut in ICP_CUTOFFS_MM:
        for _ in range(ICP_ITERATIONS):
            moved = apply(T, x)
            d, q, tri = surface.closest(moved)
            matched = (d <= cut) & ~surface.on_rim(q)
            if matched.sum() < 6:
                return T, d, matched
            n = faces[tri[matched]] if normals is None else normals[matched] @ T[:3, :3].T
            step = _plane_step(moved[matched], q[matched], n)
            T = step @ T
            if np.abs(apply(step, moved[matched]) - moved[matched]).max() < ICP_STEP_MM:
                break
    d, q, _ = surface.closest(apply(T, x))
    return T, d, (d <= ICP_CUTOFFS_MM[-1]) & ~surface.on_rim(q)

