"""``smartroom view RESULTS``: replay a finished run in the viewer (meshcat in a browser)
from its files alone: no bus, no recomputation (see :mod:`app.viewer.replay`)."""
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
    p.add_argument("--no-voxels", dest="voxels", action="store_false", help="leave voxels.bin out (lighter page)")
    p.add_argument("--max-points", type=int, default=8000, help="voxels drawn at most per frame (default 8000)")
    p.add_argument("--trail", type=int, default=25, help="past positions drawn behind each track (default 25)")
    p.add_argument("--seconds", type=float, help="stop serving after this long (default: until Ctrl-C)")


def main(args) -> int:
    from app.errors import InputError
    from app.viewer.replay import load_run, replay_commands
    from app.viewer.server import MeshcatServer, ServerError
    from app.viewer.scene import VOXELS

    if args.max_points <= 0:
        raise InputError(f"--max-points must be positive, got {args.max_points}")
    data = load_run(args.results, voxels=args.voxels, max_points=args.max_points)
    frames = data.frames
    if args.frame is not None and not frames[0] <= args.frame <= frames[-1]:
        raise InputError(f"--frame {args.frame} is outside the run's frames {frames[0]}..{frames[-1]}")
    _, commands = replay_commands(data, trail=args.trail, start=args.frame, paused=args.paused)
    try:
        server = MeshcatServer(args.bind, args.port, latest_only=[VOXELS]).start()
    except ServerError as exc:
        raise InputError(str(exc)) from None
    done = threading.Event()
    previous = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for cmd in commands:
            server.send(cmd)
        print(f"view: open {server.url}  ({len(frames)} frames {frames[0]}..{frames[-1]} at {data.fps:g} fps; "
              f"{len(data.voxels)} with voxels, {len(data.poses)} with poses, {len(data.tracks)} with tracks; "
              "Ctrl-C to stop)", file=sys.stderr, flush=True)
        done.wait(args.seconds)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        server.close()
    return 0
