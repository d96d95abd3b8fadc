"""Rigid 4×4 transforms of bone segments, and the files VSP software exchanges them in.

A transform here is in the *modelling* convention: it moves a segment's rest points,
``x = T[:3, :3] X + T[:3, 3]`` (mm, the scene's frame: x left, y anterior, z superior).

Files:

* JSON: ``{"mandible": [[4×4]], "maxilla_L": [[4×4]], ...}``, modelling convention, mm,
  the scene's frame; or one 4×4 (an occlusion).
* ITK transform text (``.tfm``/``.txt``, "Insight Transform File V1.0", as 3D Slicer and
  SimpleITK write a linear transform): ``AffineTransform_double_3_3`` (or
  ``MatrixOffsetTransformBase``, ``Rigid3DTransform``): 12 parameters (the 3×3 matrix row by
  row, then the translation) and the centre as fixed parameters. ITK stores the
  *resampling* transform (fixed to moving) in LPS: the segment's motion is its inverse,
  taken to our frame by ``F = diag(1, -1, 1)`` (LPS y is posterior, ours anterior; the
  origin is shared). `write_itk` writes the same convention back.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from meshes.errors import InputError

#: LPS (ITK, DICOM) to the scene's frame (x left, y anterior, z superior), and back.
LPS_TO_SCENE = np.diag([1.0, -1.0, 1.0, 1.0])
#: A 4×4 is accepted as rigid when its rotation block is orthonormal to this (|RᵀR - I|).
RIGID_TOL = 1e-6
#: ITK transform types read as a 3×3 matrix, a translation and a centre.
ITK_MATRIX_TYPES = ("AffineTransform", "MatrixOffsetTransformBase", "Rigid3DTransform")


def rigid(matrix, what: str = "transform") -> np.ndarray:
    """``matrix`` as a validated rigid 4×4 (float), else `InputError` naming ``what``."""
    try:
        T = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4):
        raise InputError(f"{what} must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(f"{what} has NaN/inf entries")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > RIGID_TOL:
        raise InputError(f"{what}: the last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or np.linalg.det(R) < 0:
        raise InputError(f"{what} is not rigid: its 3x3 block is not a rotation (scaling, "
                         "shear or a reflection)")
    return T


def read_itk(path) -> np.ndarray:
    """The segment motion (4×4, scene frame, modelling convention) of an ITK transform file."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read transform file {path}: {e}") from None
    fields = dict(re.findall(r"^\s*(Transform|Parameters|FixedParameters):\s*(.*?)\s*$",
                             text, flags=re.M))
    kind = fields.get("Transform", "")
    if not text.lstrip().startswith("#Insight Transform File") or not kind:
        raise InputError(f"{path} is not an ITK transform file (#Insight Transform File V1.0)")
    if not kind.startswith(ITK_MATRIX_TYPES) or not kind.endswith("_3_3"):
        raise InputError(f"{path}: transform type {kind!r} is not supported; write a linear "
                         f"transform as one of {[t + '_double_3_3' for t in ITK_MATRIX_TYPES]}")
    if text.count("Transform:") > 1:
        raise InputError(f"{path} holds several transforms; give one per segment")
    try:
        par = np.array(fields.get("Parameters", "").split(), dtype=float)
        fixed = np.array(fields.get("FixedParameters", "0 0 0").split(), dtype=float)
    except ValueError:
        raise InputError(f"{path}: parameters are not numbers") from None
    if par.shape != (12,) or fixed.shape != (3,):
        raise InputError(f"{path}: expected 12 parameters and 3 fixed ones (centre), got "
                         f"{par.size} and {fixed.size}")
    A, t, c = par[:9].reshape(3, 3), par[9:], fixed
    resample = np.eye(4)
    resample[:3, :3], resample[:3, 3] = A, t + c - A @ c
    rigid(resample, f"the transform in {path}")
    return LPS_TO_SCENE @ np.linalg.inv(resample) @ LPS_TO_SCENE


def itk_text(T) -> str:
    """ITK transform text of a segment motion T (4×4, scene frame): see the module docstring."""
    resample = LPS_TO_SCENE @ np.linalg.inv(rigid(T)) @ LPS_TO_SCENE
    par = " ".join(f"{v:.17g}" for v in [*resample[:3, :3].ravel(), *resample[:3, 3]])
    return ("#Insight Transform File V1.0\n#Transform 0\n"
            "Transform: AffineTransform_double_3_3\n"
            f"Parameters: {par}\nFixedParameters: 0 0 0\n")


def read_transform(source, what: str = "transform") -> np.ndarray:
    """One rigid 4×4 from a matrix, a JSON file holding one, or an ITK transform file."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.suffix.lower() in (".tfm", ".txt"):
            return read_itk(path)
        try:
            source = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read {what} file {path}: {e}") from None
    return rigid(source, what)


def read_transforms(path) -> dict:
    """{segment: 4×4} from a JSON file ``{segment: [[4×4]] or "file.tfm"}`` (relative paths
    from the JSON's folder), or from one ITK file named ``<segment>.tfm``."""
    path = Path(path)
    if path.suffix.lower() in (".tfm", ".txt"):
        return {path.stem: read_itk(path)}
    try:
        spec = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read transforms file {path}: {e}") from None
    if not isinstance(spec, dict) or not spec:
        raise InputError(f"{path} must hold a JSON object {{segment: 4x4 matrix or .tfm file}}")
    out = {}
    for name, value in spec.items():
        if isinstance(value, str):
            value = path.parent / value
        out[name] = read_transform(value, f"transform of {name!r} in {path}")
    return out

