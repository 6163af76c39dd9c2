"""``smartroom markers``: the colour marker detector's set-up (marker-based capture,
thesis §6.4, docs/markers.md).

    smartroom markers learn --recording DIR --camera C --clicks FILE [--frame N] --out model.json
    smartroom markers check --recording DIR --model model.json [--frame N] [--preview PNG]

``learn``: the markers' chroma model from a few pixels clicked on markers in one frame of
one camera (``--clicks``: a text file of ``x y`` pixel pairs, one per line, ``#``
comments; any image viewer that shows pixel coordinates gives them). ``check``: the
detections of a frame in every camera, counted, and drawn in ``--preview``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from app.errors import InputError

__all__ = ["add_arguments", "main", "read_clicks"]


def add_arguments(p) -> None:
    p.add_argument("action", choices=("learn", "check"), help="learn the markers' colour, or check a model")
    p.add_argument("--recording", required=True, metavar="DIR", help="recording folder")
    p.add_argument("--camera", metavar="C", help="learn: the camera the clicks are in")
    p.add_argument("--clicks", metavar="FILE", help="learn: x y pixel pairs on markers, one per line")
    p.add_argument("--frame", type=int, default=0, help="the frame (default 0)")
    p.add_argument("--out", metavar="FILE", help="learn: the model file to write (JSON)")
    p.add_argument("--model", metavar="FILE", help="check: the model file")
    p.add_argument("--radius", type=int, default=2, help="learn: pixels around each click taken (default 2)")
    p.add_argument("--preview", metavar="PNG", help="check: the frame of every camera with the detections drawn")


def read_clicks(path) -> np.ndarray:
    """``x y`` pairs (N, 2) from a text file; one line that is not two numbers is an
    :class:`InputError` naming it."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise InputError(f"clicks file {path}: {exc.strerror or exc}") from None
    pts = []
    for n, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].replace(",", " ").split()
        if not text:
            continue
        try:
            x, y = (float(v) for v in text)
        except ValueError:
            raise InputError(f"clicks file {path}, line {n}: {line.strip()!r} is not two numbers (x y)") from None
        if not (np.isfinite(x) and np.isfinite(y)):
            raise InputError(f"clicks file {path}, line {n}: not finite")
        pts.append((x, y))
    if not pts:
        raise InputError(f"clicks file {path}: no x y pairs")
    return np.array(pts)


def _frame(recording, frame: int, cameras=None) -> dict:
    if not 0 <= frame < recording.frame_count:
        raise InputError(f"--frame {frame} is outside the recording's {recording.frame_count} frames")
    for _, images in recording.frames(cameras=cameras, start=frame, stop=frame + 1):
        return images
    raise InputError(f"frame {frame} could not be read")


def main(args) -> int:
    from app.markers.detector import ChromaModel, detect_markers, learn_chroma
    from app.recording import Recording

    rec = Recording(args.recording)
    if args.action == "learn":
        if not (args.camera and args.clicks and args.out):
            raise InputError("markers learn needs --camera, --clicks and --out")
        if args.camera not in rec.cameras:
            raise InputError(f"--camera {args.camera}: the recording's cameras are {', '.join(rec.cameras)}")
        clicks = read_clicks(args.clicks)
        image = _frame(rec, args.frame, [args.camera])[args.camera]
        h, w = image.shape[:2]
        outside = [(x, y) for x, y in clicks if not (0 <= x < w and 0 <= y < h)]
        if outside:
            raise InputError(f"clicks outside the {w}x{h} image: {outside[:3]}")
        model = learn_chroma(image, clicks, radius=args.radius)
        Path(args.out).write_text(model.to_json() + "\n")
        found = detect_markers(image, model)
        print(f"wrote {args.out}: chroma Cr {model.mean[0]:.1f} Cb {model.mean[1]:.1f} from {len(clicks)} clicks; "
              f"{len(found)} markers detected in that frame of {args.camera}")
        return 0
    if not args.model:
        raise InputError("markers check needs --model")
    model = ChromaModel.load(args.model)
    images = _frame(rec, args.frame)
    drawn = []
    for cam, image in images.items():
        found = detect_markers(image, model)
        print(f"{cam}: {len(found)} markers")
        if args.preview:
            import cv2
            img = image.copy()
            for x, y in found:
                cv2.circle(img, (int(round(x)), int(round(y))), 6, (255, 0, 255), 1)
            cv2.putText(img, f"{cam}: {len(found)}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 0, 255), 1)
            drawn.append(img)
    if args.preview and drawn:
        import cv2
        h = max(i.shape[0] for i in drawn)
        row = np.concatenate([np.pad(i, ((0, h - i.shape[0]), (0, 0), (0, 0))) for i in drawn], axis=1)
        cv2.imwrite(args.preview, row)
        print(f"wrote {args.preview}", file=sys.stdout)
    return 0
