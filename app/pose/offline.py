"""Pose estimation offline on a simulated clip: the frames' voxels, ground-truth tracks
and joints, and the estimator run over them with timings. Used by the tests and by
``smartroom bench pose``.

Voxels come from the simulator's body primitives (``source="true"``: the
voxels whose centre lies inside a body, :mod:`app.simulation.occupancy`), from
shape from silhouette of the true silhouettes (``source="hull"``: what the
reconstruction stage makes of perfect masks, with its visual-hull excess) or of the
segmentation's MOG2 masks of the rendered (noisy) images (``source="mog2"``: what the
pipeline really sees, the codec aside), at the mask scale the pipeline picks for the
voxel size. ``tolerance`` (k of §2.2.4) and ``occlusion`` go to the reconstruction.
Tracks are the true centroids (the tracking stage's job is scored elsewhere).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from app.evaluation.pose import ground_truth_poses
from app.messages import JOINTS
from app.pose.estimator import PoseEstimator, PoseSettings
from app.segmentation import SILHOUETTE_FACTOR, reduce_mask

__all__ = ["ClipFrame", "simulated_clip", "run_clip", "clip_errors", "people_errors"]


@dataclass
class ClipFrame:
    frame: int
    centres: np.ndarray          # (N, 3) occupied voxel centres
    surface: np.ndarray | None   # (N,) or None
    ids: list
    positions: np.ndarray        # (P, 3) true centroids
    truth: dict                  # id -> (15, 3)
    visible: dict                # id -> (15,) bool
    silhouettes: list | None = None   # the masks carved (hull, mog2), reduced as the reconstruction sends them
    cameras: list | None = None       # ... their cameras
    colours: np.ndarray | None = None  # (N, 3) RGB of the voxels (hull, mog2 with colours=True)


SOURCES = ("true", "hull", "mog2")


def simulated_clip(scene: str, frames, voxel_size: float = 0.02, seed: int = 0, source: str = "true",
                   zenithal: bool = True, hide=None, tolerance: int = 1, occlusion: str = "none",
                   surface: bool = False, colours: bool = False) -> tuple[list[ClipFrame], object]:
    """Frames ``frames`` (an iterable of indices) of a simulated scene; ``hide(frame,
    centres) -> keep mask`` can remove voxels (a deliberate occlusion). ``surface``:
    hull voxels carry the reconstruction's visibility surface flags (as in the
    pipeline) instead of the 6-neighbour boundary the observation computes. For
    ``mog2`` every frame from 0 is segmented (the background model adapts over the
    run), only ``frames`` are reconstructed. ``colours``: hull and mog2 voxels carry the
    reconstruction's colours (its visibility colouring, as the pipeline's)."""
    from app.simulation.occupancy import true_occupancy
    from app.simulation.simulator import Simulator

    frames = list(frames)
    sim = Simulator(scene, seed=seed, seconds=(max(frames) + 2) / 25.0, zenithal=zenithal)
    cal = sim.calibration
    dims = np.ceil((np.asarray(cal.room_max) - np.asarray(cal.room_min)) / voxel_size - 1e-9).astype(np.int64)
    if source not in SOURCES:
        raise ValueError(f"voxel source {source!r} is not one of {', '.join(SOURCES)}")
    rec = segs = None
    if source in ("hull", "mog2"):
        from app.reconstruction import Reconstructor
        from app.segmentation import SegmentationParams, camera_segmenter, matched_scale
        scale = matched_scale(cal, voxel_size)
        sizes = {c.name: (c.width // scale, c.height // scale) for c in cal.cameras}
        rec = Reconstructor(cal, voxel_size, mask_sizes=sizes,
                            colouring="visibility" if (surface or colours) else "none",
                            min_top=0.25, tolerance=tolerance, occlusion=occlusion)
        if source == "mog2":
            # as the segmentation worker builds them: the floor's dark-shadow test needs the calibration
            segs = {c: camera_segmenter(SegmentationParams(scale=scale), sim.background(c), cal, c)
                    for c in sim.cameras}
    wanted = set(frames)
    out = []
    for i in range(min(frames) if segs is None else 0, max(frames) + 1):
        if i not in wanted and segs is None:
            continue
        people = sim.people(i)
        gt = sim.groundtruth(i, people)
        flags = voxel_colours = None
        if source == "true":
            idx = true_occupancy(sim.body_record(i, people), cal.room_min, voxel_size, dims)
            silhouettes = None     # true body voxels: no masks were carved
        else:
            import cv2
            images, labels, _ = sim.render_people(i, people, noise=source == "mog2")
            if source == "hull":
                masks = {c: cv2.resize((labels[c] >= 0).astype(np.float32), sizes[c], interpolation=cv2.INTER_AREA)
                         >= 0.5 for c in sim.cameras}
            else:
                masks = {c: segs[c].apply(images[c]) for c in sim.cameras}
            if i not in wanted:
                continue
            small = {c: cv2.resize(images[c], sizes[c], interpolation=cv2.INTER_AREA) for c in sim.cameras} \
                if (surface or colours) else {}
            idx, voxel_colours, flags, _ = rec.reconstruct(masks, small)
            voxel_colours = voxel_colours if colours and len(voxel_colours) == len(idx) else None
            silhouettes = [reduce_mask(masks[c], SILHOUETTE_FACTOR) for c in sim.cameras]
            flags = flags if surface and len(flags) == len(idx) else None
        surface_flags = flags
        centres = np.asarray(cal.room_min) + (idx + 0.5) * voxel_size
        if hide is not None:
            keep = hide(i, centres)
            centres = centres[keep]
            voxel_colours = None if voxel_colours is None else voxel_colours[keep]
            surface_flags = None if surface_flags is None else np.asarray(surface_flags)[keep]
        ids = [p["id"] for p in gt["people"]]
        truth, visible = ground_truth_poses([gt])[i]
        out.append(ClipFrame(
            frame=i, centres=centres, surface=surface_flags, ids=ids,
            positions=np.array([p["centroid"] for p in gt["people"]], dtype=float).reshape(-1, 3),
            truth=truth, visible=visible,
            silhouettes=silhouettes, cameras=None if silhouettes is None else list(sim.cameras),
            colours=voxel_colours))
    return out, cal


def run_clip(clip: list[ClipFrame], settings: PoseSettings, corrupt=None, calibration=None) -> dict:
    """Run the estimator over a clip: ``{"estimates": [{id: joints}], "active":
    [{id: flags}], "ms": [...], "cpu_ms": [...]}`` (wall and thread CPU time per frame).
    ``corrupt(frame, estimator)`` may tamper with the
    filters before a frame (recovery tests). With ``calibration`` and ``settings.silhouette``
    > 0 the frames' silhouettes are scored too (:mod:`app.pose.silhouette`)."""
    from app.pose.selection import silhouette_view

    est = PoseEstimator(settings)
    estimates, active, ms, cpu_ms = [], [], [], []
    for fr in clip:
        if corrupt is not None:
            corrupt(fr.frame, est)
        t0, c0 = time.perf_counter(), time.thread_time()
        view, _ = silhouette_view(fr.silhouettes or [], fr.cameras or [], calibration, settings)
        res = est.update(fr.centres, fr.surface, fr.ids, fr.positions, view=view, colours=fr.colours)
        ms.append(1e3 * (time.perf_counter() - t0))
        cpu_ms.append(1e3 * (time.thread_time() - c0))
        estimates.append({k: v[0] for k, v in res.items()})
        active.append({k: v[1] for k, v in res.items()})
    return {"estimates": estimates, "active": active, "ms": ms, "cpu_ms": cpu_ms, "estimator": est}


