"""Load, validate and write the contract's ``calibration.yaml`` (CONTRACT.md §1).

Every problem raises :class:`CalibrationError` with a one-line message naming the
file, the camera and the field, e.g.
``calibration.yaml: camera cam2: R is not a rotation (det -1.0)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from app.errors import InputError
from app.files import read_yaml, write_atomic
from calibration.camera import Camera

__all__ = ["Calibration", "CalibrationError", "load_calibration", "save_calibration"]


class CalibrationError(InputError):
    """A calibration file is missing or malformed."""


@dataclass(frozen=True)
class Calibration:
    """A calibrated room: recording fps, analysed volume and cameras."""

    fps: float
    room_min: np.ndarray
    room_max: np.ndarray
    cameras: tuple[Camera, ...]
    path: str = "calibration.yaml"

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise CalibrationError(f"{self.path}: unknown camera {name!r} (have {', '.join(self.names)})")

    def select(self, names) -> "Calibration":
        """The same room with only the named cameras (in the given order)."""
        return Calibration(self.fps, self.room_min, self.room_max,
                           tuple(self.camera(n) for n in names), self.path)

    def to_dict(self) -> dict:
        return {
            "fps": float(self.fps),
            "room": {"min": [float(v) for v in self.room_min], "max": [float(v) for v in self.room_max]},
            "cameras": [c.to_dict() for c in self.cameras],
        }


def _matrix(value, shape, where: str, field: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {field} is not a numeric array") from None
    if m.shape != shape:
        want = "x".join(str(s) for s in shape)
        got = "x".join(str(s) for s in m.shape) or "a scalar"
        raise CalibrationError(f"{where}: {field} must be {want}, got {got}")
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{where}: {field} has non-finite values")
    return m


#: Physical ranges (issue 25: fx = 1e300, k1 = 1e30 or a camera 1,000 km away used to
#: load and give an empty run; a 10 km room a MemoryError): fields of view of a lens,
#: distortion coefficients of a real lens model, the farthest a camera of the room may
#: stand from it, the largest room.
FOV_RANGE = (1.0, 179.0)        # degrees, horizontal and vertical
MAX_RADIAL = 1e3                # |k1|, |k2|, |k3|
MAX_TANGENTIAL = 1.0            # |p1|, |p2|
MAX_CAMERA_DISTANCE = 1000.0    # m from the room's box
MAX_ROOM_SIDE = 200.0           # m


def _physical(cam: Camera, where: str) -> None:
    """One-line errors for values no lens or camera has (:data:`FOV_RANGE`, ...)."""
    for axis, f, side in (("horizontal", cam.K[0, 0], cam.width), ("vertical", cam.K[1, 1], cam.height)):
        fov = 2 * np.degrees(np.arctan(side / (2 * f)))
        if not FOV_RANGE[0] <= fov <= FOV_RANGE[1]:
            raise CalibrationError(f"{where}: K gives a {fov:.3g} degree {axis} field of view over {side} pixels "
                                   f"(a lens gives {FOV_RANGE[0]:g}-{FOV_RANGE[1]:g}: a focal length in mm, or K of "
                                   "another image size?)")
    k, p = cam.dist[[0, 1, 4]], cam.dist[[2, 3]]
    if np.abs(k).max() > MAX_RADIAL or np.abs(p).max() > MAX_TANGENTIAL:
        raise CalibrationError(f"{where}: dist {', '.join(f'{v:.3g}' for v in cam.dist)} is no lens's distortion "
                               f"(|k1|, |k2|, |k3| <= {MAX_RADIAL:g}, |p1|, |p2| <= {MAX_TANGENTIAL:g})")


def _camera(entry, index: int, path: str) -> Camera:
    if not isinstance(entry, dict):
        raise CalibrationError(f"{path}: cameras[{index}] is not a mapping")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise CalibrationError(f"{path}: cameras[{index}]: name is missing")
    where = f"{path}: camera {name}"
    for key in ("width", "height", "K", "R", "t"):
        if key not in entry:
            raise CalibrationError(f"{where}: {key} is missing")
    width, height = entry["width"], entry["height"]
    for key, v in (("width", width), ("height", height)):
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise CalibrationError(f"{where}: {key} must be a positive integer, got {v!r}")
    K = _matrix(entry["K"], (3, 3), where, "K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise CalibrationError(f"{where}: K is not an intrinsic matrix [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    dist = entry.get("dist") or [0.0] * 5
    try:
        dist = np.asarray(dist, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: dist is not a numeric list") from None
    if dist.size not in (4, 5) or not np.all(np.isfinite(dist)):
        raise CalibrationError(f"{where}: dist must list k1, k2, p1, p2[, k3], got {dist.size} values")
    R = _matrix(entry["R"], (3, 3), where, "R")
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise CalibrationError(f"{where}: R is not a rotation (det {det:.1f})")
    t = _matrix(entry["t"], (3,), where, "t")
    cam = Camera(name=name, width=width, height=height, K=K, dist=dist, R=R, t=t)
    _physical(cam, where)
    return cam


def parse_calibration(data, path: str = "calibration.yaml") -> Calibration:
    """Validate an already-parsed calibration document."""
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a mapping with fps, room and cameras")
    fps = data.get("fps")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not fps > 0:
        raise CalibrationError(f"{path}: fps must be a positive number, got {fps!r}")
    room = data.get("room")
    if not isinstance(room, dict) or "min" not in room or "max" not in room:
        raise CalibrationError(f"{path}: room must have min and max corners")
    rmin = _matrix(room["min"], (3,), path, "room.min")
    rmax = _matrix(room["max"], (3,), path, "room.max")
    if not np.all(rmax > rmin):
        raise CalibrationError(f"{path}: room.max must exceed room.min on every axis")
    if np.any(rmax - rmin > MAX_ROOM_SIDE):
        size = " x ".join(f"{v:.4g}" for v in rmax - rmin)
        raise CalibrationError(f"{path}: a room of {size} m (at most {MAX_ROOM_SIDE:g} m a side: "
                               "room.min and room.max in mm, or for another world?)")
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(f"{path}: cameras must be a non-empty list")
    cameras = tuple(_camera(c, i, path) for i, c in enumerate(cams))
    for cam in cameras:
        away = float(np.linalg.norm(np.maximum(0.0, np.maximum(rmin - cam.centre, cam.centre - rmax))))
        if away > MAX_CAMERA_DISTANCE:
            raise CalibrationError(f"{path}: camera {cam.name} stands {away:.4g} m from the room (at most "
                                   f"{MAX_CAMERA_DISTANCE:g} m: t in mm, or R and t for another world?)")
    names = [c.name for c in cameras]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise CalibrationError(f"{path}: camera name {dupes[0]} appears more than once")
    return Calibration(float(fps), rmin, rmax, cameras, path)


def load_calibration(path) -> Calibration:
    """Read and validate ``calibration.yaml`` (a file or a recording folder)."""
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.yaml"
    return parse_calibration(read_yaml(p, "file", CalibrationError), str(p))


def save_calibration(calib: Calibration, path) -> None:
    """Write ``calibration.yaml`` (write, then rename)."""
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.yaml"
    write_atomic(p, yaml.safe_dump(calib.to_dict(), sort_keys=False, default_flow_style=None, width=120))
