"""``smartroom bench``: throughput profiling against the real-time target.

- ``smartroom bench [pipeline]``: the pipeline on a recording (default: the simulated
  meeting3), unpaced and paced; ``profile.json``, ``profile.png`` and a summary table
  in ``--out``. ``--sweep voxel=2,3,4,5`` (or ``--sweep worker.param=a,b``) repeats it
  and tabulates RTF against the parameter.
- ``smartroom bench bus``: codec + zenoh latency and throughput between two processes.
- ``smartroom bench flood``: the pipeline quiet and beside junk on every key of the room
  at ``--flood-rate`` messages a second (default 20,000) from another process (from outside
  the room, or with ``--flood-inside`` connected as its workers are), in each of
  ``--modes``: what the flood costs in RTF, frames delivered, messages refused, and whether
  the unpaced (offline) run wrote the same tracks and poses (:mod:`app.benchmarks.flood`).
- ``smartroom bench grabber``: decode, reduce and encode cost per camera at 640x480 and
  1920x1088, and a set of four cameras decoded serially and in parallel.
- ``smartroom bench reconstruction``: segmentation + reconstruction + colouring + surface
  per frame on one core for voxel sizes x methods x colourings, and accuracy against
  the true body volume (default: the simulated meeting3 with 5 cameras).
- ``smartroom bench simulate``: render time per multi-camera frame of a simulated scene.
- ``smartroom bench segmentation``: the masks against the simulator's true silhouettes
  (recall, precision, where the misses and the false foreground are), today's default
  against MOG2 alone; ``--hull`` adds the hull carved from each (k = 0 and 1).
- ``smartroom bench accuracy --seeds A:B``: the whole pipeline on random scenes (rendered
  once into the cache), scored against their ground truth: MOTA, IDF1, MOTP, MMTA, MMTP,
  MPJPE per scene, mean and worst, detection by stature band and activity, phantoms
  (:mod:`app.benchmarks.accuracy`; tune on seeds below 1000, report on 1000 and up).
- ``smartroom bench keypoints``: the keypoint cue's detector, ms per person crop on one
  thread and its sure keypoints against the truth (simulated ``--scene``, default meeting3).
- ``smartroom bench pose``: ms per frame of APF 600x6, SHBM-APF and DDM-APF at model
  densities 1, 2, 3 on one core, next to MMTA / MMTP (simulated gesture1 and walk1, 2 cm).
  ``--replay RUN --recording DIR --pose-seeds N``: the pose stage again over a run's own
  voxels for N filter seeds (the seed's spread; paired comparisons with ``--pose-set``).
- ``smartroom bench marker``: the marker-based APF over synthetic detections (§6.4,
  §6.6.1): MMTA for DR x FP x sigma^2 against L x N_pL, like the thesis's Fig. 6.13
  (:mod:`app.benchmarks.marker`; ``--marker-grid full`` for the thesis's whole grid).
- ``smartroom bench streaming``: the streamers (VMC, plain OSC, LSL) with ``--people``
  people at ``--stream-fps``: frames received of those sent and the latency from the pose
  message to the packet, p50/p95 (:mod:`app.benchmarks.streaming`).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from app.commands.options import add_pipeline_arguments, resolve_layout, resolve_out, resolve_source

TARGETS = ("pipeline", "bus", "reconstruction", "simulate", "pose", "tracking", "grabber", "segmentation", "accuracy",
           "keypoints", "streaming", "marker", "flood")


def add_arguments(p) -> None:
    p.add_argument("target", nargs="?", default="pipeline", choices=TARGETS, help="what to measure (default pipeline)")
    add_pipeline_arguments(p)
    p.add_argument("--sweep", metavar="P=V1,V2", help="repeat over a parameter: voxel=2,3,4,5 or worker.param=a,b")
    p.add_argument("--modes", default="unpaced,paced", help="pipeline: unpaced, paced or both (default)")
    p.add_argument("--voxel-sizes", default="2,3,4,5", help="reconstruction: voxel sizes in cm (default 2,3,4,5)")
    p.add_argument("--tolerance", type=int, default=1, help="reconstruction: k, cameras that may miss a voxel")
    p.add_argument("--filters", metavar="F:N,...",
                   help="tracking: filters and counts, e.g. naive,ss_colour:400,pf_raw:100 (default: the Table 4.3 grid)")
    p.add_argument("--tracking-scenes", default="meeting3,crowd6",
                   help="tracking: simulated scenes when no --recording is given (default meeting3,crowd6)")
    p.add_argument("--min-top", type=float, default=0.25,
                   help="reconstruction: drop blobs lower than this (m); 0 = the thesis (keep all)")
    p.add_argument("--hull", action="store_true",
                   help="reconstruction: only the hull table of issue 8 (k=0, k=1, learnt occluders; MOG2 and "
                        "true silhouettes; volume, recall, fragmentation) on a simulated recording")
    p.add_argument("--hull-losses", action="store_true",
                   help="reconstruction: what k=0 loses of the body and why (edge or hidden misses per camera; "
                        "MOG2 and true silhouettes) on a simulated recording")
    p.add_argument("--hull-bounds", action="store_true",
                   help="reconstruction: issue 8's target against the best any selection of the voxels one camera "
                        "misses can do (an oracle that reads the truth; k=0, k=1, with and without the edge test; "
                        "MOG2 and true silhouettes) on a simulated recording")
    p.add_argument("--speed", action="store_true",
                   help="reconstruction: only issue 8's speed rows (segmentation + reconstruction + colour per frame "
                        "on one core for today's method, learnt occluders and the fused method) at the first voxel size")
    p.add_argument("--pose-methods", default="apf,shbm,ddm", help="pose: methods (apf, shbm, ddm, shbm+ddm, behaviour)")
    p.add_argument("--densities", default="1,2,3", help="pose: model density factors (Eq. 6.26, default 1,2,3)")
    p.add_argument("--pose-scenes", default="gesture1,walk1",
                   help="pose: simulated scenes, built-in or random:SEED (default gesture1,walk1)")
    p.add_argument("--pose-step", type=int, default=1,
                   help="pose: every STEP-th frame of the scenes (the motion STEP times as fast; default 1)")
    p.add_argument("--voxels", default="true", choices=("true", "hull", "mog2"),
                   help="pose: voxels of the true bodies, the visual hull of the true silhouettes, or of the "
                        "segmentation's MOG2 masks (the pipeline's reconstruction; with --tolerance)")
    p.add_argument("--pose-set", metavar="K=V,...", default="",
                   help="pose: PoseSettings overrides, e.g. coverage=0 (the thesis's likelihood) or ik=straight")
    p.add_argument("--pose-seeds", type=int, default=1, help="pose: filter seeds per row, errors pooled")
    p.add_argument("--pose-surface", action="store_true",
                   help="pose: hull voxels carry the reconstruction's visibility surface flags, as in the pipeline")
    p.add_argument("--marker-scenes", default="walk1,occluded1",
                   help="marker: simulated scenes (default walk1,occluded1, held out; gesture1, statures3, "
                        "meeting3, crowd6, still2 and enter2 were tuned on); random:A:B the random scenes of "
                        "seeds A to B-1 (tune below 1000, report 1000 and up)")
    p.add_argument("--marker-cost", default="both_ways", choices=("thesis", "reprojection", "both_ways"),
                   help="marker: the likelihood (thesis: Eqs. 6.4-6.10; both_ways, the default: ours, "
                        "app/markers/likelihood.py)")
    p.add_argument("--marker-grid", default="small", choices=("small", "full"),
                   help="marker: DR 0.9, FP 0/20, sigma2 4/20, (L, N_pL) (1, 300)/(3, 700); or the thesis's grid")
    p.add_argument("--people", type=int, default=6, help="streaming: people per frame (default 6)")
    p.add_argument("--stream-fps", type=float, default=60.0, help="streaming: frame rate (default 60)")
    p.add_argument("--protocols", default="osc,vmc,lsl", help="streaming: protocols (default osc,vmc,lsl)")
    p.add_argument("--flood-rate", type=float, default=20000.0,
                   help="flood: junk messages a second on the room's keys (default 20000)")
    p.add_argument("--flood-inside", action="store_true",
                   help="flood: the junk comes in as the room's own workers do (a worker gone wrong), not from "
                        "outside the room over its TCP endpoint (which a room on one host does not let publish)")
    p.add_argument("--seeds", default="1000:1020",
                   help="accuracy: random scenes A:B (A to B-1) or a list; tune below 1000, report 1000 and up "
                        "(default 1000:1020)")
    p.add_argument("--smartroom", metavar="CMD",
                   help="accuracy: the command line of another build to run the pipeline with (an A/B: e.g. "
                        "'/path/old/.venv/bin/python -m app.cli'); default this build")
    p.add_argument("--replay", metavar="RUN",
                   help="pose: the pose stage again over the voxels of RUN (smartroom run ... --set "
                        "recorder.voxels=true) with its pose parameters and --pose-set overrides, once per seed of "
                        "--pose-seeds, scored against --recording's ground truth")


def _bus(args, out: Path) -> dict:
    from app.benchmarks import bus

    n = args.frames or 300
    results = [bus.run(frames=n, throughput_frames=max(n, 200), shm=shm) for shm in (True, False)]
    print(bus.table(results))
    return {"bus": results}


def _pipeline(args, out: Path) -> dict:
    from app.benchmarks.pipeline import profile, summary_lines, sweep_values

    layout = resolve_layout(args)
    layout.workers = [w for w in layout.workers if w.kind not in ("monitor", "viewer")]
    run = resolve_source(args)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in modes:
        if m not in ("unpaced", "paced"):
            from app.errors import InputError
            raise InputError(f"--modes: unknown mode {m!r} (unpaced, paced)")
    print(f"smartroom bench: {run.frames} frames of {run.recording} ({run.fps:g} fps); report in {out}",
          file=sys.stderr)
    if not args.sweep:
        result = profile(layout, run, out, modes)
        print("\n".join(summary_lines(result)))
        print(f"smartroom bench: {out / 'profile.json'}, {out / 'profile.png'}", file=sys.stderr)
        return result
    rows = []
    for label, lay in sweep_values(layout, args.sweep):
        print(f"smartroom bench: {label}", file=sys.stderr)
        result = profile(lay, run, out / label.replace("=", "_"), modes)
        rows.append((label, result))
        print("\n".join(summary_lines(result)))
    head = f"{'value':<20}" + "".join(f"{m + ' RTF':>14}{m + ' p95 ms':>16}" for m in modes)
    print(head)
    for label, result in rows:
        cells = ""
        for m in modes:
            r = result["modes"][m]
            cells += f"{r.get('rtf') or 0:>14.2f}{(r.get('end_to_end_latency_ms') or {}).get('p95', 0):>16.0f}"
        print(f"{label:<20}{cells}")
    return {"sweep": args.sweep, "runs": {label: r for label, r in rows}}


def _flood(args, out: Path) -> dict:
    from app.benchmarks import flood
    from app.errors import InputError

    layout = resolve_layout(args)
    layout.workers = [w for w in layout.workers if w.kind not in ("monitor", "viewer")]
    run = resolve_source(args)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or set(modes) - {"unpaced", "paced"}:
        raise InputError(f"--modes {args.modes!r}: unpaced, paced or both")
    if not 0 < args.flood_rate <= 1e6:
        raise InputError(f"--flood-rate {args.flood_rate:g}: must be above 0 and at most 1,000,000")
    print(f"smartroom bench flood: {run.frames} frames of {run.recording}, junk at {args.flood_rate:g} msg/s; "
          f"runs in {out}", file=sys.stderr)
    result = flood.measure(layout, run, out, args.flood_rate, modes, inside=args.flood_inside)
    print(flood.table(result))
    return result


def _reconstruction(args, out: Path) -> dict:
    from app.benchmarks import reconstruction
    from app.errors import InputError

    if args.recording is None:
        args.zenithal = True  # issue 4 measures 5 cameras
    run = resolve_source(args)
    try:
        sizes = tuple(float(v) / 100 for v in args.voxel_sizes.split(","))
    except ValueError:
        raise InputError(f"--voxel-sizes {args.voxel_sizes}: expected centimetres like 2,3,4,5") from None
    frames = args.frames or 60
    if args.speed:
        print(reconstruction.SPEED_HEADER)
        rows = reconstruction.speed_table(run.recording, frames=frames + 10, voxel_size=sizes[0], min_top=args.min_top)
        return {"recording": run.recording, "frames": frames, "speed": rows}
    if args.hull_losses:
        print(reconstruction.LOSSES_HEADER)
        rows = reconstruction.hull_losses(run.recording, frames=frames + 10, voxel_sizes=sizes)
        return {"recording": run.recording, "frames": frames, "hull_losses": rows}
    if args.hull_bounds:
        print(reconstruction.BOUNDS_HEADER)
        rows = reconstruction.hull_bounds(run.recording, frames=frames + 10, voxel_sizes=sizes, min_top=args.min_top)
        return {"recording": run.recording, "frames": frames, "hull_bounds": rows}
    if args.hull:
        rows = reconstruction.hull_table(run.recording, frames=frames + 10, voxel_sizes=sizes, min_top=args.min_top,
                                         verbose=False)
        print(reconstruction.format_hull_table(rows, run.recording, frames))
        return {"recording": run.recording, "frames": frames, "hull": rows}
    print(f"smartroom bench reconstruction: {frames} frames of {run.recording}", file=sys.stderr)
    print(reconstruction.HEADER)
    result = reconstruction.run(run.recording, frames=frames + 10, voxel_sizes=sizes, tolerance=args.tolerance,
                                min_top=args.min_top)
    print(reconstruction.format_table(result))
    return result


def _simulate(args, out: Path) -> dict:
    from app.simulation.bench import bench_render

    return bench_render(args.scene, frames=args.frames or 50, seconds=args.seconds, zenithal=args.zenithal)


def _pose_set(args) -> dict:
    """``--pose-set KEY=VALUE,...``: values typed as in a layout (0.5, true, tolerant; YAML),
    and numbers YAML reads as text (5e-4) as numbers."""
    import yaml

    from app.errors import InputError

    out = {}
    for item in filter(None, args.pose_set.split(",")):
        key, _, value = (v.strip() for v in item.partition("="))
        if not key or not value:
            raise InputError(f"--pose-set {item}: expected KEY=VALUE (a pose parameter)")
        try:
            typed = yaml.safe_load(value)
        except yaml.YAMLError:
            raise InputError(f"--pose-set {item}: the value is not valid YAML") from None
        if isinstance(typed, str):
            try:
                typed = float(value)
            except ValueError:
                pass
        out[key] = typed
    return out


def _pose_replay(args) -> dict:
    from app.benchmarks.pose_replay import HEADER, format_replay, replay_poses
    from app.errors import InputError

    if not args.recording:
        raise InputError("--replay needs --recording DIR (the recording the run was made on: its ground truth)")
    overrides = _pose_set(args)
    print(f"smartroom bench pose --replay {args.replay}: {args.pose_seeds} seed(s), one core", file=sys.stderr)
    print(HEADER)
    result = replay_poses(args.replay, args.recording, seeds=tuple(range(args.pose_seeds)), overrides=overrides)
    print(format_replay(result))
    return result


def _pose(args, out: Path) -> dict:
    from app.benchmarks import pose
    from app.errors import InputError

    if args.replay:
        return _pose_replay(args)
    try:
        densities = tuple(float(v) for v in args.densities.split(","))
        voxel = float(args.voxel_sizes.split(",")[0]) / 100 if args.voxel_sizes != "2,3,4,5" else 0.02
    except ValueError:
        raise InputError(f"--densities {args.densities}: expected numbers like 1,2,3") from None
    frames = args.frames or 75
    print(f"smartroom bench pose: {frames} frames of {args.pose_scenes} at {100 * voxel:g} cm, one core",
          file=sys.stderr)
    print(pose.HEADER)
    from dataclasses import fields

    from app.pose.estimator import PoseSettings
    known = {f.name for f in fields(PoseSettings)}
    settings = _pose_set(args)
    unknown = sorted(set(settings) - known)
    if unknown:
        raise InputError(f"--pose-set {unknown[0]}: not a pose setting (one of {', '.join(sorted(known))})")
    rows = pose.bench_pose(scenes=tuple(args.pose_scenes.split(",")), frames=frames, voxel_size=voxel,
                           densities=densities, methods=tuple(args.pose_methods.split(",")), source=args.voxels,
                           tolerance=args.tolerance, settings=settings, seeds=tuple(range(args.pose_seeds)),
                           surface=args.pose_surface, step=args.pose_step)
    return {"frames": frames, "voxel_size": voxel, "rows": rows}


def _tracking(args, out: Path) -> dict:
    from app.benchmarks import tracking
    from app.errors import InputError

    try:
        sizes = (0.02, 0.04, 0.05, 0.10) if args.voxel_sizes == "2,3,4,5" else \
            tuple(float(v) / 100 for v in args.voxel_sizes.split(","))
    except ValueError:
        raise InputError(f"--voxel-sizes {args.voxel_sizes}: expected centimetres like 2,5,10") from None
    configs = tracking.parse_configs(args.filters) if args.filters else tracking.CONFIGS
    if args.recording:
        recordings = [resolve_source(args).recording]
    else:
        from app.simulation.cache import default_recording
        from app.simulation.scenes import get_scene
        recordings = [default_recording(s, seconds=get_scene(s).seconds)
                      for s in args.tracking_scenes.split(",") if s]
    print(f"smartroom bench tracking: {', '.join(str(r) for r in recordings)}; CCA + tracking on one core",
          file=sys.stderr)
    result = tracking.run(recordings, voxel_sizes=sizes, configs=configs, frames=args.frames,
                          progress=lambda line: print(line, file=sys.stderr, flush=True))
    print(tracking.format_table(result))
    return result


def _grabber(args, out: Path) -> dict:
    from app.benchmarks import grabber

    rows = grabber.run(frames=args.frames or 40)
    print(grabber.format_table(rows))
    return {"grabber": rows}


def _segmentation(args, out: Path) -> dict:
    """Masks against the simulator's true silhouettes at the scales matched to the voxel
    sizes (default 2 and 4 cm), today's default against MOG2 alone; with ``--hull`` also
    the hull (k = 0 and 1) carved from each variant's masks and from the true silhouettes."""
    from app.benchmarks import segmentation
    from app.errors import InputError
    from app.recording import Recording
    from app.segmentation import matched_scale

    if args.recording is None:
        args.zenithal = True   # the 5 cameras of issue 8's figures
    run = resolve_source(args)
    try:
        sizes = (0.02, 0.04) if args.voxel_sizes == "2,3,4,5" else \
            tuple(float(v) / 100 for v in args.voxel_sizes.split(","))
    except ValueError:
        raise InputError(f"--voxel-sizes {args.voxel_sizes}: expected centimetres like 2,4") from None
    frames = args.frames or 60
    calib = Recording(run.recording).calibration
    scales = tuple(dict.fromkeys(matched_scale(calib, vs) for vs in sizes))
    rows = segmentation.mask_table(run.recording, frames=frames + 10, scales=scales, verbose=False)
    print(segmentation.format_mask_table(rows, run.recording, frames))
    result = {"recording": str(run.recording), "frames": frames, "masks": rows}
    if args.hull:
        hull = segmentation.hull_rows(run.recording, frames=frames + 10, voxel_sizes=sizes, min_top=args.min_top,
                                      verbose=False)
        print(segmentation.format_hull_rows(hull, run.recording, frames))
        result["hull"] = hull
    return result


