"""``smartroom export RESULTS``: the captured people of a finished run as BVH, C3D, TRC
or CSV files for other tools (see :mod:`app.export`)."""
from __future__ import annotations

import sys
from pathlib import Path

from app.export import DEFAULT_UP, FORMATS


def add_arguments(p) -> None:
    p.add_argument("results", metavar="RESULTS", help="results folder of a run (with poses.jsonl)")
    p.add_argument("--format", action="append", choices=FORMATS, metavar="FMT",
                   help=f"one of {', '.join(FORMATS)} (repeatable; default all)")
    p.add_argument("--track", type=int, metavar="K", help="only this track")
    p.add_argument("--out", metavar="PATH", help="folder (default RESULTS/export), or a file for one-file exports")
    p.add_argument("--up", choices=("y", "z"),
                   help="up axis of TRC/C3D/CSV: y for OpenSim, z = the room's own axes "
                        f"(defaults: {', '.join(f'{k} {v}' for k, v in DEFAULT_UP.items())}; BVH is always y-up)")
    p.add_argument("--fps", type=float, help="frame rate (default: the run's, from its layout.yaml or stats.json)")
    p.add_argument("--min-frames", type=int, metavar="N",
                   help="leave out tracks reported in fewer than N frames (default: 1 s of frames; 0 keeps all; "
                        "a track named with --track is always exported)")


def main(args) -> int:
    from app.errors import InputError
    from app.export import export_series
    from app.export.poses import load_poses

    from app.export.poses import default_min_frames, short_tracks_line

    series = load_poses(args.results, args.fps).select(args.track)
    if not series.tracks:
        raise InputError(f"{args.results}: poses.jsonl has no tracked person to export")
    if args.min_frames is not None and args.min_frames < 0:
        raise InputError(f"--min-frames must be 0 or more, got {args.min_frames}")
    if args.track is None:
        min_frames = default_min_frames(series.fps) if args.min_frames is None else args.min_frames
        series, short = series.without_short(min_frames)
        if short:
            print(f"smartroom: {short_tracks_line(short, min_frames)} (--min-frames)", file=sys.stderr)
        if not series.tracks:
            raise InputError(f"{args.results}: no track of {min_frames} frames or more to export; "
                             "lower --min-frames (0 keeps every track)")
    formats = args.format or list(FORMATS)
    out = Path(args.out) if args.out else Path(args.results) / "export"
    if len(formats) > 1 and out.suffix:
        raise InputError(f"{out}: a file name fits one format; give a folder for {', '.join(formats)}")
    for fmt in formats:
        up = args.up if fmt != "bvh" else None
        for path in export_series(series, fmt, out, up):
            print(path)
    print(f"smartroom: {len(series.tracks)} track(s), frames {series.first}..{series.last} at {series.fps:g} fps",
          file=sys.stderr)
    return 0
