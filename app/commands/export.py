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


def main(args) -> int:
    from app.errors import InputError
    from app.export import export_series
    from app.export.poses import load_poses

    series = load_poses(args.results, args.fps).select(args.track)
    if not series.tracks:
        raise InputError(f"{args.results}: poses.jsonl has no tracked person to export")
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