def _keypoints(args, out: Path) -> dict:
    """The keypoint cue's detector: ms per person crop on one thread, and its keypoints
    against the simulated scene's truth (:mod:`app.benchmarks.keypoints`)."""
    from app.benchmarks import keypoints

    res = keypoints.run(args.scene, frames=args.frames or 100, zenithal=args.zenithal)
    print(keypoints.format_table(res))
    return res


def _accuracy(args, out: Path) -> dict:
    from app.benchmarks.accuracy import bench_accuracy, command_line, format_report, parse_seeds
    from app.simulation.random_scene import RANDOM_SECONDS

    seeds = parse_seeds(args.seeds)
    extra = (["--layout", str(Path(args.layout).resolve())] if args.layout else [])
    extra += (["--config", str(Path(args.config).resolve())] if args.config else [])
    for item in args.set:
        extra += ["--set", item]
    resolve_layout(args)   # a bad layout or --set is one line here, not once per scene
    seconds = RANDOM_SECONDS if args.seconds == 10.0 else args.seconds   # 10: the option's default
    print(f"smartroom bench accuracy: seeds {args.seeds}, {seconds:g} s each; runs in {out}", file=sys.stderr)
    result = bench_accuracy(seeds, out, seconds, extra, command_line(args.smartroom),
                            progress=lambda line: print(line, file=sys.stderr, flush=True))
    print(format_report(result["rows"], result["aggregate"]))
    return result


