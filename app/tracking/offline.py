"""Voxels of a recording computed offline (no bus): segmentation and reconstruction cores
frame by frame, as the pipeline's workers run them (masks and colour at the scale matched
to the voxel size). Training the classifier and ``smartroom bench tracking`` use it so
that every tracker configuration sees the same voxels; the result is kept in a cache
file (``$SMARTROOM_CACHE/voxels``, not in the repository) keyed by recording, size and a hash of the
segmentation and reconstruction code.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

__all__ = ["VoxelFrame", "recording_voxels"]


class VoxelFrame:
    """One frame's voxels: ``frame, t, indices (N,3) uint16, colours (N,3) uint8, surface (N,) bool``
    and the silhouettes they were carved from (camera name -> boolean mask, or None),
    for the ghost test."""

    __slots__ = ("frame", "t", "indices", "colours", "surface", "silhouettes")

    def __init__(self, frame, t, indices, colours, surface, silhouettes: dict | None = None):
        self.frame, self.t = int(frame), float(t)
        self.indices, self.colours, self.surface = indices, colours, surface
        self.silhouettes = silhouettes


def _code_version() -> str:
    """A hash of the code that makes the voxels (segmentation, the backgrounds' still
    people, reconstruction), so a change there never replays voxels the old code made."""
    app = Path(__file__).resolve().parents[1]
    h = hashlib.sha1()
    for f in [app / "segmentation.py", app / "background_views.py", *sorted((app / "reconstruction").glob("*.py"))]:
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def _cache_file(recording: Path, voxel_size: float, frames: int | None, carving: dict) -> Path:
    root = Path(os.environ.get("SMARTROOM_CACHE", Path.home() / ".cache" / "smartroom")).expanduser() / "voxels"
    stamp = (recording / "calibration.yaml").stat().st_mtime_ns
    test = ",".join(f"{k}={carving[k]}" for k in sorted(carving))
    key = hashlib.sha1(f"{recording.resolve()}|{stamp}|{voxel_size:.4f}|{frames}|{test}|{_code_version()}".encode()
                       ).hexdigest()[:16]
    return root / f"{recording.name}-{int(round(voxel_size * 1000))}mm-{key}.npz"


def recording_voxels(recording, voxel_size: float, frames: int | None = None, cache: bool = True,
                     progress=None, carving: dict | None = None) -> tuple[list[VoxelFrame], dict]:
    """The voxels of the first ``frames`` frames of ``recording`` (all by default) and the
    grid ``{"origin", "dims", "voxel_size"}``, carved with the occupancy test ``carving``
    (``tolerance``, ``min_views``, ``miss_support``; default: the pipeline's,
    :data:`app.reconstruction.PIPELINE_CARVING`). The frames carry no silhouettes (the
    cache keeps voxels only): their ghost test asks the voxels' projections alone."""
    from app.reconstruction import PIPELINE_CARVING

    recording = Path(recording)
    carving = {**PIPELINE_CARVING, **(carving or {})}
    path = _cache_file(recording, voxel_size, frames, carving)
    if cache and path.is_file():
        with np.load(path) as z:   # each z[...] reads the whole array: read each once
            arrays = {k: z[k] for k in z.files}
        counts = arrays["counts"]
        ends = np.cumsum(counts)
        starts = ends - counts
        idx, col, surf = arrays["indices"], arrays["colours"], arrays["surface"]
        out = [VoxelFrame(f, t, idx[a:b], col[a:b], surf[a:b])
               for f, t, a, b in zip(arrays["frames"], arrays["times"], starts, ends)]
        return out, {"origin": arrays["origin"].tolist(), "dims": arrays["dims"].tolist(),
                     "voxel_size": float(voxel_size)}
    out, grid = _compute(recording, voxel_size, frames, progress, carving)
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".partial.npz")
        np.savez(tmp, frames=np.array([v.frame for v in out]), times=np.array([v.t for v in out]),
                 counts=np.array([len(v.indices) for v in out]),
                 indices=np.concatenate([v.indices for v in out]) if out else np.zeros((0, 3), np.uint16),
                 colours=np.concatenate([v.colours for v in out]) if out else np.zeros((0, 3), np.uint8),
                 surface=np.concatenate([v.surface for v in out]) if out else np.zeros(0, bool),
                 origin=np.asarray(grid["origin"]), dims=np.asarray(grid["dims"]))
        os.replace(tmp, path)
    return out, grid


