"""``smartroom run``: the whole pipeline as separate processes over zenoh."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from app.commands.options import add_pipeline_arguments, resolve_layout, resolve_out, resolve_source
from app.errors import InputError


def add_arguments(p) -> None:
    add_pipeline_arguments(p)
    p.add_argument("--host", metavar="NAME",
                   help="start only the workers the layout places on host NAME (another host's share of a "
                        "multi-host room; with --connect, and the layout the hub's host wrote in its results)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="with --host: zenoh endpoint of the hub, e.g. tcp/10.0.0.1:7447 (repeatable)")
    p.add_argument("--linger", action="store_true",
                   help="keep the viewer up after the stream ends (with the replay of the run) until Ctrl-C")


def main(args) -> int:
    from app.launcher import Launcher
    from app.report import Progress, summary_table

    if args.host:
        return host_share(args)
    if args.connect:
        raise InputError("--connect is for --host (another host's share); the hub's host listens on the "
                         "layout's bus endpoints")
    layout = resolve_layout(args)
    run = resolve_source(args)
    run.out = str(resolve_out(args))
    run.headless = args.headless
    layout.run = run
    lingering = args.linger and not args.headless
    for w in layout.workers:
        if lingering and w.kind == "viewer":
            w.params["linger"] = True   # its page reloads into the replay served below
    source = run.recording or ", ".join(f"{c}={s}" for c, s in run.live.items())
    # the monitor worker, when the layout has one, shows progress itself
    has_monitor = any(w.kind == "monitor" for w in layout.workers)
    progress = None if has_monitor else Progress(run.frames, run.fps)
    launcher = Launcher(layout, verbose=args.verbose, progress=progress)
    here = len(launcher.procs)
    elsewhere = sum(1 for w in layout.workers if not w.local)
    print(f"smartroom: {here} workers here" + (f" ({elsewhere} on other hosts)" if elsewhere else "")
          + f" on {source}; results in {run.out}", file=sys.stderr)
    try:
        rc = launcher.run()   # bad input raises InputError: its one line (the CLI's) is all there is to say
    finally:
        stats = Path(run.out) / "stats.json"
        summary = json.loads(stats.read_text()) if stats.is_file() else {}
        if summary and not launcher.input_error:
            if summary.get("frames_delivered"):   # no frame went through: no table of zeros
                print(summary_table(summary))
            for reason in summary.get("reasons", []):
                print(f"smartroom: incomplete: {reason}", file=sys.stderr)
            print(f"smartroom: results in {run.out}{next_steps(Path(run.out), lingering)}", file=sys.stderr)
    if lingering and rc == 0:
        from app.commands.view import linger
        rc = linger(layout, run.out)
    return rc


def host_share(args) -> int:
    """``smartroom run --host H --connect ENDPOINT --layout <hub host's out>/layout.yaml``:
    start, watch and restart the workers the layout places on host H, as clients of the
    hub elsewhere; their own ``stats.json`` and logs in ``--out``."""
    from app.launcher import Launcher

    layout = resolve_layout(args)
    run = layout.run
    if args.recording:
        run.recording = str(Path(args.recording).resolve())
    if args.frames is not None:
        run.frames = args.frames
    run.out = str(resolve_out(args))
    run.headless = args.headless or run.headless
    launcher = Launcher(layout, verbose=args.verbose, host=args.host, connect=args.connect)
    names = ", ".join(p.name for p in launcher.procs)
    print(f"smartroom: host {args.host}: {names}, clients of the hub at {', '.join(args.connect)}; "
          f"logs and stats in {run.out}", file=sys.stderr)
    rc = launcher.run()
    stats = Path(run.out) / "stats.json"
    summary = json.loads(stats.read_text()) if stats.is_file() else {}
    for reason in summary.get("reasons", []):
        print(f"smartroom: incomplete: {reason}", file=sys.stderr)
    return rc


def next_steps(out: Path, lingering: bool = False) -> str:
    """What to do with the results, said after the run: replay them, export the people."""
    import shlex
    folder = shlex.quote(str(out))
    steps = []
    if not lingering and any((out / f).is_file() for f in ("tracks.jsonl", "poses.jsonl", "voxels.bin")):
        steps.append(f"smartroom view {folder} (replay in the browser)")
    if (out / "poses.jsonl").is_file():
        steps.append(f"smartroom export {folder} (BVH, C3D, TRC, CSV for Blender, Mokka, OpenSim)")
    return "; next: " + ", ".join(steps) if steps else ""
