"""Every problem of a calibration file at once (``smartroom calibrate check``): the loader
(:mod:`calibration.loader`) stops at the first malformed field, which is right for a run;
a check lists them all, and adds what parses but cannot be right (a principal point
outside the image, a focal length in millimetres, a camera under the floor or facing
away from the room), one line each naming the file and the camera."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.files import read_yaml
from calibration.camera import Camera
from calibration.loader import Calibration, CalibrationError, _camera, _matrix

__all__ = ["Checked", "check_calibration", "camera_doubts"]

#: fx and fy of square pixels agree within this share
SQUARE = 0.10
#: horizontal fields of view (degrees) outside this range are a unit or a size gone wrong
HFOV = (5.0, 175.0)


@dataclass
class Checked:
    """What of a calibration file is usable, and every problem found in it."""

    path: str
    fps: float | None = None
    room: tuple[np.ndarray, np.ndarray] | None = None
    cameras: list[Camera] = field(default_factory=list)
    names: list[str] = field(default_factory=list)  # every camera named in the file, usable or not
    problems: list[str] = field(default_factory=list)

    @property
    def calibration(self) -> Calibration | None:
        """The usable part as a calibration, to show and draw (None without a room or a
        usable camera; fps 0 when the file's is bad)."""
        if self.room is None or not self.cameras:
            return None
        return Calibration(self.fps or 0.0, self.room[0], self.room[1], tuple(self.cameras), self.path)


def camera_doubts(camera: Camera, room_min, room_max, where: str) -> list[str]:
    """What parses but cannot be right about one camera, one phrase each."""
    out = []
    c = camera
    fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]
    if not (-0.5 <= cx <= c.width - 0.5 and -0.5 <= cy <= c.height - 0.5):
        out.append(f"{where}: principal point ({cx:.1f}, {cy:.1f}) lies outside its {c.width}x{c.height} image "
                   "(K made for another image size?)")
    if abs(fx / fy - 1) > SQUARE:
        out.append(f"{where}: fx {fx:.1f} and fy {fy:.1f} differ by {100 * abs(fx / fy - 1):.0f} % "
                   "(K scaled for another aspect ratio?)")
    hfov = 2 * math.degrees(math.atan(c.width / (2 * fx)))
    if not HFOV[0] <= hfov <= HFOV[1]:
        out.append(f"{where}: fx {fx:.4g} px gives a {hfov:.0f} degree field of view "
                   "(a focal length in mm, or for another image size?)")
    if c.centre[2] < room_min[2]:
        out.append(f"{where}: the camera is {room_min[2] - c.centre[2]:.2f} m under the floor "
                   "(z not up, or a flipped axis?)")
    lo, hi = np.asarray(room_min, float), np.asarray(room_max, float)
    grid = np.stack(np.meshgrid(*[np.linspace(lo[k], hi[k], 5) for k in range(3)]), axis=-1).reshape(-1, 3)
    if not c.sees(grid).any():
        out.append(f"{where}: sees none of the room (R and t for another world, or the room bounds wrong?)")
    return out


def check_calibration(path) -> Checked:
    """Read a calibration file (or a recording folder's) and list every problem in it.

    A missing or unparsable file still raises :class:`CalibrationError` (nothing to check)."""
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.yaml"
    data = read_yaml(p, "file", CalibrationError)
    out = Checked(str(p))
    if not isinstance(data, dict):
        out.problems.append(f"{p}: expected a mapping with fps, room and cameras")
        return out
    fps = data.get("fps")
    if isinstance(fps, (int, float)) and not isinstance(fps, bool) and fps > 0:
        out.fps = float(fps)
    else:
        out.problems.append(f"{p}: fps must be a positive number, got {fps!r}")
    room = data.get("room")
    try:
        if not isinstance(room, dict) or "min" not in room or "max" not in room:
            raise CalibrationError(f"{p}: room must have min and max corners")
        lo, hi = _matrix(room["min"], (3,), str(p), "room.min"), _matrix(room["max"], (3,), str(p), "room.max")
        if not np.all(hi > lo):
            raise CalibrationError(f"{p}: room.max must exceed room.min on every axis")
        out.room = (lo, hi)
    except CalibrationError as e:
        out.problems.append(str(e))
    entries = data.get("cameras")
    if not isinstance(entries, list) or not entries:
        out.problems.append(f"{p}: cameras must be a non-empty list")
        return out
    seen = set()
    for i, entry in enumerate(entries):
        name = entry.get("name") if isinstance(entry, dict) else None
        if isinstance(name, str) and name:
            if name in seen:
                out.problems.append(f"{p}: camera name {name} appears more than once")
                continue
            seen.add(name)
            out.names.append(name)
        try:
            cam = _camera(entry, i, str(p))
        except CalibrationError as e:
            out.problems.append(str(e))
            continue
        if out.room is not None:
            out.problems += camera_doubts(cam, *out.room, f"{p}: camera {cam.name}")
        out.cameras.append(cam)
    return out