def _marker(args, out: Path) -> dict:
    from app.benchmarks.marker import bench_marker, format_table, scene_names

    scenes = scene_names(args.marker_scenes)
    grid = None
    if args.marker_grid == "full":   # Fig. 6.13: 360 detectors x 20 filters (hours)
        grid = {"dr": (1.0, 0.9, 0.8, 0.7, 0.6), "fp": (0, 20, 40, 60, 80, 100),
                "sigma2": (0, 20, 40, 60, 80, 100),
                "filters": tuple((L, n) for L in (1, 3, 5, 7) for n in (100, 300, 500, 700, 900))}
    # the thesis's APF: no proposals, each landmark the nearest detection (Eq. 6.5)
    plain = {"proposals": 0.0, "picks": "nearest"} if args.marker_cost != "both_ways" else {}
    rows = bench_marker(scenes, frames=args.frames or 75, grid=grid, cost=args.marker_cost,
                        progress=lambda line: print(line, file=sys.stderr, flush=True), **plain)
    print(format_table(rows, scenes))
    return {"scenes": list(scenes), "rows": rows}


def _streaming(args, out: Path) -> dict:
    from app.benchmarks import streaming
    from app.errors import InputError

    protocols = tuple(p for p in args.protocols.split(",") if p)
    if not protocols or set(protocols) - {"osc", "vmc", "lsl"}:
        raise InputError(f"--protocols {args.protocols!r}: some of osc, vmc, lsl")
    if not 1 <= args.people <= 64 or not 1 <= args.stream_fps <= 1000:
        raise InputError("--people must be 1..64 and --stream-fps 1..1000")
    res = streaming.run(seconds=args.seconds, fps=args.stream_fps, people=args.people, protocols=protocols,
                        progress=lambda line: print(line, file=sys.stderr, flush=True))
    print(streaming.table(res))
    return res


def main(args) -> int:
    from app.errors import InputError

    if args.pose_seeds < 1:
        raise InputError(f"--pose-seeds {args.pose_seeds}: must be at least 1")
    out = resolve_out(args, prefix="runs/bench")
    figures = {"bus": _bus, "pipeline": _pipeline, "reconstruction": _reconstruction, "simulate": _simulate,
               "pose": _pose, "tracking": _tracking, "grabber": _grabber,
               "segmentation": _segmentation, "accuracy": _accuracy, "keypoints": _keypoints,
               "streaming": _streaming, "marker": _marker, "flood": _flood}[args.target](args, out)
    (out / f"bench_{args.target}.json").write_text(json.dumps(figures, indent=1))
    return 0
