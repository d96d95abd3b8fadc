"""Metal in a CT (brackets, arch wires, fillings, plates, screws): found, reported, and its
streaks taken out before the scan is segmented.

* **Metal**: voxels of at least `METAL_HU`, above any enamel (Cranium.inv3's teeth reach
  2986 HU; metal saturates a 12-bit CT at 3071 HU and reads 8000 HU and more on an extended
  scale).
* **Streaks**: metal's artefacts lie in the axial slices through it (the planes a CT or
  CBCT acquires in). In each run of such slices (one slice more on either side), a voxel
  that differs by more than `STREAK_HU` from the linear interpolation, along z, of the
  clean slices above and below the run takes that interpolation: the anatomy across a few
  millimetres of z, without the streaks (a run at the scan's edge takes its one clean
  neighbour). Soft tissue (±20 HU of noise) and the teeth beside a bracket (which continue
  above and below it) stay as they are; a bright streak no longer makes bone in the lip,
  nor a dark one a hole in it.
  A bright streak across enamel can lift it above `METAL_HU`: it is counted as metal (the
  report's volume is then an upper bound) and reads as a tooth, as it was.
* **The metal itself** reads `FILL_HU` (a tooth): brackets and fillings sit in or on the
  teeth and move with them, so the teeth label (`meshes.teeth`) and the lips' sliding on it
  hold under them.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from meshes.volume import Volume

log = logging.getLogger(__name__)

#: HU at or above which a voxel is metal (module docstring).
METAL_HU = 3000.0
#: A voxel in a metal slice that differs from the clean slices' interpolation by more than
#: this (HU) is a streak: metal streaks read ±500-1000 HU; soft tissue's noise, 10-40 HU.
STREAK_HU = 300.0
#: Slices added to either side of each run of metal slices: a voxel partly in the metal's.
STREAK_SLICES = 1
#: What metal reads once found (HU): enamel's (`meshes.teeth.TEETH_HU` is 2000).
FILL_HU = 2500.0
#: The teeth read as metal throughout when the enamel left (2000 HU up to metal) is less
#: than this share of the metal's volume.
ALL_METAL_SHARE = 0.1
#: Components listed in the report, the largest first.
REPORTED = 12


def _runs(slices: np.ndarray) -> list:
    """(first, last) index of each run of True in slices (K,)."""
    edges = np.diff(np.r_[0, slices.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))


def reduce_metal(volume: Volume) -> tuple:
    """(volume, report): the volume (HU) with its metal at `FILL_HU` and its streaks
    interpolated away (module docstring), itself where it has no metal; the report has the
    metal's volume (mm³), its components (centre mm in the scene's frame, mm³), the z ranges
    corrected and the streak voxels replaced (mm³)."""
    from scipy import ndimage

    from meshes.teeth import TEETH_HU

    metal = volume.array >= METAL_HU
    voxel = float(np.prod(volume.spacing))
    if not metal.any():
        return volume, {"mm3": 0.0}
    a = volume.array.astype(np.float32)   # a copy
    nz = a.shape[2]
    slices = ndimage.binary_dilation(metal.any(axis=(0, 1)), iterations=STREAK_SLICES)
    replaced, ranges, z = 0, [], volume.centres(2)
    for k0, k1 in _runs(slices):
        below, above = k0 - 1, k1 + 1
        if below < 0 and above >= nz:
            continue   # every slice holds metal: nothing clean to interpolate from
        if below < 0 or above >= nz:
            clean = a[:, :, above if below < 0 else below]
            interp = np.repeat(clean[:, :, None], k1 - k0 + 1, axis=2)
        else:
            w = (np.arange(k0, k1 + 1) - below) / (above - below)
            interp = a[:, :, below, None] * (1 - w) + a[:, :, above, None] * w
        part = a[:, :, k0:k1 + 1]
        streak = (np.abs(part - interp) > STREAK_HU) & ~metal[:, :, k0:k1 + 1]
        part[streak] = interp[streak]
        replaced += int(streak.sum())
        ranges.append([round(float(z[k0]), 2), round(float(z[k1]), 2)])
    enamel_mm3 = float(((volume.array >= TEETH_HU) & ~metal).sum()) * voxel
    a[metal] = FILL_HU
    lab, n = ndimage.label(metal, structure=np.ones((3, 3, 3)))
    sizes = np.bincount(lab.ravel())[1:] * voxel
    centres = np.array(ndimage.center_of_mass(metal, lab, np.arange(1, n + 1))) \
        * volume.spacing + volume.origin
    order = np.argsort(-sizes)[:REPORTED]
    mm3 = float(metal.sum()) * voxel
    report = {"mm3": round(mm3, 1), "components": int(n),
              "largest": [{"centre_mm": centres[i].round(1).tolist(),
                           "mm3": round(float(sizes[i]), 1)} for i in order],
              "streak_slices_mm": ranges, "streak_mm3": round(replaced * voxel, 1),
              "teeth_all_metal": bool(enamel_mm3 < ALL_METAL_SHARE * mm3)}
    log.warning("%s: %.0f mm³ of metal in %d parts (the largest at %s mm); its streaks in "
                "z %s mm were interpolated from the slices beside them (%.0f mm³)",
                volume.name, mm3, n, report["largest"][0]["centre_mm"], ranges,
                report["streak_mm3"])
    if report["teeth_all_metal"]:
        log.warning("%s: the teeth read as metal throughout (%.0f mm³ of enamel beside "
                    "%.0f mm³ of metal): their surface is the metal's", volume.name,
                    enamel_mm3, mm3)
    return dataclasses.replace(volume, array=a), report
