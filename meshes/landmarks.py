"""Soft-tissue landmarks on a skin mesh: built on the mid-sagittal profile, or read from files.

The profile is the front-most skin crossing of rays cast forward in the mid-sagittal plane,
every `PROFILE_STEP_MM` from the bottom of the face to the top (its ``s``: how far forward,
``t``: how high, both mm in the plane). On it (Farkas' soft-tissue definitions):

* ``Prn`` (pronasale): the most anterior point of the profile;
* ``N`` (soft-tissue nasion): the deepest hollow above Prn (the one that stands out most),
  where the profile turns forward again to the forehead (absent if the face ends before the
  forehead rises);
* ``Ls`` (labrale superius), ``Li`` (labrale inferius), ``Pg`` (soft-tissue pogonion): the
  three forward bulges below Prn that stand out most, top to bottom; where the nose is not
  in the scan, the lowest of the three is Pg, and the two above it Li and Ls;
* ``Sn`` (subnasale): the vertex of the nasolabial angle, the profile's sharpest concave turn
  between Prn and Ls, or `SN_CHORD_MM` below Prn where Ls is lower or not in the scan; where
  the profile ends before that, Sn is left out (the scene's report says why);
* ``Me`` (soft-tissue menton): the lowest skin point under the chin, from rays cast downward
  in the plane within `MENTON_BACK_MM` behind Pg.

Where a ray meets bone rather than skin (a tooth between parted lips, a nasal bridge whose
thin skin the mesh loses), the profile goes on across it; where it meets a crop face or
nothing, the profile has a gap.

A bulge or a hollow counts where it stands out by `PROMINENCE_MM` (the synthetic heads'
stomion is 0.9 mm deep once voxelised), or on a mesh of a CT's voxels by `STAIRCASE` of a
voxel along the profile's forward axis where that is more (`staircase_mm`: the voxels'
staircase); it is marked at the middle of its part within `PLATEAU_MM` of its extreme (N's
hollow: `HOLLOW_PLATEAU_MM`; Pg's: `CHIN_PLATEAU`), short of the next extreme of the other
kind.

A landmark whose feature the scan does not hold (a field of view that ends at the lip) is
absent, not guessed: the chains of bulges do not cross a gap in the profile longer than
`GAP_MM`, and no bulge or hollow is taken within `GAP_MM` of the end of the profile or of
such a gap.

Tragion (``T_L``, ``T_R``: the notch above the tragus, just in front of the ear canal) is
built where the ear is in the scan (`tragion_landmarks`). On each side the skin's lateral
extent e is mapped over the sagittal plane: the outermost skin crossing of lateral rays cast
from the mid-sagittal plane, every `EAR_BIN_MM` forward and up.

* The ear is where e stands out by more than `PINNA_MM` from e `EAR_FRONT_MM` in front of it
  (the cheek in front of the ear), in parts of at least `EAR_MIN_MM2` that somewhere stand
  out by as much from e `EAR_FRONT_MM` behind them (or have no skin there: the crop), more
  than `EAR_BEHIND_MM` behind the front of the face, above the lips (Li, Pg or Me), and not
  within `GAP_MM` of the skin's top or bottom. A head that only widens backward (the jaw's
  angle behind the cheek) is no ear: the synthetic CT had a tragion on its cheek.
* The ear canal is the largest pit near it: deeper than the cheek in front of it by
  `CANAL_MM`, or where a lateral ray crosses no skin between two that do (the canal open to
  the air).
* The tragion is the skin crossing one bin in front of the canal, at the canal's middle
  height: the canal's front rim, the tragus.

Without an ear and its canal (the synthetic heads, a crop in front of the ears) the landmark
is absent.

Files (`meshes.markups.read_landmark_file`): ``{name: [x, y, z]}`` (mm, the scene's frame)
or a 3D Slicer markups file (``.mrk.json``; points in RAS or LPS as its ``coordinateSystem``
says) override the built ones; each point is projected onto the nearest skin facet and must
lie within the tolerance.
"""

from __future__ import annotations

import numpy as np

from meshes.anatomy import Landmark, intersect_rays
from meshes.errors import MeshError
from meshes.plane import Plane

