"""Synthetic anatomy, validation of bad meshes, and real anatomy from files."""

import copy
import json

import meshio
import numpy as np
import pytest

from meshes.anatomy import (
    FIXED,
    SKIN,
    STANDARD_LANDMARKS,
    Anatomy,
    segment_tags,
    signed_volumes,
)
from meshes.errors import InputError, MeshError
from meshes.external import load_tet_mesh, tetrahedralise
from meshes.synthetic import CASES, RESOLUTIONS, synthetic_head


def test_tiny_head_has_everything(tiny_anatomy):
    a = tiny_anatomy
    assert a.n_vertices < 3000
    assert set(STANDARD_LANDMARKS) <= set(a.landmarks)
    assert set(a.segments) == {"mandible", "maxilla_L", "maxilla_R"}
    assert np.all(signed_volumes(a.points, a.cells) > 0)
    pos = a.landmark_positions()
    # anatomical order along the profile: nose tip most anterior, chin below lips
    assert pos["Prn"][1] > pos["Ls"][1] > pos["Sn"][1] - 5
    assert pos["N"][2] > pos["Prn"][2] > pos["Sn"][2] > pos["Ls"][2] > pos["Li"][2] \
        > pos["Pg"][2] > pos["Me"][2]
    assert pos["T_L"][0] > 60 and pos["T_R"][0] < -60
    for s in a.segments:   # maxilla halves on their own side
        x = a.pivots[s][0]
        assert {"mandible": abs(x) < 5, "maxilla_L": x > 10, "maxilla_R": x < -10}[s]


def test_cases_differ_where_expected(tiny_anatomy):
    c2 = synthetic_head("class2", "tiny").landmark_positions()
    c3 = tiny_anatomy.landmark_positions()
    assert c3["Pg"][1] - c2["Pg"][1] > 10          # prognathic vs retruded chin
    assert abs(c3["N"][1] - c2["N"][1]) < 0.5      # same upper face
    asym = synthetic_head("class3-asym", "tiny").landmark_positions()
    assert asym["Pg"][0] < -3                       # chin deviated to the right


def test_cache_is_reused(tiny_anatomy, monkeypatch):
    import meshes.synthetic as syn

    monkeypatch.setattr(syn, "build", lambda *a: pytest.fail("regenerated a cached mesh"))
    again = synthetic_head("class3", "tiny")
    np.testing.assert_array_equal(again.cells, tiny_anatomy.cells)


def test_unknown_case_and_resolution():
    with pytest.raises(InputError, match="unknown case"):
        synthetic_head("class4", "tiny")
    with pytest.raises(InputError, match="unknown resolution"):
        synthetic_head("class3", "huge")
    assert set(CASES) == {"class1", "class2", "class3", "class3-asym"}
    assert list(RESOLUTIONS) == ["tiny", "coarse", "medium", "paper", "fine"]


def _broken(a, how):
    b = copy.deepcopy(a)
    if how == "no fixed tags":
        b.facet_tags = np.where(b.facet_tags == FIXED, SKIN, b.facet_tags)
    elif how == "inverted":
        b.cells[5] = b.cells[5][[1, 0, 2, 3]]
    elif how == "duplicate":
        b.cells = np.vstack([b.cells, b.cells[:1]])
    elif how == "flat":
        b.points[b.cells[7, 3]] = b.points[b.cells[7, :3]].mean(axis=0)
    elif how == "nan":
        b.points[3, 1] = np.nan
    elif how == "landmark off skin":
        bone = b.facets[b.facet_tags == FIXED][0]
        b.landmarks["Pg"].facet = bone
    elif how == "not tets":
        b.cells = b.cells[:, :3]
    return b


@pytest.mark.parametrize("how,match", [
    ("no fixed tags", "no facets tagged fixed"), ("inverted", "inverted"),
    ("duplicate", "duplicate"), ("flat", "degenerate|inverted"), ("nan", "NaN"),
    ("landmark off skin", "off the skin"), ("not tets", "tetrahedra")])
def test_bad_mesh_clear_error(tiny_anatomy, how, match):
    with pytest.raises(MeshError, match=match):
        _broken(tiny_anatomy, how).validate()


