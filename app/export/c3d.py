"""C3D export through ``ezc3d`` (the biomechanics community's maintained C3D library),
for Mokka, Visual3D, OpenSim: the 15 contract joints of every track as points labelled
``<track>_<joint>``, one frame per recording frame from the first to the last frame of
the run, point rate = the recording's fps, millimetres, the world's z-up axes (the C3D
convention of most labs) unless asked otherwise. A joint that is inactive, or a frame
its track is absent from, has residual -1 (C3D's "invalid point"; ezc3d reads it as NaN).
"""
from __future__ import annotations

import numpy as np

from app.errors import InputError
from app.export.axes import to_axes
from app.export.poses import PoseSeries
from app.messages import JOINTS

__all__ = ["ezc3d_module", "c3d_labels", "write_c3d"]


def ezc3d_module():
    """``ezc3d``, imported on first use (an optional dependency: the ``export`` extra)."""
    try:
        import ezc3d
    except ImportError:
        raise InputError("C3D export needs ezc3d: pip install 'smartroom[export]'") from None
    return ezc3d


def c3d_labels(series: PoseSeries) -> list[str]:
    return [f"{k}_{j}" for k in sorted(series.tracks) for j in JOINTS]


def write_c3d(path, series: PoseSeries, up: str = "z") -> None:
    """Write the C3D file of every track of ``series`` (as ``<name>.partial.c3d``, then renamed)."""
    import os

    from app.files import partial_path
    ezc3d = ezc3d_module()
    F, tracks = series.count, sorted(series.tracks)
    points = np.zeros((4, len(tracks) * len(JOINTS), F))
    points[3] = 1.0
    residuals = np.full((1, len(tracks) * len(JOINTS), F), -1.0)
    for n, k in enumerate(tracks):
        tp = series.tracks[k]
        cols = slice(n * len(JOINTS), (n + 1) * len(JOINTS))
        a = tp.first - series.first
        mm = to_axes(tp.joints, up) * 1000.0                   # (f, 15, 3)
        ok = tp.active & np.all(np.isfinite(mm), axis=-1)      # (f, 15)
        points[:3, cols, a:a + len(mm)] = np.where(ok[..., None], mm, 0.0).transpose(2, 1, 0)
        residuals[0, cols, a:a + len(mm)] = np.where(ok, 0.0, -1.0).T
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(series.fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(c3d_labels(series))
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c["header"]["points"]["first_frame"] = max(0, int(series.first))
    c["data"]["points"] = points
    c["data"]["meta_points"] = {"residuals": residuals}
    tmp = partial_path(path)
    tmp = tmp.with_name(tmp.name + ".c3d")   # ezc3d adds .c3d to a name not ending in it
    c.write(str(tmp))
    os.replace(tmp, path)
