"""Pictures of a scene (matplotlib, no screen): the skin with its landmarks, and the bone
surface coloured by role. For the README and the CT pipeline's check by eye."""

from __future__ import annotations

import numpy as np

#: Facet colours by tag (RGB): fixed bone grey, free bone sand, segments, crop faces lilac.
COLOURS = {2: (0.62, 0.62, 0.62), 3: (0.93, 0.82, 0.55), 4: (0.75, 0.65, 0.9),
           11: (0.85, 0.25, 0.2), 12: (0.2, 0.6, 0.3), 13: (0.2, 0.4, 0.85)}
SKIN_COLOUR = (0.96, 0.80, 0.69)
#: Camera: from the patient's front right, a little above (matplotlib's elevation, azimuth).
VIEWS = ((8, 125), (5, 180))


def _shaded(points, tris, rgb, light=(0.3, 0.8, 0.5)):
    """Face colours (T, 4) with Lambert shading of a fixed light."""
    x = points[tris]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
    lam = 0.35 + 0.65 * np.abs(n @ (np.asarray(light) / np.linalg.norm(light)))
    c = np.asarray(rgb, float)
    c = np.broadcast_to(c, (len(tris), 3)) if c.ndim == 1 else c
    return np.c_[c * lam[:, None], np.ones(len(tris))]


def _draw(ax, points, tris, colours, view):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax.add_collection3d(Poly3DCollection(points[tris], facecolors=colours, linewidths=0))
    lo, hi = points.min(axis=0), points.max(axis=0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.view_init(*view)
    ax.set_box_aspect((1, 1, 1), zoom=1.5)
    ax.set_axis_off()


def render_scene(anatomy, path, title: str | None = None) -> None:
    """A PNG at ``path``: the skin with landmarks (front right and profile), and the bone
    facets coloured by role (`COLOURS`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from meshes.anatomy import SKIN, _facet_keys, boundary_facets

    pts, tags, tris = anatomy.points, anatomy.facet_tags, anatomy.facets
    fig = plt.figure(figsize=(15, 5.4))
    # the whole surface: skin in skin colour, the rest (crop faces, free surfaces) grey
    surface = boundary_facets(anatomy.cells)
    is_skin = np.isin(_facet_keys(surface, len(pts)),
                      _facet_keys(np.sort(tris[tags == SKIN], axis=1), len(pts)))
    rgb = np.where(is_skin[:, None], SKIN_COLOUR, (0.8, 0.8, 0.82))
    lms = anatomy.landmark_positions()
    for k, view in enumerate(VIEWS):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        _draw(ax, pts, surface, _shaded(pts, surface, rgb), view)
        for name, p in lms.items():
            ax.scatter(*p, color="k", s=14, depthshade=False)
            ax.text(*(p + [0, 4, 0]), name, fontsize=9)
    bone = np.flatnonzero(tags != SKIN)
    rgb = np.array([COLOURS.get(int(t), (0.5, 0.5, 0.5)) for t in tags[bone]])
    ax = fig.add_subplot(1, 3, 3, projection="3d")
    _draw(ax, pts, tris[bone], _shaded(pts, tris[bone], rgb), VIEWS[0])
    names = {v: k for k, v in anatomy.segments.items()}
    handles = [plt.Rectangle((0, 0), 1, 1, color=COLOURS[t]) for t in sorted(COLOURS)
               if np.any(tags == t)]
    labels = [names.get(t, {2: "fixed bone", 3: "free bone", 4: "crop (held)"}.get(t))
              for t in sorted(COLOURS) if np.any(tags == t)]
    ax.legend(handles, labels, loc="lower left", fontsize=8, frameon=False)
    fig.suptitle(title or f"{anatomy.name}: {anatomy.n_vertices} vertices, "
                 f"{anatomy.n_cells} tets")
    fig.subplots_adjust(0, 0, 1, 0.94, 0, 0)
    fig.savefig(path, dpi=80, format="png")
    plt.close(fig)