def _compute(recording: Path, voxel_size: float, frames, progress, carving: dict):
    from app.reconstruction import Reconstructor
    from app.recording import Recording
    from app.segmentation import SegmentationParams, camera_segmenter, recording_background, matched_scale

    rec = Recording(recording)
    calib = rec.calibration
    scale = matched_scale(calib, voxel_size)
    params = SegmentationParams(scale=scale)
    segs = {}
    for cam in rec.cameras:
        # as the segmentation worker: people left out, the floor's shadow test
        segs[cam] = camera_segmenter(params, recording_background(rec, cam), calib, cam)
    fps = float(getattr(calib, "fps", 25.0) or 25.0)
    recon = None
    out = []
    for i, images in rec.frames(stop=frames):
        masks, colours = {}, {}
        for cam, img in images.items():
            masks[cam] = segs[cam].apply(img)
            colours[cam] = segs[cam].small
        if recon is None:
            recon = Reconstructor(calib, voxel_size, mask_sizes={c: m.shape[::-1] for c, m in masks.items()},
                                  colour_sizes={c: im.shape[1::-1] for c, im in colours.items()}, **carving)
        idx, col, surf, _ = recon.reconstruct(masks, colours)
        out.append(VoxelFrame(i, i / fps, np.array(idx), np.array(col), np.array(surf, dtype=bool)))
        if progress and i % 100 == 0:
            progress(i)
    g = recon.grid
    return out, {"origin": [float(v) for v in g.origin], "dims": [int(v) for v in g.dims],
                 "voxel_size": float(voxel_size)}


def track_frames(frames, grid: dict, params=None, classifier=None, timings: dict | None = None, calibration=None):
    """Run CCA (+ person test) and the multi-tracker over voxel frames, as the workers
    do; ``{frame: (ids, positions)}``. With the run's ``calibration``, new tracks pass
    the ghost test as in the tracking worker (``tracking.ghosts``, its default).
    ``timings`` (optional) gets the per-frame ms of ``cca`` and ``tracking`` (wall
    clock) and ``cca_cpu`` and ``tracking_cpu`` (this thread's CPU time: what one core
    spends, whatever else shares the machine)."""
    import time

    from app.tracking.blobs import ComponentAnalysis
    from app.tracking.scene import OccupancyIndex, SceneFrame
    from app.tracking.tracker import MultiTracker

    cca = ComponentAnalysis(grid["dims"], grid["origin"], grid["voxel_size"], classifier)
    occupancy = OccupancyIndex(grid["dims"])
    ghost_test = None
    if calibration is not None:
        from app.tracking.ghosts import GhostTest

        ghost_test = GhostTest(calibration.cameras)
    tracker = MultiTracker(params, classifier, ghost_test)
    out = {}
    for v in frames:
        c0, t0 = time.thread_time(), time.perf_counter()
        labels, feats, person = cca(v.indices)
        c1, t1 = time.thread_time(), time.perf_counter()
        scene = SceneFrame(v.frame, v.t, v.indices, v.colours, v.surface, labels, feats, person,
                           grid["origin"], grid["voxel_size"], occupancy, v.silhouettes)
        out[v.frame] = tracker.update(scene)
        c2, t2 = time.thread_time(), time.perf_counter()
        if timings is not None:
            timings.setdefault("cca", []).append((t1 - t0) * 1e3)
            timings.setdefault("tracking", []).append((t2 - t1) * 1e3)
            timings.setdefault("cca_cpu", []).append((c1 - c0) * 1e3)
            timings.setdefault("tracking_cpu", []).append((c2 - c1) * 1e3)
    return out
