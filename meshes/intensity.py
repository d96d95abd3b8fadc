"""A scan's intensities read from its own histogram: a CBCT's gray values to HU.

A CBCT's values are not HU: each scanner maps attenuation to its own scale (an offset, a
gain, 12-bit storage, the air clipped at 0). Every threshold of the CT pipeline (skin, bone,
teeth, fat, metal, the head frame's air) is in HU, so a scan is first put on HU by three
classes found in its histogram:

* **air**: the mode below the lower of the whole volume's two three-class Otsu splits;
* **soft tissue**: the mode between the two;
* **bone**: the median of the upper Otsu class of the voxels above the skin level (halfway
  between air and soft tissue).

These classes survive what scanners do: Otsu's split is equivariant under a linear map, a
median and a mode under any monotone one, and the soft-tissue and bone classes lie above a
clipping of the air. The map to HU goes through the classes' reference HU (`AIR_HU`,
`SOFT_HU`, `BONE_HU`):

* linear through air and bone where soft tissue falls on that line (within `HU_TOLERANCE`):
  a scanner's gain and offset, found within a few HU (air and bone are 1866 HU apart, and
  soft tissue's own HU differs between patients: Cranium 23, headsq 57);
* piecewise linear through all three where it does not (a non-linear scale);
* through soft tissue and bone where the air is clipped (`CLIPPED_SHARE`);

and extended beyond the outer two by their slope.

Metal is decided in the scan's own values (`Intensity.metal_scan`), since nothing anchors the
map above bone: a 12-bit scale puts Cranium's enamel (2986 HU) 85 HU below metal's 3071, and
over 2000 HU of extrapolation a scale's curvature moves it more (the upper segment's slope
read it 3208 HU under gamma 1.25). A voxel is metal where the scan saturates (at least
`SATURATED` voxels at its maximum, above bone), or where it reaches `meshes.metal.METAL_HU`
under the lower of two extensions above bone: the upper segment's slope, and the slope at
bone of the parabola through the three classes. Other voxels read below `METAL_HU`.

A scan whose classes already lie at those HU (`HU_TOLERANCE`) is taken as HU and left as it
is (source ``"hu"``); any other is mapped (``"estimated"``); a scene file's ``"calibration":
"none"`` takes its values as they are, thresholds included (``"given"``). A volume with no
bone class above its soft tissue is refused with one line.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from meshes.errors import MeshError
from meshes.metal import METAL_HU
from meshes.volume import Volume, read_volume

#: Reference HU of the classes. Soft tissue: the histogram's mode between the Otsu splits,
#: Cranium.inv3 24 HU, headsq 57 HU (their mean, 40, is also the synthetic CT's lean tissue).
#: Bone: the median of the upper Otsu class of the voxels above the skin level, Cranium 870,
#: headsq 862 HU (0.96 and 3.2 mm voxels), so 866; the synthetic CT's 1000 HU bone lies
#: within the tolerance below.
AIR_HU, SOFT_HU, BONE_HU = -1000.0, 40.0, 866.0
#: A scan is in HU when its soft-tissue and bone classes lie this close (HU) to the references
#: and its minimum is at most -900 (air): Cranium (16, 4 HU off), headsq (17, 4), the
#: synthetic CT (0, 134) are.
HU_TOLERANCE = {"soft": 60.0, "bone": 200.0, "air_max": -900.0}
#: The air is clipped (no anchor) when more than this share of the voxels below the lower split
#: sit at the volume's minimum (a CBCT mapped to gray values and clipped at 0).
CLIPPED_SHARE = 0.5
#: The bone class must lie at least this far above soft tissue, as a share of soft tissue's
#: distance above the air (or the clip): 0.82 in HU; a volume without bone gives about 0.05.
MIN_BONE_CONTRAST = 0.3
#: Values below this are a CT's padding beyond its field of view (-2000, -3024), not air:
#: left out of the histogram (a post-operative CT's, `inverse.postop.FOV_PAD_HU`).
PAD_HU = -1500.0
#: A scan saturates (its top is metal) when at least this many voxels hold its maximum, and it
#: lies above bone: a bracket is some 30 voxels at 1 mm; Cranium's maximum holds 1 voxel,
#: in HU and in every test mapping.
SATURATED = 8
#: Histogram bins for the modes, and the voxels sampled (evenly, at most SAMPLES: a CBCT's
#: 152 M voxels as 2 M float64, 16 MB).
BINS, SAMPLES = 512, 2_000_000


@dataclasses.dataclass(frozen=True)
class Intensity:
    """How a scan's values became HU.

    Attributes:
        source: ``"hu"`` (in HU already), ``"estimated"`` (mapped by its classes) or
            ``"given"`` (taken as they are: the scene file's ``"calibration": "none"``).
        classes: class centres in the scan's own values: ``air``, ``soft``, ``bone``.
        anchors: (scan values (K,), HU (K,)) of the piecewise-linear map.
        noise_hu: the soft-tissue class's spread (robust SD), HU; None where not estimated.
        metal_scan: the scan value from which a voxel is metal (module docstring); None
            where the map is the identity.
    """

    source: str
    classes: dict
    anchors: tuple
    noise_hu: float | None
    metal_scan: float | None = None

    def to_hu(self, values) -> np.ndarray:
        """The HU of scan values (any shape): piecewise linear and extended linearly, metal
        (`metal_scan`) at least `METAL_HU` and every other value below it."""
        xp, fp = (np.asarray(a, float) for a in self.anchors)
        v = np.asarray(values, np.float32)
        lo = (fp[1] - fp[0]) / (xp[1] - xp[0])
        hi = (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
        out = np.interp(v, xp, fp).astype(np.float32)
        out = np.where(v < xp[0], fp[0] + (v - xp[0]) * lo, out)
        out = np.where(v > xp[-1], fp[-1] + (v - xp[-1]) * hi, out)
        if self.metal_scan is not None:
            out = np.where(v >= self.metal_scan, np.maximum(out, METAL_HU),
                           np.minimum(out, METAL_HU - 1.0))
        return out.astype(np.float32)

    def to_scan(self, hu: float) -> float:
        """The scan value of an HU value (the map's inverse)."""
        xp, fp = (np.asarray(a, float) for a in self.anchors)
        if hu == METAL_HU and self.metal_scan is not None:
            return float(self.metal_scan)
        if hu < fp[0]:
            return float(xp[0] + (hu - fp[0]) * (xp[1] - xp[0]) / (fp[1] - fp[0]))
        if hu > fp[-1]:
            return float(xp[-1] + (hu - fp[-1]) * (xp[-1] - xp[-2]) / (fp[-1] - fp[-2]))
        return float(np.interp(hu, fp, xp))

    def report(self, thresholds: dict | None = None, given: tuple = ()) -> dict:
        """JSON-ready: the source, class centres, the noise and each threshold (HU) with its
        scan value and where it came from (``given``: the names the scene file gave)."""
        out = {"source": self.source, "classes": {k: round(float(v), 2)
                                                  for k, v in self.classes.items()},
               "noise_hu": None if self.noise_hu is None else round(self.noise_hu, 1)}
        default = {"hu": "HU default", "estimated": "estimated", "given": "given"}[self.source]
        out["thresholds"] = {k: {"hu": float(v), "scan": _finite(self.to_scan(v)),
                                 "source": "given" if k in given else default}
                             for k, v in (thresholds or {}).items()}
        return out


def _finite(x: float):
    """x rounded to 0.01, or None where no scan value reaches it (JSON has no infinity)."""
    return round(x, 2) if np.isfinite(x) else None


def _metal_scan(flat: np.ndarray, xp: list, fp: list) -> float:
    """The scan value from which a voxel of ``flat`` (N,) is metal, for the map through the
    anchors (xp, fp) (module docstring); +inf where none is."""
    top = float(flat.max())
    s = np.diff(fp) / np.diff(xp)
    slope = s[-1]
    if len(s) > 1:   # the parabola's slope at the last anchor
        m = (np.asarray(xp[:-1]) + np.asarray(xp[1:])) / 2
        tangent = s[-1] + (s[-1] - s[-2]) * (xp[-1] - m[-1]) / (m[-1] - m[-2])
        slope = min(slope, tangent) if tangent > 0 else slope
    reach = xp[-1] + (METAL_HU - fp[-1]) / slope
    if top > xp[-1] and np.count_nonzero(flat == top) >= SATURATED:
        reach = min(reach, top)
    return float(reach) if reach <= top else float("inf")


def _mode(values: np.ndarray) -> tuple:
    """(mode, robust SD) of values (K,): the smoothed histogram's peak over their own range,
    and its half width at half maximum / 1.177."""
    from scipy import ndimage

    lo, hi = np.percentile(values, [0.5, 99.5])
    if hi <= lo:
        return float(lo), 0.0
    h, e = np.histogram(values, bins=BINS, range=(lo, hi))
    h = ndimage.gaussian_filter1d(h.astype(float), 1.5)
    c = (e[:-1] + e[1:]) / 2
    k = int(np.argmax(h))
    half = h >= h[k] / 2
    a, b = k, k
    while a > 0 and half[a - 1]:
        a -= 1
    while b < len(h) - 1 and half[b + 1]:
        b += 1
    return float(c[k]), float((c[b] - c[a] + (e[1] - e[0])) / 2 / 1.177)


def estimate(volume: Volume) -> Intensity:
    """The scan's classes and its map to HU (module docstring); `MeshError` with one line when
    the histogram has no bone class."""
    from skimage.filters import threshold_multiotsu, threshold_otsu

    flat = volume.array.ravel()
    v = flat[::max(1, -(-flat.size // SAMPLES))].astype(np.float64)
    v = v[v > PAD_HU] if np.any(v > PAD_HU) else v   # beyond a CT's field of view
    v = v[v <= np.percentile(v, 99.9)]   # metal and its streaks off the histogram's scale
    if v.min() == v.max():
        raise MeshError(f"no body found in {volume.name}: it holds one value, {v.min():g}")
    if len(np.unique(v)) < 3:
        raise MeshError(f"{volume.name} has no bone class in its histogram: it holds two values "
                        f"({v.min():g}, {v.max():g}); is it a head CT?")
    split, top = threshold_multiotsu(v, classes=3)
    low = v[v <= split]
    air, _ = _mode(low)
    soft, noise = _mode(v[(v > split) & (v <= top)])
    clipped = np.mean(low == v.min()) > CLIPPED_SHARE
    body = v[v > (air + soft) / 2]
    above = body[body > threshold_otsu(body)] if np.ptp(body) > 0 else body[:0]
    bone = float(np.median(above)) if len(above) else soft
    floor = v.min() if clipped else air
    if soft <= floor or (bone - soft) < MIN_BONE_CONTRAST * (soft - floor):
        raise MeshError(f"{volume.name} has no bone class in its histogram (air {air:g}, soft "
                        f"tissue {soft:g}, the brightest class {bone:g}): is it a head CT?")
    classes = {"air": air, "soft": soft, "bone": bone}
    xp, fp = [soft, bone], [SOFT_HU, BONE_HU]
    if not clipped:
        soft_on_line = AIR_HU + (soft - air) * (BONE_HU - AIR_HU) / (bone - air)
        linear = abs(soft_on_line - SOFT_HU) <= HU_TOLERANCE["soft"]
        xp, fp = ([air, bone], [AIR_HU, BONE_HU]) if linear else \
            ([air, *xp], [AIR_HU, *fp])
    tol = HU_TOLERANCE
    is_hu = abs(soft - SOFT_HU) <= tol["soft"] and abs(bone - BONE_HU) <= tol["bone"] \
        and v.min() <= tol["air_max"]
    if is_hu:
        return Intensity("hu", classes, ([0.0, 1.0], [0.0, 1.0]), noise)
    scale = (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])   # HU per scan unit (the upper segment)
    return Intensity("estimated", classes, (xp, fp), noise * scale, _metal_scan(flat, xp, fp))


def as_given() -> Intensity:
    """The identity map: the values are taken as they are (``"calibration": "none"``)."""
    return Intensity("given", {}, ([0.0, 1.0], [0.0, 1.0]), None)


def calibrated(volume: Volume, intensity: Intensity) -> Volume:
    """The volume in HU (float32), or itself where the map is the identity."""
    if intensity.source != "estimated":
        return volume
    return dataclasses.replace(volume, array=intensity.to_hu(volume.array))


def read_ct(path, calibration: str = "auto") -> tuple:
    """(volume in HU, `Intensity`) of a CT or CBCT file (`meshes.volume.read_volume`);
    ``calibration``: ``"auto"`` (module docstring) or ``"none"``."""
    if calibration not in ("auto", "none"):
        raise MeshError(f"calibration: expected 'auto' or 'none', got {calibration!r}")
    volume = read_volume(path)
    intensity = estimate(volume) if calibration == "auto" else as_given()
    return calibrated(volume, intensity), intensity
