"""``smartroom record``: write a recording folder from what the grabber reads
(live cameras, or another recording), with the calibration copied in."""
from __future__ import annotations

import sys


def add_arguments(p) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="recording folder to write")
    p.add_argument("--recording", metavar="DIR", help="read this recording instead of live cameras")
    p.add_argument("--live", action="append", metavar="CAM=SRC", help="live camera: device index or URL (repeat)")
    p.add_argument("--calibration", metavar="FILE", help="calibration.yaml of the live cameras")
    p.add_argument("--frames", type=int, metavar="N", help="frames to record (live: default until Ctrl-C)")
    p.add_argument("--codec", default="mp4v", help="fourcc of the videos (mp4v -> .mp4, MJPG -> .avi)")


def main(args) -> int:
    from app.errors import InputError
    from app.recording import RecordingWriter
    from app.sources import LiveSource, RecordingSource, parse_live
    from calibration import load_calibration

    if args.live:
        if not args.calibration:
            raise InputError("--live needs --calibration FILE")
        calib = load_calibration(args.calibration)
        # the limit counts frames written: the first ticks, before every camera has
        # delivered its first image, write nothing
        source = LiveSource(parse_live(args.live), calib)
        calib = calib.select(source.cameras)
    elif args.recording:
        source = RecordingSource(args.recording, frames=args.frames)
        calib = source.calibration
    else:
        raise InputError("record needs --live CAM=SRC ... or --recording DIR")
    writer = RecordingWriter(args.out, calib, codec=args.codec)
    last = {}
    n = 0
    try:
        for index, images in source.frames():
            last.update(images)  # a camera missing a frame repeats its last image
            if len(last) < len(calib.cameras):
                if getattr(source, "failed", None):
                    raise InputError("camera %s never delivered an image; nothing recorded"
                                     % ", ".join(sorted(source.failed)))
                continue
            writer.write({c.name: last[c.name] for c in calib.cameras})
            n += 1
            if args.frames is not None and n >= args.frames:
                break
            if n % 25 == 0:
                print(f"\rrecorded {n} frames", end="", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        source.close()
    path = writer.close()
    print(f"\nsmartroom: {n} frames of {len(calib.cameras)} cameras written to {path}", file=sys.stderr)
    return 0