PROFILE_STEP_MM = 0.5
PROMINENCE_MM = 0.5
#: A mesh of a CT's segmentation follows its voxels' staircase, in bumps of up to half a voxel
#: across the surface. The synthetic head in 2 mm voxels, pitched 8 degrees, meshed at paper:
#: a 0.6 mm bump under the nose passed PROMINENCE_MM, was taken for Ls, and put Li and Pg on
#: Ls and Li (Sn lost). Half a voxel (1 mm) drops it; headsq (3.2 mm: 1.6 mm) and Cranium
#: (0.96 mm) keep every landmark where it was, at coarse and paper.
STAIRCASE = 0.5
GAP_MM = 4.0
#: Sn (module docstring) is sought between Prn and Ls, or the profile this far below Prn
#: where that is nearer (Ls lies 23 mm below Prn on the synthetic heads, 29 mm on Cranium),
#: as the profile's sharpest concave turn, its d²s/dt² smoothed over SN_SMOOTH_MM. Cranium's
#: field of view ends 33 mm below Prn, through the upper lip. Sn was the point farthest
#: behind the chord from Prn to Ls or to the profile's end; but the lip below Sn runs nearly
#: along that chord, and moving the scan by a quarter or half a voxel moved Sn's rest
#: position by 3.5-4.1 mm (medium) and its motion under a 5 mm LeFort I by 0.5-0.9 mm.
SN_CHORD_MM = 25.0
SN_SMOOTH_MM = 1.5
PLATEAU_MM = 0.25
#: N's hollow is flatter than a bulge: Cranium's lies within 0.5 mm of its deepest point over
#: 5-8 mm of profile, and the middle of its part within 0.25 mm followed the skin's staircase.
#: Cranium at paper pitched 5 and 10 degrees, shifted a quarter and half a voxel: N's rest
#: position 1.65, 0.79, 0.30, 0.35 mm from the unmoved scan's, against 2.15, 1.76, 0.42, 0.80
#: at `PLATEAU_MM` (a voxel's diagonal: 2.02 mm).
HOLLOW_PLATEAU_MM = 0.5
#: Pg's plateau on a mesh of voxels, in voxels along the forward axis (`staircase_mm`), where
#: that is more than `PLATEAU_MM`: the chin's front can be flat over more than a voxel, and
#: the staircase then holds it only to within one. The synthetic CT (1.25 mm voxels) at
#: paper, moved a quarter and half a voxel and pitched 5 and 10 degrees: its chin's front
#: is flat within 0.08 mm over 14 mm on the unmoved scan and a slanted staircase on the
#: moved ones; Pg's rest position moved 3.19 mm (a voxel's diagonal: 2.17) at `PLATEAU_MM`,
#: 1.62 at one voxel. Not for the lips, which are curved: a voxel's plateau there moved Ls
#: 5.3 mm on the synthetic CT in 12-bit gray values, and Li down to where the tragion's
#: search (above Li) took the jaw for an ear.
CHIN_PLATEAU = 1.0
MENTON_BACK_MM = 20.0
#: The tragion's construction (module docstring). The pinna stands out from the side of the
#: head by 15-25 mm (headsq: 7 voxels of 3.2 mm), the cheek in front of it by far less than
#: PINNA_MM over EAR_FRONT_MM. The tragion lies 95-115 mm behind pronasale in adults (Farkas'
#: norms); EAR_BEHIND_MM leaves room for a face front cut through the nose (headsq: 90 mm)
#: and keeps the forehead and cheeks, which narrow forward, out of the search (the synthetic
#: head's temples, 61-70 mm behind Prn, stand out by 8 mm over EAR_FRONT_MM).
EAR_BIN_MM = 3.0
PINNA_MM = 6.0
EAR_FRONT_MM = 15.0
EAR_BEHIND_MM = 75.0
EAR_MIN_MM2 = 60.0
CANAL_MM = 5.0


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


def staircase_mm(voxel_mm=None, frame=None) -> float:
    """A voxel's depth (mm) along the head's forward axis, on a mesh made from voxels of
    ``voxel_mm`` (3,) mm (None: not from voxels: 0), its head frame ``frame``
    (`meshes.frame.HeadFrame`, None: the identity): the profile's staircase (module docstring)."""
    if voxel_mm is None:
        return 0.0
    forward = np.array([0.0, 1.0, 0.0]) if frame is None else frame.rotation[:, 1]
    return float(np.linalg.norm(np.asarray(voxel_mm) * forward))


