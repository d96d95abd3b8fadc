"""3D Slicer markups files (``.mrk.json``): points and planes in the scene's frame.

Slicer writes each markup's control points in its ``coordinateSystem`` (LPS by default, or
RAS); the scene's frame is x left, y anterior, z superior (`FROM_FRAME`). A Plane markup
gives its ``center`` and ``normal`` (Slicer 4.11 and later), or three control points
(``planeType`` 3Points): the plane through them, its normal Slicer's (p1 - p0) × (p2 - p0)
in RAS.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from meshes.errors import MeshError

#: RAS or LPS -> orthodiff (x left, y anterior, z superior).
FROM_FRAME = {"RAS": np.diag([-1.0, 1.0, 1.0]), "LPS": np.diag([1.0, -1.0, 1.0])}


def read_markups(path) -> list | None:
    """The ``markups`` list of a Slicer markups file, or None when the JSON is not one."""
    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise MeshError(f"cannot read {path}: {e}") from None
    if not isinstance(spec, dict) or "markups" not in spec:
        return None
    if not isinstance(spec["markups"], list):
        raise MeshError(f"{path}: 'markups' must be a list")
    return spec["markups"]


def _frame(path, m) -> np.ndarray:
    frame = FROM_FRAME.get(str(m.get("coordinateSystem", "LPS")).upper())
    if frame is None:
        raise MeshError(f"{path}: unknown coordinateSystem {m.get('coordinateSystem')!r}; "
                        "RAS or LPS")
    return frame


def markup_points(path, markups: list) -> dict:
    """{label: (3,)} mm of every control point of ``markups`` (from `read_markups`)."""
    out = {}
    for m in markups:
        frame = _frame(path, m)
        for cp in m.get("controlPoints", []):
            out[str(cp.get("label"))] = frame @ np.asarray(cp["position"], float)
    return out


def markup_planes(path) -> dict:
    """{name: {"point": [x, y, z], "normal": [nx, ny, nz]}} mm of the Plane markups of a
    Slicer markups file. Raises `MeshError` (one line): not a markups file, no plane, a plane
    with a zero normal or without center and normal or three points."""
    markups = read_markups(path)
    if markups is None:
        raise MeshError(f"{path} is not a 3D Slicer markups file")
    out = {}
    for m in markups:
        if not isinstance(m, dict) or m.get("type") != "Plane":
            continue
        name, frame = str(m.get("name", "")), _frame(path, m)
        try:   # in the scene's frame
            if m.get("center") is not None and m.get("normal") is not None:
                point, normal = (frame @ np.asarray(m[k], float) for k in ("center", "normal"))
            else:
                q = np.array([cp["position"] for cp in m.get("controlPoints", [])], float)
                if q.shape[0] < 3:
                    raise MeshError(f"{path}: plane {name!r} has neither a center and a "
                                    "normal nor three control points")
                q = q @ frame.T
                # Slicer's normal is the cross product in RAS, a reflection of the scene's
                # frame: there it is the opposite of the scene's own cross product
                point, normal = q[0], -np.cross(q[1] - q[0], q[2] - q[0])
        except (KeyError, TypeError, ValueError):
            raise MeshError(f"{path}: plane {name!r}: center, normal and control points "
                            "must be 3 numbers each") from None
        if point.shape != (3,) or normal.shape != (3,) \
                or not np.all(np.isfinite(np.r_[point, normal])):
            raise MeshError(f"{path}: plane {name!r}: center and normal must be 3 finite "
                            "numbers each")
        if np.linalg.norm(normal) < 1e-9 * max(1.0, np.abs(point).max()):
            raise MeshError(f"{path}: plane {name!r} has a zero normal (its points are "
                            "collinear)")
        out[name] = {"point": point.tolist(), "normal": normal.tolist()}
    if not out:
        raise MeshError(f"{path} holds no Plane markup")
    return out


def read_landmark_file(path) -> dict:
    """Points {name: (3,)} mm in the scene's frame from a JSON ``{name: [x, y, z]}`` or a
    3D Slicer markups file (``.mrk.json``, `meshes.markups`)."""
    markups = read_markups(path)
    if markups is not None:
        return markup_points(path, markups)
    spec = json.loads(Path(path).read_text())
    if not isinstance(spec, dict):
        raise MeshError(f"{path}: expected {{name: [x, y, z]}} or a 3D Slicer markups file")
    return {k: np.asarray(v, float) for k, v in spec.items()}
