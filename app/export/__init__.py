"""Exports of the captured people for other tools (BVH for Blender / MotionBuilder, C3D
for Mokka / Visual3D, TRC for OpenSim, CSV for spreadsheets), from a run's
``poses.jsonl`` (``smartroom export``) or live from the bus (the ``exporter`` worker).

One module per format; :func:`export_series` writes the files of one format and both
paths go through it, so a live export equals the offline export of the same run.
"""
from __future__ import annotations

from pathlib import Path

from app.errors import InputError
from app.export.poses import PoseSeries

__all__ = ["FORMATS", "PER_TRACK", "DEFAULT_UP", "export_series", "output_names"]

FORMATS = ("bvh", "c3d", "trc", "csv")
PER_TRACK = ("bvh", "trc")            # one file per track; the others hold every track
DEFAULT_UP = {"bvh": "y", "trc": "y", "c3d": "z", "csv": "z"}


def output_names(series: PoseSeries, fmt: str) -> list[str]:
    """File names a format writes for ``series``."""
    if fmt in PER_TRACK:
        return [f"track{k}.{fmt}" for k in sorted(series.tracks)]
    return [f"poses.{fmt}"]


def export_series(series: PoseSeries, fmt: str, out, up: str | None = None) -> list[Path]:
    """Write ``series`` in ``fmt`` into folder ``out`` (or to file ``out`` when it ends in
    ``.<fmt>`` and the export is one file); the paths written, each complete (written as
    ``.partial`` and renamed)."""
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r} (known: {', '.join(FORMATS)})")
    up = up or DEFAULT_UP[fmt]
    if fmt == "bvh" and up != "y":
        raise InputError("BVH is written y-up (Blender's importer converts it); --up z does not apply")
    out = Path(out)
    names = output_names(series, fmt)
    if out.suffix.lower() == f".{fmt}":
        if len(names) != 1:
            raise InputError(f"{out}: {len(names)} tracks make {len(names)} {fmt.upper()} files; "
                             "give a folder or --track K")
        paths = [out]
    else:
        paths = [out / n for n in names]
    paths[0].parent.mkdir(parents=True, exist_ok=True)
    if fmt == "bvh":   # one timeline for every file: each starts at the run's first frame
        from app.export.bvh import write_bvh
        for path, k in zip(paths, sorted(series.tracks)):
            write_bvh(path, series.tracks[k], series.fps, span=(series.first, series.last))
    elif fmt == "trc":
        from app.export.trc import write_trc
        for path, k in zip(paths, sorted(series.tracks)):
            write_trc(path, series.tracks[k], series.fps, up)
    elif fmt == "c3d":
        from app.export.c3d import write_c3d
        write_c3d(paths[0], series, up)
    else:
        from app.export.csv import write_csv
        write_csv(paths[0], series, up)
    return paths