def _write_tet_mesh(a: Anatomy, path, landmarks):
    meshio.write(path, meshio.Mesh(a.points, [("tetra", a.cells), ("triangle", a.facets)],
                                   cell_data={"tag": [np.zeros(len(a.cells), int),
                                                      a.facet_tags]}))
    side = {"facet_data": "tag", "roles": {"skin": 1, "fixed": 2, "free_bone": 3, "rim": 4},
            "segments": {k: int(v) for k, v in a.segments.items()},
            "teeth": {k: int(segment_tags(v)[1]) for k, v in a.segments.items()},
            "landmarks": landmarks}
    with open(str(path) + ".json", "w") as fh:
        json.dump(side, fh)


def test_tet_mesh_with_sidecar(tiny_anatomy, tmp_path):
    pos = tiny_anatomy.landmark_positions()
    f = tmp_path / "head.vtu"
    _write_tet_mesh(tiny_anatomy, f, {k: pos[k].tolist() for k in ("Pg", "Li", "N")})
    a = load_tet_mesh(f)
    assert a.n_cells == tiny_anatomy.n_cells and set(a.segments) == set(tiny_anatomy.segments)
    for k, v in a.landmark_positions().items():
        np.testing.assert_allclose(v, pos[k], atol=1e-6)
    # a landmark 3 mm outside the skin is refused
    _write_tet_mesh(tiny_anatomy, f, {"Pg": (pos["Pg"] + [0, 3, 0]).tolist()})
    with pytest.raises(MeshError, match="off the skin"):
        load_tet_mesh(f)


