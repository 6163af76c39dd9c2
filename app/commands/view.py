"""``smartroom view RESULTS``: replay a finished run in the viewer (meshcat in a browser)
from its files alone: no bus, no recomputation (see :mod:`app.viewer.replay`). Also what
``smartroom run --linger`` serves once the stream has ended."""
from __future__ import annotations

import signal
import sys
import threading


def add_arguments(p) -> None:
    p.add_argument("results", metavar="RESULTS", help="results folder of a run")
    p.add_argument("--bind", default="127.0.0.1", help="address the page listens on (0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=0, help="port of the page (default: the first free from 7000)")
    p.add_argument("--frame", type=int, metavar="N", help="open paused on frame N (default: play from the start)")
    p.add_argument("--paused", action="store_true", help="open paused on the first frame")
    p.add_argument("--range", metavar="A:B", help="only frames A to B (the page holds every frame it plays: "
                                                 "replay a long run a part at a time)")
    p.add_argument("--no-voxels", dest="voxels", action="store_false", help="leave voxels.bin out (lighter page)")
    p.add_argument("--max-points", type=int, default=8000, help="voxels drawn at most per frame (default 8000)")
    p.add_argument("--trail", type=int, default=25, help="past positions drawn behind each track (default 25)")
    p.add_argument("--images", metavar="CAM", help="also show this camera's recorded frames (bottom left)")
    p.add_argument("--image-width", type=int, default=320, help="width of the shown frames in pixels (default 320)")
    p.add_argument("--seconds", type=float, help="stop serving after this long (default: until Ctrl-C)")


def serve(results, bind: str = "127.0.0.1", port: int = 0, frame: int | None = None, paused: bool = False,
          voxels: bool = True, max_points: int = 8000, trail: int = 25, seconds: float | None = None,
          allow_empty: bool = False, last: bool = False, images: str | None = None, image_width: int = 320,
          span: tuple | None = None) -> int:
    """Serve the replay of ``results`` until Ctrl-C / SIGTERM (or ``seconds``). ``last``:
    open paused on the last frame; ``allow_empty``: a run with nothing to replay shows the room."""
    from app.errors import InputError
    from app.viewer.replay import load_run, replay_commands
    from app.viewer.server import MeshcatServer, ServerError

    if max_points <= 0:
        raise InputError(f"--max-points must be positive, got {max_points}")
    if image_width <= 0:
        raise InputError(f"--image-width must be positive, got {image_width}")
    data = load_run(results, voxels=voxels, max_points=max_points, allow_empty=allow_empty, images=images,
                    image_width=image_width, span=span)
    frames = data.frames
    if frames and last:
        frame = frames[-1]
    if frame is not None and frames and not frames[0] <= frame <= frames[-1]:
        raise InputError(f"--frame {frame} is outside the run's frames {frames[0]}..{frames[-1]}")
    _, commands = replay_commands(data, trail=trail, start=frame, paused=paused)
    try:
        server = MeshcatServer(bind, port).start()
    except ServerError:
        if not port:
            raise
        server = None
    if server is None:   # the port is taken: any free one
        try:
            server = MeshcatServer(bind, 0).start()
        except ServerError as exc:
            raise InputError(str(exc)) from None
    done = threading.Event()
    previous = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for cmd in commands:
            server.send(cmd)
        what = "nothing recorded"
        if frames:
            what = (f"{len(frames)} frames {frames[0]}..{frames[-1]} at {data.fps:g} fps; {len(data.voxels)} with "
                    f"voxels, {len(data.poses)} with poses, {len(data.tracks)} with tracks, {len(data.images)} with images")
        print(f"view: open {server.url}  ({what}; Ctrl-C to stop)", file=sys.stderr, flush=True)
        done.wait(seconds)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        server.close()
    return 0


def parse_range(text: str | None) -> tuple | None:
    """``A:B`` (either side may be empty) as ``(A, B)``."""
    from app.errors import InputError
    if text is None:
        return None
    a, sep, b = text.partition(":")
    try:
        span = (int(a) if a else -1, int(b) if b else float("inf"))
    except ValueError:
        span = None
    if not sep or span is None or span[0] > span[1]:
        raise InputError(f"--range must be FIRST:LAST frame numbers, got {text!r}")
    return span


def main(args) -> int:
    return serve(args.results, args.bind, args.port, args.frame, args.paused, args.voxels, args.max_points,
                 args.trail, args.seconds, images=args.images, image_width=args.image_width,
                 span=parse_range(args.range))


def linger(layout, out) -> int:
    """``smartroom run --linger``: after the stream, the run's replay at the viewer's address."""
    import json
    from pathlib import Path
    from urllib.parse import urlparse

    spec = next((w for w in layout.workers if w.kind == "viewer"), None)
    if spec is None:
        print("smartroom: --linger: the layout has no viewer", file=sys.stderr)
        return 0
    port = int(spec.params.get("port") or 0)
    try:
        workers = json.loads((Path(out) / "stats.json").read_text()).get("workers") or {}
        url = (workers.get(spec.name) or {}).get("url")
        port = urlparse(url).port or port if url else port
    except (OSError, ValueError, AttributeError):
        pass
    print("smartroom: the stream has ended; the viewer stays up with the replay of the run", file=sys.stderr)
    return serve(out, spec.params.get("bind", "127.0.0.1"), port, allow_empty=True, last=True)
