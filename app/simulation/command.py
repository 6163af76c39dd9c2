"""``smartroom simulate``: write a simulated recording folder with ground truth.

    smartroom simulate --scene NAME --out DIR [--seconds S] [--fps F] [--seed K]
                       [--zenithal] [--size WxH] [--occupancy SIZE_M] [--markers]
    smartroom simulate --random SEED --out DIR [--seconds S] [--fps F]
    smartroom simulate --list
    smartroom simulate --preview PNG [--scene NAME] [--frame N] [--seed K]

Heavy modules (numba kernels) are imported only when a verb runs, so
``smartroom --help`` stays fast.
"""
from __future__ import annotations

import math
import sys

from app.errors import InputError

__all__ = ["add_arguments", "main", "parse_size"]


def add_arguments(parser) -> None:
    parser.add_argument("--scene", default="meeting3", help="scene name (see --list; default meeting3)")
    parser.add_argument("--random", type=int, default=None, metavar="SEED",
                        help="a random scene drawn from SEED instead: room, cameras, people and what they do "
                             "(--size and --zenithal do not apply: the scene brings its cameras)")
    parser.add_argument("--out", metavar="DIR", help="recording folder to write")
    parser.add_argument("--seconds", type=float, default=None,
                        help="length in seconds (default: the scene's own length)")
    parser.add_argument("--fps", type=float, default=25.0, help="frame rate (default 25)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: people, clothes, paths (default 0)")
    parser.add_argument("--zenithal", action="store_true", help="add the zenithal ceiling camera cam4")
    parser.add_argument("--size", default="640x480", metavar="WxH", help="image size (default 640x480)")
    parser.add_argument("--occupancy", type=float, default=None, metavar="SIZE_M",
                        help="also write occupancy.npz: the true occupied voxels at this voxel size (m)")
    parser.add_argument("--markers", action="store_true",
                        help="paint coloured markers on the people's joints (marker-based capture, docs/markers.md)")
    parser.add_argument("--codec", default="mp4v", help="video codec fourcc (default mp4v)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    parser.add_argument("--list", action="store_true", help="list the scenes and exit")
    parser.add_argument("--preview", metavar="PNG",
                        help="write one frame of every camera with the true skeletons drawn, and exit")
    parser.add_argument("--frame", type=int, default=None, help="frame of --preview (default: the middle one)")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x480, got {text!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise InputError(f"--size {w}x{h} is out of range (16..8192 pixels a side)")
    return w, h


def _check_number(name: str, value, positive: bool = True):
    if value is None:
        return
    if not math.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{name} must be a positive number, got {value}")


def main(args) -> int:
    from app.simulation.random_scene import RANDOM_SECONDS
    from app.simulation.scenes import SCENES, get_scene
    from app.simulation.simulator import RANDOM

    if args.list:
        width = max(len(n) for n in SCENES)
        for name, scene in SCENES.items():
            print(f"{name:<{width}}  {scene.description} ({scene.seconds:g} s, {len(scene.people)} "
                  f"{'person' if len(scene.people) == 1 else 'people'})")
        print(f"{RANDOM:<{width}}  --random SEED: a room, a camera rig, 1-6 people and what they do, drawn from "
              f"the seed ({RANDOM_SECONDS:g} s)")
        return 0
    if args.random is not None or args.scene == RANDOM:
        if args.random is not None:
            args.seed = args.random
        if args.random is not None and args.random < 0:
            raise InputError(f"--random {args.random}: a seed is a number from 0 up")
        name, natural = RANDOM, RANDOM_SECONDS
    else:
        scene = get_scene(args.scene)
        name, natural = scene.name, scene.seconds
    _check_number("--seconds", args.seconds)
    _check_number("--fps", args.fps)
    _check_number("--occupancy", args.occupancy)
    if args.fps > 1000:
        raise InputError(f"--fps {args.fps} is not a camera frame rate")
    width, height = parse_size(args.size)
    if args.preview:
        from app.simulation.preview import write_preview
        from app.simulation.simulator import Simulator
        sim = Simulator(name, seed=args.seed, fps=args.fps, seconds=args.seconds, width=width, height=height,
                        zenithal=args.zenithal, markers=args.markers)
        n = sim.frame_count()
        frame = n // 2 if args.frame is None else args.frame
        if not 0 <= frame < max(n, 1):
            raise InputError(f"--frame {frame} is outside the scene's {n} frames")
        path = write_preview(args.preview, sim, frame)
        print(f"wrote {path} (scene {name}, seed {args.seed}, frame {frame}, cameras {', '.join(sim.cameras)})")
        return 0
    if not args.out:
        raise InputError("simulate needs --out DIR (or --preview PNG, or --list)")
    from app.simulation.simulator import print_progress, render_recording
    seconds = args.seconds if args.seconds is not None else natural
    if seconds * args.fps < 1:
        raise InputError(f"--seconds {seconds} at --fps {args.fps} is less than one frame")
    progress = None if args.quiet else print_progress(f"simulate {name}" + (f" {args.seed}" if name == RANDOM else ""))
    path = render_recording(name, args.out, seconds=seconds, fps=args.fps, seed=args.seed,
                            zenithal=args.zenithal, width=width, height=height, occupancy=args.occupancy,
                            progress=progress, codec=args.codec, overwrite=args.overwrite, markers=args.markers)
    print(f"wrote {path}", file=sys.stdout)
    return 0
