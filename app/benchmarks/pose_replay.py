"""``smartroom bench pose --replay RUN``: the pose stage again over a pipeline run's own
voxels, once per filter seed, scored against the recording's ground truth.

What a pose change is worth on the pipeline's input is easy to misread: the pose filters
draw random particles, and one scene's MMTA moves by 0.01-0.02 from one seed to the next
(meeting3 at 4 cm: 0.79-0.85 over 30 seeds), more than most changes gain. This replays a
run made with ``--set recorder.voxels=true``: its ``voxels.bin`` through the tracker (the
tracking worker's defaults and its ghost test, as :func:`app.tracking.offline.track_frames`
runs it with the recording's calibration) and a
:class:`~app.pose.estimator.PoseEstimator` with the run's pose worker parameters (its
``layout.yaml``) and overrides, each frame posed as the worker poses it
(:func:`app.pose.selection.pose_frame`). With the run's own seed it gives the run's poses;
other seeds give the spread, and the same seeds with and without an override give paired
differences.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.errors import InputError

__all__ = ["replay_poses", "format_replay"]


def _pose_params(results: Path, overrides: dict) -> dict:
    """The run's pose worker parameters with ``overrides``, validated as a layout's."""
    from app.config import apply_overrides, load_layout

    path = results / "layout.yaml"
    if not path.is_file():
        raise InputError(f"{path}: file not found (the results of smartroom run)")
    layout = load_layout(path)
    specs = [w for w in layout.workers if w.kind == "pose"]
    if len(specs) != 1:
        raise InputError(f"{path}: expected one pose worker, found {len(specs)}")
    if overrides:
        layout = apply_overrides(layout, {specs[0].name: overrides}, "--pose-set")
    return dict(layout.worker(specs[0].name).params)


def _tracks(msgs, calibration) -> dict:
    from app.tracking.classifier import DEFAULT_TREE, load_tree
    from app.tracking.offline import VoxelFrame, track_frames
    from app.tracking.tracker import TrackerParams

    frames = [VoxelFrame(m.frame, m.t, m.indices.reshape(-1, 3), m.colours, m.surface,
                         dict(zip(m.cameras, m.silhouette_masks())) or None) for m in msgs]
    grid = {"origin": list(msgs[0].origin), "dims": list(msgs[0].dims), "voxel_size": float(msgs[0].voxel_size)}
    return dict(track_frames(frames, grid, TrackerParams(), load_tree(DEFAULT_TREE), calibration=calibration).items())


def _truth(recording: Path) -> dict:
    from app.evaluation.pose import ground_truth_poses
    from app.files import read_jsonl

    path = recording / "groundtruth.jsonl"
    if not path.is_file():
        raise InputError(f"{path}: file not found (the replay scores against the recording's ground truth)")
    return ground_truth_poses(read_jsonl(path))


def replay_poses(results, recording, seeds=(0,), overrides: dict | None = None, epsilon: float = 0.1,
                 verbose: bool = True) -> dict:
    """``{"rows": [{seed, mmta, mmtp_mm, mpjpe_mm, pcp, cpu_ms}], "summary": {...}, "params": ...}``
    for each of ``seeds``; ``overrides``: pose worker parameters (``coverage``, ``voxels``, ...)."""
    from app.evaluation.pose import pose_report
    from app.pose.estimator import PoseEstimator, PoseSettings
    from app.pose.selection import pose_frame
    from app.results import iter_voxels

    results, recording = Path(results), Path(recording)
    params = _pose_params(results, overrides or {})
    path = results / "voxels.bin"
    if not path.is_file():
        raise InputError(f"{path}: file not found (run with --set recorder.voxels=true to keep the voxels)")
    msgs = list(iter_voxels(path))
    if not msgs:
        raise InputError(f"{path}: no frames")
    truth = _truth(recording)
    missing = [m.frame for m in msgs if m.frame not in truth]
    if missing:
        raise InputError(f"{recording}: no ground truth for frame {missing[0]} of {path} (another recording?)")
    from calibration import load_calibration
    calibration = load_calibration(recording / "calibration.yaml")
    tracks = _tracks(msgs, calibration)   # with the ghost test, as the tracking worker
    if verbose and float(params.get("silhouette", 0)) > 0 and not any(m.silhouette_sizes for m in msgs):
        print(f"{path}: the voxels carry no silhouettes (a run of an older build, or reconstruction.silhouettes=0): "
              "posed without the silhouette term", flush=True)
    vs = round(float(msgs[0].voxel_size), 6)
    lo = tuple(float(v) for v in msgs[0].origin)
    hi = tuple(np.asarray(lo) + np.asarray(msgs[0].dims) * vs)
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)))
    rows = []
    for seed in seeds:
        settings = PoseSettings.from_params({**params, "seed": int(seed)})
        try:
            settings.validate()
        except ValueError as exc:
            raise InputError(f"pose: {exc}") from None
        settings.voxel_size, settings.room_lo, settings.room_hi = vs, lo, hi
        est = PoseEstimator(settings)
        scored = []
        t0 = time.process_time()
        for m in msgs:
            ids, positions = tracks.get(m.frame, empty)
            result = pose_frame(est, m, ids, positions, params, calibration=calibration).result
            people, visible = truth[m.frame]
            scored.append((people, {t: r[0] for t, r in result.items()}, visible))
        cpu = (time.process_time() - t0) / len(msgs) * 1e3
        rep = pose_report(scored, epsilon=epsilon)
        row = {"seed": int(seed), "mmta": rep["mmta"], "mmtp_mm": rep["mmtp_mm"], "mpjpe_mm": rep["mpjpe_mm"],
               "pcp": rep.get("pcp"), "cpu_ms": round(cpu, 1)}
        rows.append(row)
        if verbose:
            print(_line(row), flush=True)
    mmta = np.array([r["mmta"] for r in rows], dtype=float)
    summary = {"seeds": len(rows), "frames": len(msgs), "mmta_mean": round(float(mmta.mean()), 4),
               "mmta_sd": round(float(mmta.std(ddof=1)), 4) if len(rows) > 1 else 0.0,
               "mmta_min": float(mmta.min()), "mmta_median": float(np.median(mmta)), "mmta_max": float(mmta.max()),
               "mmtp_mm_mean": round(float(np.mean([r["mmtp_mm"] for r in rows])), 2)}
    return {"rows": rows, "summary": summary, "params": {k: params[k] for k in sorted(params)}}


HEADER = f"{'seed':>5}{'MMTA':>8}{'MMTP mm':>9}{'MPJPE mm':>10}{'PCP':>7}{'cpu ms':>8}"


def _line(r: dict) -> str:
    pcp = f"{r['pcp']:.3f}" if isinstance(r.get("pcp"), float) else "-"
    return f"{r['seed']:>5}{r['mmta']:>8.4f}{r['mmtp_mm']:>9.1f}{r['mpjpe_mm']:>10.1f}{pcp:>7}{r['cpu_ms']:>8.1f}"


def format_replay(out: dict) -> str:
    s = out["summary"]
    return (f"{s['seeds']} seed(s) over {s['frames']} frames: MMTA mean {s['mmta_mean']:.4f} sd {s['mmta_sd']:.4f} "
            f"(min {s['mmta_min']:.4f}, median {s['mmta_median']:.4f}, max {s['mmta_max']:.4f}), "
            f"MMTP mean {s['mmtp_mm_mean']:.1f} mm")