def _extrema(s, sign: float, prominence: float):
    """(indices, prominences mm) of the local maxima of sign * s that stand out by
    ``prominence`` mm."""
    from scipy.signal import find_peaks

    found, props = find_peaks(sign * s, prominence=prominence)
    return found, props["prominences"]


def profile_landmarks(points: np.ndarray, skin: np.ndarray, plane: Plane,
                      surface=None, staircase: float = 0.0,
                      notes: dict | None = None) -> dict:
    """Landmarks {name: `Landmark`} on the skin facets ``skin`` (S, 3) over ``points`` (N, 3),
    built on the profile in ``plane`` (module docstring). ``surface``: (facets (B, 3), is_bone
    (B,)) the rest of the boundary; a ray that misses the skin and meets bone first bridges
    the profile (a free crop face or a held one in front of it does not). ``staircase``: a
    voxel's depth (mm) along the profile (`staircase_mm`). ``notes`` (a dict, filled):
    why a landmark the scan seems to hold was left out."""
    notes = {} if notes is None else notes
    prominence = max(PROMINENCE_MM, STAIRCASE * staircase)
    o, a, u = _plane_axes(plane)
    tris = skin[_crossing(points, skin, plane)]
    other, is_bone = (np.empty((0, 3), dtype=np.int64), np.empty(0, dtype=bool)) \
        if surface is None else surface
    cut = _crossing(points, other, plane)
    other, is_bone = other[cut], is_bone[cut]
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
    bridged = np.zeros(len(ok), dtype=bool)
    for i in np.flatnonzero(~ok) if is_bone.any() else ():
        hit = intersect_rays(points, other, o + s0 * a + ts[i] * u, a)
        bridged[i] = hit is not None and is_bone[hit[0]]
    # top to bottom; a run is a stretch with no gap longer than GAP_MM (a crop, a cut field
    # of view). Bone in the profile does not end a run: a tooth between parted lips, the
    # nasal bridge where the mesh loses its thin skin (Cranium: 2-5 mm of bone there, more
    # or less with the head's tilt)
    gap = np.zeros(len(ok), dtype=bool)
    missing = np.flatnonzero(~ok & ~bridged)
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
    peaks, hollows, stands_out = [], [], {}
    edge = int(np.ceil(GAP_MM / PROFILE_STEP_MM))   # the rounded rim of a cut or crop face
    for r in np.unique(run):
        idx = np.flatnonzero(run == r)
        for marks, sign in ((peaks, 1.0), (hollows, -1.0)):
            found_r, prom = _extrema(s[idx], sign, prominence)
            keep = (found_r >= edge) & (found_r < len(idx) - edge)
            marks += list(idx[found_r[keep]])
            stands_out.update(zip(idx[found_r[keep]], prom[keep]))
    found = {}
    prn = int(np.argmax(s))
    lips = ("Ls", "Li", "Pg")
    if prn in peaks:   # the nose is in the scan: the bulges below it, from the nose down
        found["Prn"] = prn
        upper = [j for j in hollows if j < prn and run[j] == run[prn]]
        found["N"] = max(upper, key=stands_out.get) if upper else None
        chain = _most_prominent([j for j in peaks if j > prn and run[j] == run[prn]], stands_out)
        found.update(zip(lips, chain))
        lower = np.flatnonzero((run == run[prn]) & (ts <= ts[prn] - SN_CHORD_MM))
        ends = [j for j in (found.get("Ls"), lower[0] if len(lower) else None) if j is not None]
        end = min(ends, default=None)
        if end is None:
            notes["Sn"] = (f"the profile ends {ts[prn] - ts[run == run[prn]].min():.1f} mm "
                           f"below Prn, without Ls (field of view): Sn needs {SN_CHORD_MM:g} mm")
        between = np.arange(prn + edge, prn if end is None else end - edge)
        if len(between):   # the profile's sharpest concave turn
            found["Sn"] = int(between[np.argmax(_bend(s, ts, prn, end)[between - prn])])
    elif peaks:   # no nose: from the chin up, Pg the lowest bulge
        last = max(peaks)
        chain = _most_prominent([j for j in peaks if run[j] == run[last]], stands_out)[::-1]
        found.update(zip(lips[::-1], chain))
    plateaus = {"N": HOLLOW_PLATEAU_MM, "Pg": max(PLATEAU_MM, CHIN_PLATEAU * staircase)}
    for name in ("Prn", "N", "Ls", "Li", "Pg"):   # a flat bulge or hollow: its middle
        if found.get(name) is not None:
            sign, stops = (-1.0, peaks) if name == "N" else (1.0, hollows)
            found[name] = _middle(s, run, found[name], sign, plateaus.get(name, PLATEAU_MM),
                                  stops)
    out = {name: Landmark(tris[hits[i][0]].copy(), hits[i][1].copy())
           for name, i in found.items() if i is not None}
    if found.get("Pg") is not None:
        me = _menton(points, tris, o, a, u, s[found["Pg"]], ts[found["Pg"]])
        if me is not None:
            out["Me"] = me
    return out