def test_bad_files(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        load_tet_mesh(tmp_path / "nothing.vtu")
    (tmp_path / "trunc.vtu").write_text("<VTKFile type=")
    with pytest.raises(MeshError, match="cannot read"):
        load_tet_mesh(tmp_path / "trunc.vtu")
    tri = tmp_path / "surf.vtu"
    meshio.write(tri, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    (tmp_path / "surf.vtu.json").write_text("{}")
    with pytest.raises(MeshError, match="no tetrahedra"):
        load_tet_mesh(tri)


def _sphere(r, n=2):
    """Icosphere of radius r (points, triangles), outward oriented."""
    t = (1 + 5 ** 0.5) / 2
    p = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    pts, tris = list(p / np.linalg.norm(p, axis=1)[:, None]), [tuple(x) for x in f]
    for _ in range(n):
        cache, new = {}, []
        for a, b, c in tris:
            m = []
            for i, j in ((a, b), (b, c), (c, a)):
                key = (min(i, j), max(i, j))
                if key not in cache:
                    q = pts[i] + pts[j]
                    pts.append(q / np.linalg.norm(q))
                    cache[key] = len(pts) - 1
                m.append(cache[key])
            new += [(a, m[0], m[2]), (b, m[1], m[0]), (c, m[2], m[1]), (m[0], m[1], m[2])]
        tris = new
    return r * np.array(pts), np.array(tris)


def test_tetrahedralise_surfaces(tmp_path):
    for name, r in (("skin.stl", 50.0), ("bone.ply", 30.0)):
        p, t = _sphere(r)
        meshio.write(tmp_path / name, meshio.Mesh(p, [("triangle", t)]))
    regions = [{"role": "free_bone", "box": [[-99, -99, -15], [99, 99, 0]]},
               {"role": "mandible", "box": [[-99, -99, -99], [99, 99, -15]]}]
    a = tetrahedralise(tmp_path / "skin.stl", tmp_path / "bone.ply", regions,
                       {"Pg": [0, 0, -50], "N": [0, 50, 0]}, h=8.0)
    assert a.segments == {"mandible": 11}
    assert np.all(signed_volumes(a.points, a.cells) > 0)
    vol = np.abs(signed_volumes(a.points, a.cells)).sum()
    assert 0.85 * 4 / 3 * np.pi * (50 ** 3 - 30 ** 3) < vol < 4 / 3 * np.pi * (50 ** 3 - 30 ** 3)
    assert np.linalg.norm(a.landmark_positions()["Pg"] - [0, 0, -50]) < 0.5


def _kuhn_box(cubes) -> tuple:
    """(points, cells): unit cubes at the integer corners ``cubes`` [(i, j, k)], six tets each
    (Kuhn's), sharing their vertices."""
    import itertools

    index, cells = {}, []
    for c in cubes:
        for perm in itertools.permutations(range(3)):
            path, corner = [tuple(c)], list(c)
            for axis in perm:
                corner[axis] += 1
                path.append(tuple(corner))
            cells.append([index.setdefault(v, len(index)) for v in path])
    points = np.zeros((len(index), 3))
    for v, i in index.items():
        points[i] = v
    return points, np.array(cells)


@pytest.mark.unit
def test_a_cuts_band_edge_runs_along_its_line_not_along_the_facets():
    """A block's floor (bone, 8 x 8 unit cubes) under a cut's band edges at a slant: once
    `meshes.ct.snap_to_edges` slides the floor's vertices onto them, only facets at the
    floor's rim (whose vertices lie on the walls too, and stay) straddle a line, so the area
    on each side read at facet midpoints is exact to within those facets' area (before: a
    ragged row of facets). No other vertex moves, no cell turns over or falls below
    `meshes.ct.SNAP_QUALITY`."""
    from meshes.anatomy import tet_quality
    from meshes.ct import SNAP_QUALITY, _boundary, snap_to_edges
    from meshes.plane import Plane

    n = 8
    points, cells = _kuhn_box([(i, j, k) for i in range(n) for j in range(n) for k in range(2)])
    facets, _ = _boundary(cells, points)
    floor = (points[facets][:, :, 2] == 0).all(axis=1)
    plane = Plane((0.0, 3.3, 0.0), tuple(np.array([0.35, 1.0, 0.0]) / np.hypot(0.35, 1.0)))
    levels = [(plane, -1.1), (plane, 2.05)]
    snapped = snap_to_edges(points, cells, facets, floor, levels)
    off_floor = np.setdiff1d(np.arange(len(points)), np.unique(facets[floor]))
    assert np.array_equal(snapped[off_floor], points[off_floor])
    q = tet_quality(snapped, cells)
    assert (signed_volumes(snapped, cells) * signed_volumes(points, cells) > 0).all()
    assert q.min() >= SNAP_QUALITY
    rim = np.zeros(len(points), dtype=bool)
    rim[facets[~floor]] = True
    u, w = np.meshgrid((np.arange(4000) + 0.5) / 500, (np.arange(4000) + 0.5) / 500)
    fine = np.stack([u.ravel(), w.ravel(), 0 * u.ravel()], axis=1)   # the floor, sampled
    for x, left in ((points, {}), (snapped, {})):
        for plane_, level in levels:
            phi = plane_.distance(x[facets[floor]].reshape(-1, 3)).reshape(-1, 3) - level
            straddle = (phi.min(axis=1) < -1e-9) & (phi.max(axis=1) > 1e-9)
            a = x[facets[floor]]
            area = 0.5 * np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
            below = area[phi.mean(axis=1) < 0].sum()
            exact = n * n * np.mean(plane_.distance(fine) < level)
            left[level] = (straddle, area[straddle].sum(), abs(below - exact))
        if x is points:
            assert all(s.sum() > 10 for s, _, _ in left.values())   # the ragged row
    for straddle, straddled, error in left.values():
        assert rim[facets[floor][straddle]].any(axis=1).all()
        assert error <= straddled + 1e-2, (straddle.sum(), error)


@pytest.mark.unit
def test_flaps_one_cell_thick_between_free_surfaces_are_dropped():
    """A block held below (FIXED) with skin on top, and a sheet one cube thick sticking out of
    its side between a free surface and the cut's free band: the sheet goes, every cell that
    has a face on the held bone or touches the skin stays, the tags follow their facets, and
    the result has no pinched vertex; with the sheet on held bone instead, nothing changes."""
    from meshes.anatomy import FREE_BONE, boundary_facets
    from meshes.ct import _boundary, drop_flaps, split_pinched_vertices

    block = [(i, j, k) for i in range(4) for j in range(4) for k in range(3)]
    sheet = [(i, j, 1) for i in range(4, 7) for j in range(4)]

    def tagged(points, cells):
        facets, _ = _boundary(cells, points)
        z = points[facets][:, :, 2]
        tags = np.zeros(len(facets), dtype=np.int32)
        tags[(z == 0).all(axis=1)] = FIXED
        tags[(z == 3).all(axis=1)] = SKIN
        tags[(z == 1).all(axis=1) & (points[facets][:, :, 0] >= 4).all(axis=1)] = FREE_BONE
        return facets, tags

    points, cells = _kuhn_box(block + sheet)
    facets, tags = tagged(points, cells)
    assert (points[cells].mean(axis=1)[:, 0] > 4).sum() == 6 * len(sheet)
    p2, c2, f2, t2 = drop_flaps(points, cells, facets, tags)
    assert (p2[c2].mean(axis=1)[:, 0] > 4).sum() == 0
    def at(p, c):   # each cell as the set of its corners' positions
        return {frozenset(map(tuple, x)) for x in p[c]}

    on_bone = {tuple(x) for x in points[facets[tags == FIXED]].reshape(-1, 3)}
    on_skin = {tuple(x) for x in points[facets[tags == SKIN]].reshape(-1, 3)}
    held = [c for c in at(points, cells) if len(on_bone & c) >= 3 or on_skin & c]
    assert len(held) > 2 * 32 and set(held) <= at(p2, c2)   # a face on the bone, or skin
    for t in (FIXED, SKIN):
        assert (t2 == t).sum() == (tags == t).sum() == 32
    assert {tuple(f) for f in np.sort(f2, axis=1)} == {tuple(f) for f in boundary_facets(c2)}
    assert len(split_pinched_vertices(c2)[1]) == len(p2)
    points, cells = _kuhn_box(block + sheet)   # the sheet on held bone: no flap
    facets, tags = tagged(points, cells)
    tags[tags == FREE_BONE] = FIXED
    out = drop_flaps(points, cells, facets, tags)
    assert all(x is y for x, y in zip(out, (points, cells, facets, tags)))


@pytest.mark.unit
def test_a_small_bump_does_not_take_a_lips_name():
    """A profile made by hand (Gaussians: the nose at z = 0, the lips at -27 and -40, the
    chin at -56 mm, and a 0.8 mm bump at -15, under Sn): Ls, Li and Pg are the lips and the
    chin, not the bump, which stands out by more than `PROMINENCE_MM` but least of the four.
    On the synthetic CT at paper a 0.4 mm bulge under Sn, meshed 1.0 mm high on one voxel
    grid and flat on the next, moved Ls, Li and Pg one bulge up (10-20 mm)."""
    from meshes.landmarks import PROMINENCE_MM, profile_landmarks
    from meshes.plane import Plane

    bulges = {"Prn": (0.0, 20.0, 4.0), "Ls": (-27.0, 4.0, 3.0), "Li": (-40.0, 4.0, 3.0),
              "Pg": (-56.0, 5.0, 4.0), "bump": (-15.0, 0.8, 1.0)}   # z, height, width mm
    assert bulges["bump"][1] > PROMINENCE_MM
    x, z = np.meshgrid(np.linspace(-20, 20, 21), np.arange(-70.0, 30.0, 0.25), indexing="ij")
    y = 80.0 + sum(h * np.exp(-0.5 * ((z - c) / w) ** 2) for c, h, w in bulges.values())
    points = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    nx, nz = x.shape
    k = np.arange(nx * nz).reshape(nx, nz)[:-1, :-1].ravel()
    tris = np.concatenate([np.stack([k, k + nz, k + 1], 1),
                           np.stack([k + 1, k + nz, k + nz + 1], 1)])
    found = profile_landmarks(points, tris, Plane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)))
    for name in ("Prn", "Ls", "Li", "Pg"):
        assert abs(found[name].position(points)[2] - bulges[name][0]) < 0.5, name


@pytest.mark.unit
def test_a_plateau_stops_at_the_next_hollow():
    """A bulge's middle (`meshes.landmarks._middle`) is taken over its part within the
    plateau of its top, short of the hollow beside it: a chin's plateau a voxel deep
    (`meshes.landmarks.CHIN_PLATEAU`) would otherwise run over a shallow labiomental fold
    into the lower lip. The profile by hand: Li at 2, the fold at 4, Pg's flat top at 6-7."""
    from meshes.landmarks import _middle

    s = np.array([0.0, 2.0, 3.0, 2.6, 2.5, 2.8, 3.2, 3.2, 3.1, 1.0, 0.0])
    run = np.zeros(len(s), dtype=int)
    assert _middle(s, run, 6, 1.0, 1.0) == 5   # across the fold: (2 + 8) // 2
    assert _middle(s, run, 6, 1.0, 1.0, stops=[4]) == 6   # (5 + 8) // 2
