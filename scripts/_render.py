"""Pictures of a scene (matplotlib, no screen): the skin with its landmarks, and the bone
surface coloured by role. For the README and the CT pipeline's check by eye. Drawn in the
head frame (`meshes.frame`): the front and profile views are the face's, however the head
lay in the scanner."""

from __future__ import annotations

import numpy as np

#: Facet colours by tag (RGB): fixed bone grey, free bone sand, segments, crop faces lilac.
COLOURS = {2: (0.62, 0.62, 0.62), 3: (0.93, 0.82, 0.55), 4: (0.75, 0.65, 0.9),
           11: (0.85, 0.25, 0.2), 12: (0.2, 0.6, 0.3), 13: (0.2, 0.4, 0.85)}
SKIN_COLOUR = (0.96, 0.80, 0.69)
#: Camera: from the patient's front right, a little above (matplotlib's elevation, azimuth).
VIEWS = ((8, 125), (5, 180))
#: Landmarks and targets within this distance of the mid-sagittal plane (mm) are drawn on
#: the profile.
PROFILE_BAND_MM = 10.0


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

    ax.add_collection3d(Poly3DCollection(points[tris], facecolors=colours, edgecolors=colours,
                                         linewidths=0.3))   # no seams between faces
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
    from meshes.frame import HeadFrame

    frame = anatomy.head_frame or HeadFrame.identity()
    pts, tags, tris = frame.to_head(anatomy.points), anatomy.facet_tags, anatomy.facets
    fig = plt.figure(figsize=(15, 5.4))
    # the whole surface: skin in skin colour, the rest (crop faces, free surfaces) grey
    surface = boundary_facets(anatomy.cells)
    is_skin = np.isin(_facet_keys(surface, len(pts)),
                      _facet_keys(np.sort(tris[tags == SKIN], axis=1), len(pts)))
    rgb = np.where(is_skin[:, None], SKIN_COLOUR, (0.8, 0.8, 0.82))
    lms = {n: frame.to_head(p) for n, p in anatomy.landmark_positions().items()}
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



def _midsagittal(rest, tris):
    """Segments (S, 2, 2 weights...) of the skin's cut by the rest plane x = 0: for each cut
    triangle edge pair, (vertex a, vertex b, t) so that a point is (1 - t) x_a + t x_b."""
    x = rest[:, 0]
    cuts = []
    for tri in tris:
        pts = []
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            if (x[a] < 0) != (x[b] < 0):
                pts.append((a, b, x[a] / (x[a] - x[b])))
        if len(pts) == 2:
            cuts.append(pts)
    return cuts


def _curve(points, cuts):
    """(S, 2, 3) segment end points on ``points`` for the cuts of `_midsagittal`."""
    return np.array([[(1 - t) * points[a] + t * points[b] for a, b, t in c] for c in cuts])


