"""Options shared by the verbs that run a pipeline (run, bench), resolved in one place."""
from __future__ import annotations

import os
import time
from pathlib import Path

from app.config import RunSpec, apply_overrides, load_layout, load_overrides, parse_assignment
from app.errors import InputError

DEFAULT_SCENE = "meeting3"


def add_pipeline_arguments(p, source: bool = True) -> None:
    if source:
        p.add_argument("--recording", metavar="DIR", help="recording folder (default: the built-in simulated room)")
        p.add_argument("--scene", default=DEFAULT_SCENE,
                       help=f"simulated scene used when no --recording is given (default {DEFAULT_SCENE})")
        p.add_argument("--seconds", type=float, default=10.0, help="length of the simulated scene (default 10)")
        p.add_argument("--zenithal", action="store_true", help="the simulated room has a fifth, zenithal camera")
        p.add_argument("--live", action="append", metavar="CAM=SRC",
                       help="live camera: a cv2.VideoCapture device index or URL (repeat per camera)")
        p.add_argument("--calibration", metavar="FILE", help="calibration.yaml of the live cameras")
    p.add_argument("--layout", metavar="FILE", help="process layout YAML (default deploy/layouts/local.yaml)")
    p.add_argument("--config", metavar="FILE", help="parameter overrides: {worker name or kind: {param: value}}")
    p.add_argument("--set", action="append", default=[], metavar="W.P=V",
                   help="override one parameter, e.g. --set segmentation.history=300 (repeatable)")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("--headless", action="store_true", help="no viewer (kiosk, CI, systemd)")
    p.add_argument("--no-pace", dest="pace", action="store_false",
                   help="read a recording as fast as the pipeline takes it instead of at its fps")
    p.add_argument("--out", metavar="DIR", help="results folder (default runs/<date-time>)")
    p.add_argument("-v", "--verbose", action="store_true", help="log every worker's progress")


def resolve_layout(args):
    """The layout with ``--config`` and ``--set`` applied."""
    layout = load_layout(args.layout)
    if args.config:
        layout = apply_overrides(layout, load_overrides(args.config), args.config)
    if args.set:
        overrides: dict = {}
        for text in args.set:
            target, param, value = parse_assignment(text)
            overrides.setdefault(target, {})[param] = value
        layout = apply_overrides(layout, overrides, "--set")
    return layout


def resolve_source(args) -> RunSpec:
    """A RunSpec naming a validated recording (or live cameras) and the frame limit."""
    if args.frames is not None and args.frames <= 0:
        raise InputError(f"--frames must be positive, got {args.frames}")
    if getattr(args, "live", None):
        from app.sources import parse_live
        from calibration import load_calibration
        if not args.calibration:
            raise InputError("--live needs --calibration FILE")
        calib = load_calibration(args.calibration)
        live = parse_live(args.live)
        for cam in live:
            calib.camera(cam)
        return RunSpec(calibration=str(Path(args.calibration).resolve()), fps=calib.fps, live=live,
                       frames=args.frames, pace=True)
    from app.recording import Recording
    path = args.recording
    if path is None:
        from app.simulation.cache import default_recording
        path = default_recording(args.scene, seconds=args.seconds, zenithal=args.zenithal)
    rec = Recording(path)
    frames = rec.frame_count if args.frames is None else min(args.frames, rec.frame_count)
    if args.frames is not None and args.frames > rec.frame_count:
        import sys
        print(f"smartroom: --frames {args.frames}, but {path} has only {rec.frame_count} frames; running "
              f"{rec.frame_count}", file=sys.stderr)
    from app.recording import fingerprint
    return RunSpec(recording=str(Path(path).resolve()), recording_id=fingerprint(rec), fps=rec.fps, frames=frames,
                   pace=args.pace)


RESULT_FILES = ("stats.json", "layout.yaml", "tracks.jsonl", "poses.jsonl", "voxels.bin")


def resolve_out(args, prefix: str = "runs") -> Path:
    """A new (or empty) results folder, created and checked writable: a run never writes
    over the results of another."""
    if not args.out:
        return _fresh_folder(Path(prefix) / time.strftime("%Y%m%d-%H%M%S"))
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    if out.is_dir():
        held = [f for f in RESULT_FILES if (out / f).exists() or (out / (f + ".partial")).exists()]
        if held:
            raise InputError(f"--out {out}: already holds the results of a run ({', '.join(held)}); "
                             "choose another folder or remove it")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"   # two commands may check one folder at once
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InputError(f"--out {out}: cannot write there ({exc.strerror or exc.__class__.__name__})") from None
    return out.resolve()


def _fresh_folder(base: Path) -> Path:
    """``base``, or ``base-2``, ``base-3``, ... : a folder this command alone creates (two
    commands started in the same second get their own)."""
    for n in range(1, 1000):
        out = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            raise InputError(f"{out}: cannot create the results folder "
                             f"({exc.strerror or exc.__class__.__name__}); choose one with --out") from None
        return out.resolve()
    raise InputError(f"{base}: too many results folders of this second; choose one with --out")