def clip_errors(clip: list[ClipFrame], estimates: list) -> np.ndarray:
    """Joint errors ``(T, 15)`` of a one-person clip (NaN where no pose)."""
    out = np.full((len(clip), len(JOINTS)), np.nan)
    for t, (fr, est) in enumerate(zip(clip, estimates)):
        for pid, joints in fr.truth.items():
            if est:
                best = min(est.values(), key=lambda j: np.linalg.norm(j[0] - joints[0]))
                out[t] = np.linalg.norm(best - joints, axis=1)
    return out


def people_errors(clip: list[ClipFrame], estimates: list, warmup: int = 0) -> tuple[np.ndarray, int]:
    """Joint errors ``(R, 15)`` of every person of a clip, one row per person and frame
    after the person's first ``warmup`` frames in the room (estimates matched to the truth
    by track id: the clip's tracks are the true people), and the joints of those frames a
    person had no pose (missed, for :func:`app.evaluation.pose.point_metrics`)."""
    rows, missed, seen = [], 0, {}
    for fr, est in zip(clip, estimates):
        for pid, joints in fr.truth.items():
            seen[pid] = seen.get(pid, 0) + 1
            if seen[pid] <= warmup:
                continue
            if pid in est:
                rows.append(np.linalg.norm(est[pid] - joints, axis=1))
            else:
                missed += len(JOINTS)
    return np.array(rows).reshape(-1, len(JOINTS)), missed
