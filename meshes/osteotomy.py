"""Osteotomies as planes: which bone facet belongs to which segment.

Shared by the synthetic heads and the CT pipeline. A plane is a point and a normal (mm, in
the scene's frame x left, y anterior, z superior); the signed distance ``d = (X - P)·n`` says
on which side a facet midpoint lies. The cuts (the JSON keys of an osteotomy file):

* ``lefort1`` (normal up): the maxilla lies below it (d < 0);
* ``midsagittal`` (normal to the patient's left): splits the maxilla into ``maxilla_L``
  (d ≥ 0) and ``maxilla_R``, and the mandible's sides for the ramus cuts; a cut plane only
  (the landmarks are built on the head frame's mid-sagittal plane, `meshes.frame`). A CT
  scene file may leave it out: the head frame's then serves;
* ``occlusal`` (normal up): the maxilla above it, the mandible below;
* ``ramus_L``, ``ramus_R`` (normal anterior): the BSSO cut of each side; the distal segment
  ``mandible`` lies in front (d > 0), the proximal segments behind stay fixed. Without an
  ``occlusal`` plane there is no mandible segment;
* ``pterygomaxillary`` (normal anterior, optional): the posterior end of the LeFort I
  segment; by default the ramus planes bound the maxilla too.

A plane may also come from a 3D Slicer markups file (`resolve_plane_files`).

Bone within ``band_mm / 2`` of a cut (and, behind a ramus cut, ``split_mm`` back: the sagittal
split's overlap) is left free: the elevated periosteum. A moving segment that borders fixed bone
makes the Jacobian indefinite (DESIGN.md, measured); see `meshes.synthetic` for the split.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from meshes.anatomy import FIXED, FREE_BONE, SEGMENT_TAG0
from meshes.errors import MeshError
from meshes.plane import Plane

SEGMENTS = ("mandible", "maxilla_L", "maxilla_R")
SEGMENT_TAGS = {name: SEGMENT_TAG0 + i for i, name in enumerate(SEGMENTS)}
PLANES = ("lefort1", "midsagittal", "occlusal", "ramus_L", "ramus_R", "pterygomaxillary")
BAND_MM, SPLIT_MM = 10.0, 15.0
#: The axis each cut's normal points along (module docstring): a plane drawn in 3D Slicer
#: has no side, so its normal is turned to this one.
NORMAL_AXIS = {"lefort1": 2, "occlusal": 2, "midsagittal": 0, "ramus_L": 1, "ramus_R": 1,
               "pterygomaxillary": 1}


def resolve_plane_files(spec: dict, folder) -> dict:
    """A scene file's planes from 3D Slicer markups files (paths relative to ``folder``):
    ``"planes": "cuts.mrk.json"`` (or a list of files) gives each of their Plane markups
    named like a cut (`PLANES`); a cut given as a file name, ``"lefort1": "le.mrk.json"``,
    is that file's plane of the cut's name, or its only plane. A cut given as a point and a
    normal wins over a ``"planes"`` file. Returns the spec with points and normals."""
    from meshes.markups import markup_planes

    out = dict(spec)
    drawn = set()   # the cuts taken from markups
    files = out.pop("planes", None)
    files = [files] if isinstance(files, str) else files
    if files is not None and (not isinstance(files, list)
                              or not all(isinstance(f, str) for f in files)):
        raise MeshError(f"'planes' must name 3D Slicer markups files, got {spec['planes']!r}")
    for f in files or []:
        planes = markup_planes(Path(folder) / f)
        named = {k: v for k, v in planes.items() if k in PLANES}
        if not named:
            raise MeshError(f"{f}: no plane is named as a cut {list(PLANES)}; its planes: "
                            f"{sorted(planes)}")
        for k, v in named.items():
            if k not in out:
                out[k] = v
                drawn.add(k)
    for k in PLANES:
        if isinstance(out.get(k), str):
            planes = markup_planes(Path(folder) / out[k])
            if k not in planes and len(planes) != 1:
                raise MeshError(f"{out[k]}: no plane named {k!r} among {sorted(planes)}")
            out[k] = planes[k] if k in planes else next(iter(planes.values()))
            drawn.add(k)
    for k in drawn:   # a plane drawn in Slicer has no side: the cut's convention
        n = np.asarray(out[k]["normal"], float)
        out[k] = dict(out[k], normal=(n if n[NORMAL_AXIS[k]] >= 0 else -n).tolist())
    return out


@dataclasses.dataclass(frozen=True)
class Osteotomies:
    """The cuts of a double-jaw (or LeFort I only) treatment, as planes (module docstring)."""

    midsagittal: Plane | None = None
    lefort1: Plane | None = None
    occlusal: Plane | None = None
    ramus_L: Plane | None = None
    ramus_R: Plane | None = None
    pterygomaxillary: Plane | None = None
    band_mm: float = BAND_MM
    split_mm: float = SPLIT_MM

    @classmethod
    def from_dict(cls, spec: dict, where: str = "osteotomies") -> "Osteotomies":
        if not isinstance(spec, dict):
            raise MeshError(f"{where}: expected a JSON object of planes")
        planes = {k: Plane.of(k, spec[k]) for k in PLANES if spec.get(k) is not None}
        if ("ramus_L" in planes) != ("ramus_R" in planes):
            raise MeshError(f"{where}: give both ramus cuts, 'ramus_L' and 'ramus_R', or none")
        if "ramus_L" in planes and "occlusal" not in planes:
            raise MeshError(f"{where}: the ramus cuts need the 'occlusal' plane that separates "
                            "the mandible from the maxilla")
        if "lefort1" in planes and "ramus_L" not in planes and "pterygomaxillary" not in planes:
            raise MeshError(f"{where}: the LeFort I segment needs a posterior end: "
                            "'pterygomaxillary' or the ramus cuts")
        if "lefort1" not in planes and "ramus_L" not in planes:
            raise MeshError(f"{where}: no segment: give 'lefort1' or the ramus cuts")
        widths = {}
        for key, default in (("band_mm", BAND_MM), ("split_mm", SPLIT_MM)):
            w = spec.get(key, default)
            if not isinstance(w, (int, float)) or not np.isfinite(w) or w < 0:
                raise MeshError(f"{where}: {key} must be a finite number >= 0, got {w!r}")
            widths[key] = float(w)
        return cls(**planes, **widths)

    @classmethod
    def read(cls, path) -> "Osteotomies":
        try:
            spec = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise MeshError(f"cannot read the osteotomy file {path}: {e}") from None
        return cls.from_dict(spec, str(path))

    def with_midsagittal(self, plane: Plane) -> "Osteotomies":
        """These cuts with ``plane`` as the midsagittal cut where they have none."""
        if self.midsagittal is not None:
            return self
        return dataclasses.replace(self, midsagittal=plane)

    def segments(self) -> dict:
        """Segment name -> facet tag of the segments these cuts make."""
        names = (["mandible"] if self.ramus_L is not None else []) + \
            (["maxilla_L", "maxilla_R"] if self.lefort1 is not None else [])
        return {n: SEGMENT_TAGS[n] for n in names}

    def classify(self, mid: np.ndarray) -> np.ndarray:
        """Facet tags (K,) of bone facets with midpoints ``mid`` (K, 3): a segment tag,
        `FREE_BONE` or `FIXED`."""
        b = self.band_mm / 2
        k = len(mid)
        d_mid = self.midsagittal.distance(mid)
        left = d_mid >= 0
        tags = np.full(k, FIXED, dtype=np.int32)
        near = np.zeros(k, dtype=bool)
        if self.ramus_L is not None:
            d_ramus = np.where(left, self.ramus_L.distance(mid), self.ramus_R.distance(mid))
            front = d_ramus > 0
            near |= (d_ramus > -self.split_mm) & (d_ramus < b)
        else:
            front = np.ones(k, dtype=bool)
        if self.pterygomaxillary is not None:
            d_ptm = self.pterygomaxillary.distance(mid)
            front_max, near_max = d_ptm > 0, np.abs(d_ptm) < b
        else:
            front_max, near_max = front, np.zeros(k, dtype=bool)
        if self.occlusal is not None:
            d_occ = self.occlusal.distance(mid)
            above = d_occ >= 0
            near |= (np.abs(d_occ) < b) & front
        else:
            above = np.ones(k, dtype=bool)
        if self.ramus_L is not None:
            tags[front & ~above] = SEGMENT_TAGS["mandible"]
        if self.lefort1 is not None:
            d_lf = self.lefort1.distance(mid)
            maxilla = front_max & above & (d_lf < 0)
            tags[maxilla & left] = SEGMENT_TAGS["maxilla_L"]
            tags[maxilla & ~left] = SEGMENT_TAGS["maxilla_R"]
            near |= np.abs(d_lf) < b
            near |= maxilla & (np.abs(d_mid) < b) | near_max & above & (d_lf < 0)
        tags[near] = FREE_BONE
        return tags

    def edges(self) -> list:
        """The level sets (plane, d mm) where `classify` changes a facet's tag: each cut's
        free band's edges, d = ±``band_mm``/2 (behind a ramus cut, -``split_mm``)."""
        b = self.band_mm / 2
        out = []
        for name in PLANES:
            plane = getattr(self, name)
            if plane is not None:
                lo = -self.split_mm if name.startswith("ramus") else -b
                out += [(plane, lo), (plane, b)]
        return out

    def check_cuts(self, bone_points: np.ndarray):
        """Raise `MeshError` for a plane that cuts no bone (all of ``bone_points`` (K, 3) on
        one side of it)."""
        for name in PLANES:
            plane = getattr(self, name)
            if plane is None:
                continue
            d = plane.distance(bone_points)
            if d.min() >= 0 or d.max() <= 0:
                raise MeshError(f"the {name} plane through {np.round(plane.point, 1).tolist()} "
                                f"with normal {np.round(plane.normal, 3).tolist()} cuts no bone "
                                f"(all bone lies {'above' if d.min() >= 0 else 'below'} it, "
                                f"{min(abs(d.min()), abs(d.max())):.1f} mm away at least)")
