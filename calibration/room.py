"""The analysed volume (the voxel grid's bounds): parsed from the command line, or
estimated from where the cameras' fields of view meet over the floor."""
from __future__ import annotations

import re

import numpy as np

from app.errors import InputError

__all__ = ["parse_room", "estimate_room", "format_room", "ROOM_PATTERN"]

#: ``xmin,ymin,zmin,xmax,ymax,zmax``: numbers that may be negative (argparse must not take
#: ``-3,-1.5,0,3,2,2.5`` for an option; see ``app/commands/calibrate.py``).
ROOM_PATTERN = re.compile(r"^-?\d*\.?\d+(?:[eE][-+]?\d+)?(?:\s*,\s*-?\d*\.?\d+(?:[eE][-+]?\d+)?)+$")


def parse_room(text: str, option: str = "--room") -> tuple[np.ndarray, np.ndarray]:
    """``"xmin,ymin,zmin,xmax,ymax,zmax"`` (metres; negative values allowed) to two corners."""
    try:
        v = [float(x) for x in str(text).replace(" ", "").split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not np.all(np.isfinite(v)):
        raise InputError(f"{option} must be xmin,ymin,zmin,xmax,ymax,zmax in metres, got {text!r}")
    lo, hi = np.array(v[:3]), np.array(v[3:])
    if not np.all(hi > lo):
        raise InputError(f"{option} {text}: each max must exceed its min (x, y and z)")
    return lo, hi


def format_room(lo, hi) -> str:
    return (f"x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, z {lo[2]:.2f}..{hi[2]:.2f} m "
            f"(--room={','.join(f'{v:g}' for v in list(lo) + list(hi))})")


def estimate_room(cameras, min_views: int | None = None, step: float = 0.05,
                  height: float = 2.2) -> tuple[np.ndarray, np.ndarray]:
    """The box over the floor area that at least ``min_views`` cameras see (default: 2,
    or 1 with a single camera), searched within the span of the camera centres (cameras
    hang on the walls and in the corners of the room they watch; 5 m around them when
    they stand in a row), up to ``height`` metres (a standing
    person with raised arms; lower when every camera hangs lower)."""
    cams = list(cameras)
    k = min_views or min(2, len(cams))
    centres = np.array([c.centre for c in cams])
    lo, hi = centres[:, :2].min(axis=0), centres[:, :2].max(axis=0)
    if np.any(hi - lo < 1.0):  # cameras in a row: look 5 m around them
        lo, hi = centres[:, :2].min(axis=0) - 5.0, centres[:, :2].max(axis=0) + 5.0
    xs, ys = np.arange(lo[0], hi[0] + step, step), np.arange(lo[1], hi[1] + step, step)
    gx, gy = np.meshgrid(xs, ys)
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    seen = np.zeros(len(floor), dtype=np.int32)
    for c in cams:
        seen += c.sees(floor)
    pts = floor[seen >= k]
    if len(pts) == 0:
        raise InputError(f"no floor area is seen by {k} cameras: give the room with --room=xmin,ymin,zmin,xmax,ymax,zmax")
    top = float(min(height, max(1.0, np.median(centres[:, 2]))))
    lo3 = np.array([*(np.floor(pts[:, :2].min(axis=0) / step) * step), 0.0])
    hi3 = np.array([*(np.ceil(pts[:, :2].max(axis=0) / step) * step), top])
    return np.round(lo3, 6), np.round(hi3, 6)
