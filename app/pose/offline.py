"""Pose estimation offline on a simulated clip: the frames' voxels, ground-truth tracks
and joints, and the estimator run over them with timings. Used by the tests and by
``smartroom bench pose``.

Voxels come either from the simulator's body primitives (``source="true"``: the
voxels whose centre lies inside a body, :mod:`app.simulation.occupancy`) or from
shape from silhouette of the true silhouettes (``source="hull"``: what the
reconstruction stage makes of perfect masks, with its visual-hull excess).
Tracks are the true centroids (the tracking stage's job is scored elsewhere).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from app.messages import JOINTS
from app.pose.estimator import PoseEstimator, PoseSettings

__all__ = ["ClipFrame", "simulated_clip", "run_clip"]


@dataclass
class ClipFrame:
    frame: int
    centres: np.ndarray          # (N, 3) occupied voxel centres
    surface: np.ndarray | None   # (N,) or None
    ids: list
    positions: np.ndarray        # (P, 3) true centroids
    truth: dict                  # id -> (15, 3)
    visible: dict                # id -> (15,) bool


def simulated_clip(scene: str, frames, voxel_size: float = 0.02, seed: int = 0, source: str = "true",
                   zenithal: bool = True, hide=None) -> tuple[list[ClipFrame], object]:
    """Frames ``frames`` (an iterable of indices) of a simulated scene; ``hide(frame,
    centres) -> keep mask`` can remove voxels (a deliberate occlusion)."""
    from app.simulation.occupancy import true_occupancy
    from app.simulation.simulator import Simulator

    frames = list(frames)
    sim = Simulator(scene, seed=seed, seconds=(max(frames) + 2) / 25.0, zenithal=zenithal)
    cal = sim.calibration
    dims = np.ceil((np.asarray(cal.room_max) - np.asarray(cal.room_min)) / voxel_size - 1e-9).astype(np.int64)
    rec = None
    if source == "hull":
        from app.reconstruction import Reconstructor
        size = (320, 240)
        rec = Reconstructor(cal, voxel_size, mask_sizes={c: size for c in sim.cameras}, colouring="none", min_top=0.25)
    out = []
    for i in frames:
        people = sim.people(i)
        gt = sim.groundtruth(i, people)
        if source == "true":
            idx = true_occupancy(sim.body_record(i, people), cal.room_min, voxel_size, dims)
            surface = None
        elif source == "hull":
            import cv2
            _, labels, _ = sim.render(i, noise=False)
            masks = {c: cv2.resize((labels[c] >= 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
                     .astype(bool) for c in sim.cameras}
            idx, _, surface, _ = rec.reconstruct(masks, {})
        else:
            raise ValueError(f"voxel source {source!r} is not true or hull")
        centres = np.asarray(cal.room_min) + (idx + 0.5) * voxel_size
        if hide is not None:
            keep = hide(i, centres)
            centres = centres[keep]
            surface = None if surface is None or len(surface) == 0 else np.asarray(surface)[keep]
        ids = [p["id"] for p in gt["people"]]
        out.append(ClipFrame(
            frame=i, centres=centres, surface=surface, ids=ids,
            positions=np.array([p["centroid"] for p in gt["people"]], dtype=float).reshape(-1, 3),
            truth={p["id"]: np.array([p["joints"][n] for n in JOINTS]) for p in gt["people"]},
            visible={p["id"]: np.array([p.get("visible", {}).get(n, True) for n in JOINTS]) for p in gt["people"]}))
    return out, cal


def run_clip(clip: list[ClipFrame], settings: PoseSettings, corrupt=None) -> dict:
    """Run the estimator over a clip: ``{"estimates": [{id: joints}], "active":
    [{id: flags}], "ms": [...], "cpu_ms": [...]}`` (wall and thread CPU time per frame).
    ``corrupt(frame, estimator)`` may tamper with the
    filters before a frame (recovery tests)."""
    est = PoseEstimator(settings)
    estimates, active, ms, cpu_ms = [], [], [], []
    for fr in clip:
        if corrupt is not None:
            corrupt(fr.frame, est)
        t0, c0 = time.perf_counter(), time.thread_time()
        res = est.update(fr.centres, fr.surface, fr.ids, fr.positions)
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