def skin_landmarks(points: np.ndarray, skin: np.ndarray, plane: Plane, surface=None,
                   staircase: float = 0.0, notes: dict | None = None) -> dict:
    """Every landmark the scan holds {name: `Landmark`}: the profile's (``surface``,
    ``staircase`` and ``notes``: as in `profile_landmarks`), and tragion searched above the
    lowest of Li, Pg and Me that the profile found (module docstring)."""
    found = profile_landmarks(points, skin, plane, surface, staircase, notes)
    _, _, u = _plane_axes(plane)
    floor = max(((found[k].position(points) - plane.point) @ u for k in ("Li", "Pg", "Me")
                 if k in found), default=-np.inf)
    return {**found, **tragion_landmarks(points, skin, plane, floor)}


def tragion_landmarks(points: np.ndarray, skin: np.ndarray, plane: Plane,
                      t_floor: float = -np.inf) -> dict:
    """``T_L`` and ``T_R`` {name: `Landmark`} where the ear is on the skin facets ``skin`` (S, 3)
    over ``points`` (N, 3); ``plane`` is the mid-sagittal plane, its normal pointing to the
    patient's left or right. Searched above the height ``t_floor`` (mm in the plane, from its
    point; the lips: below them the neck behind the jaw stands out from the chin as an ear
    does from the cheek), and not within `GAP_MM` of the skin's top or bottom (a crop face's
    rim; module docstring)."""
    o, a, u = _plane_axes(plane)
    n = np.asarray(plane.normal, float) * np.sign(plane.normal[0])   # to the patient's left
    rel = points - o
    d, s, t = rel @ n, rel @ a, rel @ u
    on_skin = np.unique(skin)
    s_front = s[on_skin].max()
    s_bins = np.arange(s[on_skin].min() + EAR_BIN_MM / 2, s_front, EAR_BIN_MM)
    t_bins = np.arange(max(t[on_skin].min() + GAP_MM, t_floor) + EAR_BIN_MM / 2,
                       t[on_skin].max() - GAP_MM, EAR_BIN_MM)
    shift = int(round(EAR_FRONT_MM / EAR_BIN_MM))
    out = {}
    for name, sign in (("T_L", 1.0), ("T_R", -1.0)):
        e = np.full((len(s_bins), len(t_bins)), np.nan)   # lateral extent, mm
        hits = {}
        for j, t_j in enumerate(t_bins):   # the triangles on this side at this height
            row = skin[(t[skin].min(axis=1) <= t_j) & (t[skin].max(axis=1) >= t_j) &
                       ((sign * d[skin]).max(axis=1) > 0)]
            if len(row) == 0:
                continue
            for i, s_i in enumerate(s_bins):
                hit = intersect_rays(points, row, o + s_i * a + t_j * u, sign * n)
                if hit is not None:
                    e[i, j] = abs(hit[1] @ d[row[hit[0]]])
                    hits[i, j] = (row[hit[0]], hit[1])
        front, behind = np.full_like(e, np.nan), np.full_like(e, np.nan)
        front[:-shift], behind[shift:] = e[shift:], e[:-shift]   # EAR_FRONT_MM either way
        with np.errstate(invalid="ignore"):
            ear = (e - front > PINNA_MM) & (s_bins[:, None] < s_front - EAR_BEHIND_MM)
            drops = ~(e - behind <= PINNA_MM)   # the head behind narrower, or out of view
        parts, sizes = _components(ear)
        pinna = np.unique(parts[ear & drops])
        big = np.isin(parts, np.intersect1d(
            pinna, 1 + np.flatnonzero(sizes * EAR_BIN_MM ** 2 >= EAR_MIN_MM2)))
        if not big.any():
            continue
        canal = _canal(e, front, big, shift)
        if canal is None:
            continue
        i_s, i_t = canal
        j = i_t[np.argmin(np.abs(i_t - np.median(i_t)))]   # its middle row
        i = int(i_s[i_t == j].max()) + 1   # the rim in front of it
        if (i, int(j)) in hits:
            facet, weights = hits[i, int(j)]
            out[name] = Landmark(facet.copy(), weights.copy())
    return out


