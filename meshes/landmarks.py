"""Soft-tissue landmarks on a skin mesh: built on the mid-sagittal profile, or read from files.

The profile is the front-most skin crossing of rays cast forward in the mid-sagittal plane,
every `PROFILE_STEP_MM` from the bottom of the face to the top (its ``s``: how far forward,
``t``: how high, both mm in the plane). On it (Farkas' soft-tissue definitions):

* ``Prn`` (pronasale): the most anterior point of the profile;
* ``N`` (soft-tissue nasion): the deepest point above Prn, where the profile turns forward
  again to the forehead (absent if the face ends before the forehead rises);
* ``Ls`` (labrale superius), ``Li`` (labrale inferius), ``Pg`` (soft-tissue pogonion): the
  first, second and third forward bulges below Prn; where the nose is not in the scan, the
  lowest bulge is Pg, and the two above it Li and Ls;
* ``Sn`` (subnasale): the point between Prn and Ls farthest behind their chord, the vertex of
  the nasolabial angle (where the scan ends above Ls: between Prn and the profile's end);
* ``Me`` (soft-tissue menton): the lowest skin point under the chin, from rays cast downward
  in the plane within `MENTON_BACK_MM` behind Pg.

A bulge or a hollow counts where it stands out by `PROMINENCE_MM` (the synthetic heads'
stomion is 0.9 mm deep once voxelised); a flat one is marked at the middle of its part within
`PLATEAU_MM` of its extreme. A landmark whose feature the
scan does not hold (a field of view that ends at the lip) is absent, not guessed: the chains
of bulges do not cross a gap in the profile longer than `GAP_MM`, and no bulge or hollow is
taken within `GAP_MM` of the end of the profile or of such a gap. Tragion is not
built: it needs the ear's cartilage, which this construction does not see.

Files: ``{name: [x, y, z]}`` (mm, the scene's frame) or a 3D Slicer markups file
(``.mrk.json``; points in RAS or LPS as its ``coordinateSystem`` says) override the built ones;
each point is projected onto the nearest skin facet and must lie within the tolerance.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from meshes.anatomy import Landmark, intersect_rays
from meshes.errors import MeshError
from meshes.osteotomy import Plane

PROFILE_STEP_MM = 0.5
PROMINENCE_MM = 0.5
GAP_MM = 4.0
PLATEAU_MM = 0.25
MENTON_BACK_MM = 20.0
#: RAS or LPS -> orthodiff (x left, y anterior, z superior).
FROM_FRAME = {"RAS": np.diag([-1.0, 1.0, 1.0]), "LPS": np.diag([1.0, -1.0, 1.0])}


def _plane_axes(plane: Plane):
    """(origin, forward a, up u) of the mid-sagittal plane: y and z projected into it."""
    n = np.asarray(plane.normal)
    a = np.array([0.0, 1.0, 0.0]) - n[1] * n
    a /= np.linalg.norm(a)
    u = np.array([0.0, 0.0, 1.0]) - n[2] * n - a[2] * a
    u /= np.linalg.norm(u)
    return np.asarray(plane.point, float), a, u


def _crossing(points, tris, plane):
    """Indices of the triangles that the plane crosses."""
    d = plane.distance(points)[tris]
    return np.flatnonzero((d.min(axis=1) <= 0) & (d.max(axis=1) >= 0))


def _extrema(s, sign: float):
    """Indices of the local maxima of sign * s that stand out by `PROMINENCE_MM`."""
    from scipy.signal import find_peaks

    return find_peaks(sign * s, prominence=PROMINENCE_MM)[0]


def profile_landmarks(points: np.ndarray, skin: np.ndarray, plane: Plane) -> dict:
    """Landmarks {name: `Landmark`} on the skin facets ``skin`` (S, 3) over ``points`` (N, 3),
    built on the profile in ``plane`` (module docstring)."""
    o, a, u = _plane_axes(plane)
    tris = skin[_crossing(points, skin, plane)]
    if len(tris) == 0:
        raise MeshError("the mid-sagittal plane does not cross the skin")
    rel = points[np.unique(tris)] - o
    s0 = (rel @ a).min() - 10.0
    t_lo, t_hi = (rel @ u).min(), (rel @ u).max()
    ts = np.arange(t_lo + PROFILE_STEP_MM / 2, t_hi, PROFILE_STEP_MM)
    hits = [intersect_rays(points, tris, o + s0 * a + t * u, a) for t in ts]
    ok = np.array([h is not None for h in hits])
    if ok.sum() < 10:
        raise MeshError("the skin's mid-sagittal profile is too short to place landmarks")
    # top to bottom; a run is a stretch with no gap longer than GAP_MM (a crop, a cut field
    # of view; a tooth between parted lips is a short gap)
    gap = np.zeros(len(ok), dtype=bool)
    missing = np.flatnonzero(~ok)
    if len(missing):
        starts = np.r_[0, np.flatnonzero(np.diff(missing) > 1) + 1]
        for lo, hi in zip(starts, np.r_[starts[1:], len(missing)]):
            if (hi - lo) * PROFILE_STEP_MM > GAP_MM:
                gap[missing[lo]:missing[hi - 1] + 1] = True
    run = np.cumsum(gap)[::-1][ok[::-1]]
    hits = [h for h in hits if h is not None][::-1]
    ts = ts[ok][::-1]
    pos = np.array([h[1] @ points[tris[h[0]]] for h in hits])
    s = (pos - o) @ a
    peaks, hollows = [], []
    edge = int(np.ceil(GAP_MM / PROFILE_STEP_MM))   # the rounded rim of a cut or crop face
    for r in np.unique(run):
        idx = np.flatnonzero(run == r)
        for marks, sign in ((peaks, 1.0), (hollows, -1.0)):
            found_r = _extrema(s[idx], sign)
            marks += list(idx[found_r[(found_r >= edge) & (found_r < len(idx) - edge)]])
    found = {}

    def below(i, marks):   # the first mark below index i in i's run
        return next((j for j in sorted(marks) if j > i and run[j] == run[i]), None)

    def above(i, marks):
        return next((j for j in sorted(marks, reverse=True) if j < i and run[j] == run[i]),
                    None)

    prn = int(np.argmax(s))
    lips = ("Ls", "Li", "Pg")
    if prn in peaks:   # the nose is in the scan: the bulges below it, from the nose down
        found["Prn"] = prn
        found["N"] = above(prn, hollows)
        chain = [j for j in sorted(peaks) if j > prn and run[j] == run[prn]][:3]
        found.update(zip(lips, chain))
        end = found.get("Ls", np.flatnonzero(run == run[prn])[-1])
        between = np.arange(prn + 1, end)
        if len(between):   # how far behind the chord Prn-Ls, along s
            chord = s[prn] + (ts[between] - ts[prn]) / (ts[end] - ts[prn]) * (s[end] - s[prn])
            sn = int(between[np.argmax(chord - s[between])])
            found["Sn"] = sn if end - sn > edge else None
    elif peaks:   # no nose: from the chin up, Pg the lowest bulge
        last = max(peaks)
        chain = [j for j in sorted(peaks, reverse=True) if run[j] == run[last]][:3]
        found.update(zip(lips[::-1], chain))
    for name in ("Prn", "N", "Ls", "Li", "Pg"):   # a flat bulge or hollow: its middle
        if found.get(name) is not None:
            found[name] = _middle(s, run, found[name], -1.0 if name == "N" else 1.0)
    out = {name: Landmark(tris[hits[i][0]].copy(), hits[i][1].copy())
           for name, i in found.items() if i is not None}
    if found.get("Pg") is not None:
        me = _menton(points, tris, o, a, u, s[found["Pg"]], ts[found["Pg"]])
        if me is not None:
            out["Me"] = me
    return out


def _middle(values, run, i: int, sign: float) -> int:
    """The middle sample of the stretch of i's run around the extremum i where sign * values
    stays within `PLATEAU_MM` of it: the most anterior (or deepest) point of a flat bulge is
    where its flat part is, not wherever 0.1 mm of noise puts it."""
    v = sign * np.asarray(values)
    lo = hi = i
    while lo > 0 and run[lo - 1] == run[i] and v[lo - 1] >= v[i] - PLATEAU_MM:
        lo -= 1
    while hi < len(v) - 1 and run[hi + 1] == run[i] and v[hi + 1] >= v[i] - PLATEAU_MM:
        hi += 1
    return (lo + hi) // 2


def _menton(points, tris, o, a, u, s_pg, t_pg):
    """The lowest skin crossing of downward rays within `MENTON_BACK_MM` behind Pg (the
    middle of its flat part, `_middle`)."""
    hits, ts = [], []
    for s in np.arange(s_pg - MENTON_BACK_MM, s_pg, PROFILE_STEP_MM):
        h = intersect_rays(points, tris, o + s * a + (t_pg + 1.0) * u, -u)
        t = np.inf if h is None else (h[1] @ points[tris[h[0]]] - o) @ u
        hits.append(h)
        ts.append(t if t < t_pg else np.inf)
    ts = np.array(ts)
    if not np.isfinite(ts).any():
        return None
    run = np.cumsum(~np.isfinite(ts))
    i = _middle(np.where(np.isfinite(ts), ts, 1e9), run, int(np.argmin(ts)), -1.0)
    return Landmark(tris[hits[i][0]].copy(), hits[i][1].copy())


def read_landmark_file(path) -> dict:
    """Points {name: (3,)} mm in the scene's frame from a JSON ``{name: [x, y, z]}`` or a
    3D Slicer markups file (``.mrk.json``)."""
    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise MeshError(f"cannot read the landmark file {path}: {e}") from None
    if isinstance(spec, dict) and "markups" in spec:
        out = {}
        for m in spec["markups"]:
            frame = FROM_FRAME.get(str(m.get("coordinateSystem", "LPS")).upper())
            if frame is None:
                raise MeshError(f"{path}: unknown coordinateSystem "
                                f"{m.get('coordinateSystem')!r}; RAS or LPS")
            for cp in m.get("controlPoints", []):
                out[str(cp.get("label"))] = frame @ np.asarray(cp["position"], float)
        return out
    if not isinstance(spec, dict):
        raise MeshError(f"{path}: expected {{name: [x, y, z]}} or a 3D Slicer markups file")
    return {k: np.asarray(v, float) for k, v in spec.items()}
