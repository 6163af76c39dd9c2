"""``smartroom bench pose``: ms per frame of the pose filters on one core next to their
accuracy (MMTA / MMTP at 100 mm, MPJPE), so the accuracy price of the model density
(Eq. 6.26, the thesis's Fig. 6.18) and the APF < SHBM-APF ordering are visible in one
table.

Each row runs one method at one density over the same simulated clip(s): one person,
voxels of the true body at ``voxel_size`` (default 2 cm), the visual hull of the
true silhouettes (``source="hull"``) or of the MOG2 masks (``source="mog2"``), true
centroids as tracks (the hulls' voxels coloured as the pipeline's when the behaviour
method is in: its blobs' evidence; true-body voxels have no colours). Times are wall clock
and the thread's CPU time (the latter is what one core costs when other processes
share the machine). The first
``warmup`` frames (lock-on and kernel compilation) are timed but not scored.
"""
from __future__ import annotations

import numpy as np

from app.evaluation.pose import point_metrics
from app.pose.estimator import PoseSettings
from app.pose.offline import people_errors, run_clip, simulated_clip

__all__ = ["bench_pose", "format_table", "CONFIGS"]

#: (label, method, extra settings)
CONFIGS = (
    ("APF 600x6", "apf", {"particles": 600, "layers": 6}),
    ("SHBM-APF", "shbm", {}),
    ("DDM-APF", "ddm", {}),
    ("SHBM+DDM", "shbm+ddm", {}),
    ("Behaviour", "behaviour", {}),
)


def bench_pose(scenes=("gesture1", "walk1"), frames: int = 75, start: int = 0, voxel_size: float = 0.02,
               densities=(1, 2, 3), methods=("apf", "shbm", "ddm"), source: str = "true", warmup: int = 5,
               epsilon: float = 0.1, verbose: bool = True, tolerance: int = 1, occlusion: str = "none",
               settings: dict | None = None, seeds=(0,), surface: bool = False, step: int = 1) -> list[dict]:
    """``source``: ``true`` (body voxels), ``hull`` (shape from the true silhouettes) or
    ``mog2`` (shape from the segmentation's MOG2 masks of the rendered images, the
    pipeline's reconstruction) with ``tolerance`` k and ``occlusion``; ``settings``:
    :class:`PoseSettings` overrides (e.g. ``{"coverage": 0}`` for the thesis's
    likelihood); ``seeds``: filter seeds, errors pooled over them; ``surface``: hull
    voxels carry the reconstruction's visibility surface flags, as in the pipeline
    (default: the 6-neighbour boundary the observation computes). ``scenes``: built-in
    scenes or ``random:SEED`` (:mod:`app.simulation.random_scene`); every person of a
    frame is scored (by track id), each after their first ``warmup`` frames in the room,
    and with several scenes a ``pooled`` row pools every scene's errors. ``step``: every
    ``step``-th frame, the motion ``step`` times as fast."""
    clips, cals = {}, {}
    for scene in scenes:
        name, _, seed = scene.partition(":")
        clips[scene], cals[scene] = simulated_clip(name, range(start, start + frames * step, step), voxel_size,
                                                   seed=int(seed or 0), source=source, tolerance=tolerance,
                                                   occlusion=occlusion, surface=surface,
                                                   colours="behaviour" in methods)
    rows = []
    for label, method, extra in CONFIGS:
        if method not in methods:
            continue
        for density in densities:
            pooled = {"E": [], "missed": 0, "ms": [], "cpu": []}
            for scene, clip in clips.items():
                cal = cals[scene]
                Es, missed, ms, cpu = [], 0, [], []
                for seed in seeds:
                    s = PoseSettings(method=method, voxel_size=voxel_size, density=float(density), seed=int(seed),
                                     room_lo=tuple(cal.room_min), room_hi=tuple(cal.room_max),
                                     **{**extra, **(settings or {})})
                    res = run_clip(clip, s, calibration=cal)   # silhouettes scored when s.silhouette > 0
                    E, lost = people_errors(clip, res["estimates"], warmup)
                    Es.append(E)
                    missed += lost
                    ms += res["ms"][warmup:]
                    cpu += res["cpu_ms"][warmup:]
                parts = [(scene, len(clip), Es, missed, ms, cpu)]
                pooled["E"] += Es
                pooled["missed"] += missed
                pooled["ms"] += ms
                pooled["cpu"] += cpu
                if len(clips) > 1 and scene == list(clips)[-1]:
                    parts.append(("pooled", sum(map(len, clips.values())), pooled["E"], pooled["missed"],
                                  pooled["ms"], pooled["cpu"]))
                for name, n, Es, missed, ms, cpu in parts:
                    row = _row(label, name, density, n, np.concatenate(Es), missed, ms, cpu, epsilon)
                    rows.append(row)
                    if verbose:
                        print(_line(row), flush=True)
    return rows


def _row(label, scene, density, frames, E, missed, ms, cpu, epsilon) -> dict:
    """One table row: the frames' times (ms, all the frame's people) and the pooled errors."""
    m = point_metrics(E, epsilon, missed)
    ms, cpu = np.array(ms), np.array(cpu)
    return {"method": label, "scene": scene, "density": density, "frames": frames,
            "ms_p50": round(float(np.median(ms)), 1), "ms_p95": round(float(np.percentile(ms, 95)), 1),
            "cpu_ms_p50": round(float(np.median(cpu)), 1), "person_frames": int(len(E)),
            "mmta": m.get("mmta", 0.0), "mmtp_mm": m.get("mmtp_mm"), "mpjpe_mm": m.get("mpjpe_mm", float("nan")),
            "mu_mm": m.get("mu_mm"), "sigma_mm": m.get("sigma_mm")}


HEADER = (f"{'method':<12}{'scene':<13}{'density':>8}{'ms p50':>9}{'ms p95':>9}{'cpu p50':>9}{'MMTA':>8}{'MMTP mm':>9}"
          f"{'MPJPE mm':>10}")


def _line(r) -> str:
    return (f"{r['method']:<12}{r['scene']:<13}{r['density']:>8}{r['ms_p50']:>9.1f}{r['ms_p95']:>9.1f}"
            f"{r.get('cpu_ms_p50', 0):>9.1f}{r['mmta']:>8.3f}{r['mmtp_mm'] or 0:>9.1f}{r['mpjpe_mm']:>10.1f}")


def format_table(rows) -> str:
    return "\n".join([HEADER] + [_line(r) for r in rows])
