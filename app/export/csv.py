"""A plain CSV of the captured joints for spreadsheets: one row per frame and track,
``frame, t, track``, then ``<joint>_x, <joint>_y, <joint>_z`` in metres (the world's
z-up axes unless asked otherwise) for the 15 contract joints, then ``<joint>_active``
(1 or 0). Frames a track is absent from have no row. Rows are in frame, then track order.
"""
from __future__ import annotations

import numpy as np

from app.export.axes import to_axes
from app.export.poses import PoseSeries
from app.messages import JOINTS

__all__ = ["csv_header", "csv_rows", "csv_text", "write_csv"]


def csv_header() -> str:
    cols = ["frame", "t", "track"] + [f"{j}_{c}" for j in JOINTS for c in "xyz"] + [f"{j}_active" for j in JOINTS]
    return ",".join(cols) + "\n"


def csv_rows(frame: int, fps: float, tracks, joints: np.ndarray, active: np.ndarray, up: str = "z") -> str:
    """Rows of one frame: tracks (N,), joints (N, 15, 3) metres, active (N, 15)."""
    pts = to_axes(joints, up)
    out = []
    for k, p, a in sorted(zip(tracks, pts, active), key=lambda r: r[0]):
        cells = [str(int(frame)), f"{frame / fps:.6f}", str(int(k))]
        cells += ["" if not np.isfinite(v) else f"{v:.4f}" for v in p.reshape(-1)]
        cells += ["1" if x else "0" for x in a]
        out.append(",".join(cells) + "\n")
    return "".join(out)


def csv_text(series: PoseSeries, up: str = "z") -> str:
    parts = [csv_header()]
    for f in range(series.first, series.last + 1):
        here = [tp for tp in series.tracks.values()
                if tp.first <= f < tp.first + len(tp.joints) and np.isfinite(tp.joints[f - tp.first]).all()]
        if here:
            parts.append(csv_rows(f, series.fps, [tp.track for tp in here],
                                  np.array([tp.joints[f - tp.first] for tp in here]),
                                  np.array([tp.active[f - tp.first] for tp in here]), up))
    return "".join(parts)


def write_csv(path, series: PoseSeries, up: str = "z") -> None:
    from app.files import write_atomic
    write_atomic(path, csv_text(series, up))