def _canal(e, front, ear, shift: int):
    """Bin indices (i_s, i_t) of the ear canal: the largest connected pit, in the box of the
    ear bins ``ear`` grown by ``shift`` bins forward, deeper than the cheek in front of it
    (``front``) by `CANAL_MM`, or where the lateral ray misses the skin between two hits in
    its row (the canal open to the air); None without one."""
    i_s, i_t = np.nonzero(ear)
    box = np.zeros_like(ear)
    box[i_s.min():i_s.max() + shift + 1, i_t.min():i_t.max() + 1] = True
    hit = np.isfinite(e)
    behind = np.maximum.accumulate(hit, axis=0)   # a hit at or behind, in the row
    ahead = np.maximum.accumulate(hit[::-1], axis=0)[::-1]
    with np.errstate(invalid="ignore"):
        pit = box & ((~hit & behind & ahead) | (e < front - CANAL_MM))
    parts, sizes = _components(pit)
    return np.nonzero(parts == 1 + int(np.argmax(sizes))) if len(sizes) else None


def _components(mask):
    """The connected parts of a boolean grid: labels (same shape, 0 outside, part k is k) and
    each part's size in cells (K,)."""
    from scipy import ndimage

    parts, count = ndimage.label(mask)
    return parts, ndimage.sum(mask, parts, index=np.arange(1, count + 1))


def _most_prominent(marks: list, prominence: dict, n: int = 3) -> list:
    """The ``n`` of ``marks`` (profile samples) that stand out most, top to bottom: the lips
    and chin, not a bump between them (the synthetic head's 0.4 mm bulge under Sn, which
    one voxelisation meshes 1.0 mm high and the next flat, took Ls's place)."""
    return sorted(sorted(marks, key=prominence.get, reverse=True)[:n])


def _bend(s, ts, i: int, j: int) -> np.ndarray:
    """d²s/dt² (1/mm) of the profile from sample i to j (j - i + 1,), smoothed over
    `SN_SMOOTH_MM`: largest where the columella turns into the upper lip."""
    from scipy import ndimage

    g = ndimage.gaussian_filter1d(s[i:j + 1], SN_SMOOTH_MM / PROFILE_STEP_MM, mode="nearest")
    return np.gradient(np.gradient(g, ts[i:j + 1]), ts[i:j + 1])


def _middle(values, run, i: int, sign: float, plateau: float = PLATEAU_MM, stops=()) -> int:
    """The middle sample of the stretch of i's run around the extremum i where sign * values
    stays within ``plateau`` mm of it, short of the samples ``stops`` (the extrema of the other
    kind): the most anterior (or deepest) point of a flat bulge is where its flat part is, not
    wherever 0.1 mm of noise puts it."""
    v = sign * np.asarray(values)
    stop = np.zeros(len(v), dtype=bool)
    stop[list(stops)] = True
    lo = hi = i
    while lo > 0 and run[lo - 1] == run[i] and not stop[lo - 1] and v[lo - 1] >= v[i] - plateau:
        lo -= 1
    while hi < len(v) - 1 and run[hi + 1] == run[i] and not stop[hi + 1] and \
            v[hi + 1] >= v[i] - plateau:
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
