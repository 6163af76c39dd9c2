"""TRC export (OpenSim's marker file, "Track Row Column"): one file per track.

Five tab-separated header lines (``PathFileType 4 (X/Y/Z) <file>``; the names and values
of DataRate, CameraRate, NumFrames, NumMarkers, Units, OrigDataRate, OrigDataStartFrame,
OrigNumFrames; ``Frame#  Time  <marker>  ...``; ``X1 Y1 Z1 ...``), a blank line, then one
row per frame: the frame number, the time, and x y z per marker in millimetres. The
markers are the 15 contract joints; a joint that is inactive (or a frame the track is
absent from) has empty cells, which OpenSim reads as a gap. Frame numbers are the
recording's frame indices, times ``frame / fps``.

Axes: OpenSim is y-up, so the default writes ``(x, z, -y)`` of the world (see
:mod:`app.export.axes`); ``up="z"`` writes the world's own z-up axes.
"""
from __future__ import annotations

import numpy as np

from app.export.axes import to_axes
from app.export.poses import TrackPoses
from app.messages import JOINTS

__all__ = ["trc_header", "trc_rows", "trc_text", "write_trc"]

FIELDS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
          "OrigDataStartFrame", "OrigNumFrames")


def _rate(fps: float) -> str:
    return f"{fps:g}"


def trc_header(name: str, fps: float, first: int, frames: int | str) -> str:
    """The header lines and the blank line before the data (``frames`` may be a
    fixed-width placeholder while a live file grows)."""
    values = (_rate(fps), _rate(fps), str(frames), str(len(JOINTS)), "mm", _rate(fps), str(first), str(frames))
    markers = "\t".join(f"{j}\t\t" for j in JOINTS)
    coords = "\t".join(f"X{n}\tY{n}\tZ{n}" for n in range(1, len(JOINTS) + 1))
    return (f"PathFileType\t4\t(X/Y/Z)\t{name}\n" + "\t".join(FIELDS) + "\n" + "\t".join(values) + "\n"
            + f"Frame#\tTime\t{markers}\n" + f"\t\t{coords}\n\n")


def trc_rows(frames: np.ndarray, fps: float, joints: np.ndarray, active: np.ndarray, up: str = "y") -> str:
    """Data rows of frames (F,), joints (F, 15, 3) in metres, active (F, 15)."""
    mm = to_axes(joints, up) * 1000.0
    out = []
    for f, row, act in zip(frames, mm, active):
        cells = [str(int(f)), f"{f / fps:.6f}"]
        for p, a in zip(row, act):
            cells += [f"{v:.3f}" for v in p] if a and np.all(np.isfinite(p)) else ["", "", ""]
        out.append("\t".join(cells) + "\n")
    return "".join(out)


def trc_text(track: TrackPoses, fps: float, name: str, up: str = "y") -> str:
    return trc_header(name, fps, track.first, len(track.joints)) + \
        trc_rows(track.frames, fps, track.joints, track.active, up)


def write_trc(path, track: TrackPoses, fps: float, up: str = "y") -> None:
    from pathlib import Path

    from app.files import write_atomic
    write_atomic(path, trc_text(track, fps, Path(path).name, up))