def render_before_after(rest, after, tris, landmarks: dict, targets: dict, path,
                        title: str, frame=None, band=None) -> None:
    """A PNG at ``path``: the mid-sagittal skin profile before (rest, (N, 3) mm) and after a
    plan (``after``), with the landmarks after ({name: (3,)}, black) and their targets (red),
    and ``band`` (N,) mm, where given, shaded on either side of the profile after (the 95 %
    radius of `inverse.uncertainty`); and the face after the plan from the front, coloured
    by its displacement from rest (mm). ``tris``: (T, 3) skin triangles into the points;
    all in the scene's frame, drawn in the head frame ``frame`` (`meshes.frame.HeadFrame`;
    None: the scene's)."""
    import matplotlib

    if frame is not None:
        rest, after = frame.to_head(rest), frame.to_head(after)
        landmarks = {n: frame.to_head(p) for n, p in landmarks.items()}
        targets = {n: frame.to_head(p) for n, p in targets.items()}

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig = plt.figure(figsize=(12, 6))
    grid = fig.add_gridspec(1, 3, width_ratios=(5, 1.3, 6) if band is not None else (6, 0, 6))
    ax = fig.add_subplot(grid[0])
    cuts = _midsagittal(rest, tris)
    if band is not None:
        from matplotlib.collections import PolyCollection

        seg = _curve(after, cuts)[:, :, 1:]
        width = _curve(np.repeat(np.asarray(band, float)[:, None], 3, axis=1), cuts)[:, :, 0]
        side = fig.add_subplot(grid[1], sharey=ax)   # the band's size along the profile
        side.add_collection(LineCollection(np.stack([width, seg[:, :, 1]], axis=2),
                                           colors="tab:orange", linewidths=1.6))
        side.set_xlim(0, max(width.max(), 1e-3) * 1.1)
        side.set_xlabel("95 % band, mm")
        side.tick_params(labelleft=False)
        d = seg[:, 1] - seg[:, 0]
        n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(
            np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        quads = np.stack([seg[:, 0] + width[:, :1] * n, seg[:, 1] + width[:, 1:] * n,
                          seg[:, 1] - width[:, 1:] * n, seg[:, 0] - width[:, :1] * n], axis=1)
        ax.add_collection(PolyCollection(quads, facecolors="tab:orange", edgecolors="none",
                                         alpha=0.45, label="95 % band (tissue)"))
    for pts, style in ((rest, dict(colors="0.55", linestyles="--", label="before")),
                       (after, dict(colors="k", label="after"))):
        seg = _curve(pts, cuts)[:, :, 1:]   # (y anterior, z superior)
        ax.add_collection(LineCollection(seg, linewidths=1.6, **style))
    near = lambda p: abs(p[0]) < PROFILE_BAND_MM   # noqa: E731  (off the profile: tragion)
    for name, p in landmarks.items():
        if near(p):
            ax.plot(p[1], p[2], "ko", ms=4)
            ax.annotate(name, (p[1], p[2]), xytext=(6, 0), textcoords="offset points",
                        fontsize=9)
    for name, t in targets.items():
        if near(t):
            ax.plot(t[1], t[2], "rx", ms=7, mew=2)
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("anterior y (head frame), mm")
    ax.set_ylabel("superior z (head frame), mm")
    ax.legend(loc="lower left", fontsize=9, frameon=False)
    ax.set_title("mid-sagittal profile; x: targets", fontsize=10)
    disp = np.linalg.norm(after - rest, axis=1)
    cmap = plt.get_cmap("viridis")
    colour = cmap(disp[tris].mean(axis=1) / max(disp.max(), 1e-9))[:, :3]
    ax3 = fig.add_subplot(grid[2], projection="3d")
    _draw(ax3, after, tris, _shaded(after, tris, colour, light=(0.2, 1.0, 0.3)), (5, 90))
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, disp.max()))
    fig.colorbar(sm, ax=ax3, shrink=0.6, label="displacement from rest, mm")
    ax3.set_title("after, from the front", fontsize=10)
    fig.suptitle(title)
    fig.subplots_adjust(0.06, 0.08, 0.98, 0.9, 0.05, 0)
    fig.savefig(path, dpi=80, format="png")
    plt.close(fig)


def render_distance(points, tris, d, covered, path, title: str, frame=None) -> None:
    """A PNG at ``path``: the skin ``points`` (N, 3) mm with triangles ``tris`` from the front
    and in profile, coloured by the signed distance ``d`` (N,) mm (blue: the prediction lies
    inside the real face, red: outside it), grey where not ``covered`` (N,); a legend in mm.
    Drawn in the head frame ``frame`` (`meshes.frame.HeadFrame`; None: the scene's)."""
    import matplotlib

    if frame is not None:
        points = frame.to_head(points)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    limit = max(1.0, float(np.percentile(np.abs(d[covered]), 98)))
    cmap = plt.get_cmap("RdBu_r")
    face_d = d[tris].mean(axis=1)
    colour = cmap(0.5 + 0.5 * np.clip(face_d / limit, -1, 1))[:, :3]
    colour[~covered[tris].all(axis=1)] = 0.75
    fig = plt.figure(figsize=(12, 6))
    for k, (view, name) in enumerate((((5, 90), "front"), ((5, 0), "profile, from the left"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        _draw(ax, points, tris, _shaded(points, tris, colour, light=(0.2, 1.0, 0.3)), view)
        ax.set_title(name, fontsize=10)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(-limit, limit))
    fig.colorbar(sm, ax=fig.axes, shrink=0.6, label="predicted to real skin, mm "
                 "(> 0: the prediction stands out; grey: not in the scan)")
    fig.suptitle(title)
    fig.savefig(path, dpi=80, format="png")
    plt.close(fig)
