"""What every calibration reader shares: one-line errors naming the file and the field,
numeric parsing, and the result of an import (cameras plus what was assumed)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import Camera
from calibration.loader import CalibrationError, _camera

__all__ = ["FormatError", "Imported", "fail", "numbers", "rotation", "make_camera", "metres_per_unit"]


class FormatError(CalibrationError):
    """A calibration file of another format is malformed: one line, file and field."""


@dataclass
class Imported:
    """Cameras read from another format, the frame rate if the file has one, and notes
    saying which conventions were applied (printed by ``smartroom calibrate import``)."""

    cameras: list[Camera]
    fps: float | None = None
    notes: list[str] = field(default_factory=list)


def read_xml(path):
    """The root element of an XML calibration file, or a one-line error naming it."""
    import xml.etree.ElementTree as ET

    p = Path(path)
    if not p.is_file():
        raise FormatError(f"{p}: file not found")
    try:
        return ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise FormatError(f"{p}: not valid XML ({exc})") from None


def fail(path, where: str, problem: str) -> FormatError:
    """``FILE: WHERE: PROBLEM`` as a :class:`FormatError` (to raise)."""
    return FormatError(f"{path}: {where}: {problem}" if where else f"{path}: {problem}")


def numbers(value, count, path, where: str) -> np.ndarray:
    """Parse ``value`` (text with blanks/commas, a list, an array) into ``count`` floats
    (``count`` an int, a tuple of accepted counts, or None for any)."""
    try:
        if isinstance(value, str):
            arr = np.array([float(v) for v in value.replace(",", " ").split()], dtype=np.float64)
        else:
            arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise fail(path, where, f"is not numeric ({str(value)[:40]!r})") from None
    counts = (count,) if isinstance(count, int) else count
    if counts is not None and arr.size not in counts:
        want = " or ".join(str(c) for c in counts)
        raise fail(path, where, f"must have {want} numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise fail(path, where, "has non-finite values")
    return arr


def rotation(value, path, where: str) -> np.ndarray:
    """A 3x3 rotation matrix from a Rodrigues vector (3 numbers) or a matrix (9 numbers)."""
    r = numbers(value, (3, 9), path, where)
    if r.size == 3:
        return cv2.Rodrigues(r.reshape(3, 1))[0]
    R = r.reshape(3, 3)
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise fail(path, where, f"is not a rotation matrix (det {np.linalg.det(R):.3f})")
    return R


def make_camera(path, index: int, name, width, height, K, dist, R, t) -> Camera:
    """Build and validate a camera; errors name the source file and the camera."""
    entry = {"name": str(name), "width": width, "height": height, "K": np.asarray(K).tolist(),
             "dist": np.asarray(dist, dtype=np.float64).ravel()[:5].tolist(),
             "R": np.asarray(R).tolist(), "t": np.asarray(t, dtype=np.float64).ravel().tolist()}
    for key in ("width", "height"):
        v = entry[key]
        if isinstance(v, float) and v.is_integer():
            entry[key] = int(v)
    d = np.asarray(entry["dist"])
    if d.size < 4:
        entry["dist"] = np.concatenate([d, np.zeros(4 - d.size)]).tolist()
    return _camera(entry, index, str(path))


def metres_per_unit(units: str, translations, path, notes: list[str], what: str = "translations") -> float:
    """Scale from the file's length unit to metres: ``m``, ``mm``, ``cm`` or ``auto``
    (millimetres when the cameras sit more than 50 units from the origin on average,
    which no room in metres does); the guess is added to ``notes``."""
    table = {"m": 1.0, "cm": 0.01, "mm": 0.001}
    if units in table:
        return table[units]
    if units != "auto":
        raise FormatError(f"--units must be m, cm, mm or auto, got {units!r}")
    dist = float(np.mean([np.linalg.norm(t) for t in translations])) if len(translations) else 0.0
    if dist > 50.0:
        notes.append(f"{Path(path).name}: {what} read as millimetres (cameras {dist:.0f} units from the "
                     "origin on average; give --units m to override)")
        return 0.001
    notes.append(f"{Path(path).name}: {what} read as metres (give --units mm if they are millimetres)")
    return 1.0
