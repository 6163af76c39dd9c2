"""``smartroom bench reconstruction``: segmentation + shape from silhouette + colouring
+ surface per frame, on one core, against the real-time budget (issue 4), and the
reconstruction's accuracy against the true body volume.

The frames of a recording (default: the simulated meeting3 with 5 cameras) go through
the segmentation core (every camera, in order, as the worker does: masks and colour
images at half size) and then through the reconstruction core for every voxel size x
{flat, hierarchical} x {raw, coloured}. The table reports ms per frame (p50 and p95)
of segmentation of all cameras, of reconstruction, and of both, and the occupied
voxels per frame; accuracy (recall, precision, spurious voxels, floor shadow blobs)
is scored with the hierarchical method (it gives the same voxels as the flat one).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from app.segmentation import shrink

__all__ = ["segment_frames", "run", "format_table", "BUDGET_MS", "hull_table", "format_hull_table"]

#: issue 4's targets: segmentation + reconstruction + colouring + surface per frame
BUDGET_MS = {0.02: 40.0, 0.04: 15.0}


def segment_frames(recording, frames: int, scale: int = 2, colour_scale: int | None = None):
    """The first ``frames`` frames through the segmentation core at one mask scale:
    ``(calibration, [(masks, images)], segmentation ms per frame (all cameras), frame
    indices)``; colour images at ``colour_scale`` (default: the mask scale)."""
    from app.recording import Recording
    from app.segmentation import SegmentationParams, camera_segmenter, recording_background

    rec = Recording(recording)
    colour_scale = scale if colour_scale is None else colour_scale
    params = SegmentationParams(scale=scale)
    segs = {}
    for cam in rec.cameras:
        # the floor region, as the worker
        segs[cam] = camera_segmenter(params, recording_background(rec, cam), rec.calibration, cam)
    out, seg_ms, indices = [], [], []
    for i, images in rec.frames(stop=frames):
        t0 = time.perf_counter()
        masks, colours = {}, {}
        for cam, img in images.items():
            masks[cam] = segs[cam].apply(img)
            colours[cam] = segs[cam].small if colour_scale == scale else shrink(img, colour_scale)
        seg_ms.append((time.perf_counter() - t0) * 1e3)
        out.append((masks, colours))
        indices.append(i)
    return rec.calibration, out, np.asarray(seg_ms), indices


def _accuracy(recording, calib, frames, indices, voxel_size: float, warmup: int, **options) -> dict:
    """Recall, precision, spurious and ghost voxels, floor shadow blobs (hierarchical)."""
    from app.evaluation.reconstruction import score_frame, summarise_scores
    from app.reconstruction import Reconstructor
    from app.simulation.occupancy import load_bodies, true_occupancy

    if not (Path(recording) / "bodies.jsonl").is_file():
        return {}
    bodies = {r["frame"]: r for r in load_bodies(recording)}
    masks0, images0 = frames[0]
    r = Reconstructor(calib, voxel_size, mask_sizes={c: m.shape[::-1] for c, m in masks0.items()},
                      colour_sizes={c: im.shape[1::-1] for c, im in images0.items()}, colouring="none", **options)
    scores = []
    for (masks, _), i in zip(frames[warmup:], indices[warmup:]):
        idx = r.carve(masks)
        truth = true_occupancy(bodies[i], r.grid.origin, voxel_size, r.grid.dims)
        scores.append(score_frame(i, idx, truth, r.grid.dims, voxel_size))
    return summarise_scores(scores)


def run(recording, frames: int = 60, voxel_sizes=(0.02, 0.03, 0.04, 0.05), methods=("flat", "hierarchical"),
        colourings=("none", "visibility"), warmup: int = 10, tolerance: int = 1, min_top: float = 0.25,
        verbose=True) -> dict:
    """The benchmark table (rows) and the accuracy per voxel size; each voxel size is
    fed masks at the scale matched to it (:func:`app.segmentation.matched_scale`), as
    the pipeline does."""
    from app.reconstruction.bench import bench_reconstruction
    from app.recording import Recording
    from app.segmentation import matched_scale

    calib = Recording(recording).calibration
    by_scale: dict[int, tuple] = {}
    rows, accuracy = [], {}
    for vs in voxel_sizes:
        scale = matched_scale(calib, vs)
        if scale not in by_scale:
            by_scale[scale] = segment_frames(recording, frames, scale)
        _, segmented, seg_ms, indices = by_scale[scale]
        timed = segmented[warmup:]   # the background models settle on the first frames
        seg = seg_ms[warmup:]
        for row in bench_reconstruction(calib, timed, (vs,), methods, colourings, warmup=2, verbose=False,
                                        tolerance=tolerance, min_top=min_top):
            per_frame = np.asarray(row.pop("total_per_frame"))
            total = per_frame + seg[:len(per_frame)]
            row["mask_scale"] = scale
            row["segmentation_p50"] = float(np.percentile(seg, 50))
            row["segmentation_p95"] = float(np.percentile(seg, 95))
            row["frame_p50"] = float(np.percentile(total, 50))
            row["frame_p95"] = float(np.percentile(total, 95))
            rows.append(row)
            if verbose:
                print(format_row(row), flush=True)
        accuracy[f"{vs:g}"] = _accuracy(recording, calib, segmented, indices, vs, warmup, tolerance=tolerance,
                                        min_top=min_top)
    return {"recording": str(recording), "cameras": len(calib.cameras), "frames": frames - warmup,
            "tolerance": tolerance, "min_top": min_top, "rows": rows, "accuracy": accuracy}


HEADER = (f"{'voxel':>5} {'mask':>7} {'method':<12} {'colour':<10} {'occupied':>8} {'seg p50/p95':>13} "
          f"{'recon p50/p95':>14} {'frame p50/p95':>14} {'budget':>7}")


def format_row(r: dict) -> str:
    budget = BUDGET_MS.get(round(r["voxel_size"], 3))
    verdict = "" if budget is None or r["colouring"] == "none" else \
        ("ok" if r["frame_p50"] <= budget else "OVER") + f" {budget:.0f}"
    mask = f"1/{r['mask_scale']}"
    return (f"{r['voxel_size'] * 100:4.0f}cm {mask:>7} {r['method']:<12} {r['colouring']:<10} {r['occupied']:8d} "
            f"{r['segmentation_p50']:6.1f}/{r['segmentation_p95']:5.1f} {r['total_p50']:6.1f}/{r['total_p95']:6.1f} "
            f"{r['frame_p50']:6.1f}/{r['frame_p95']:6.1f} {verdict:>7}")


def format_table(result: dict) -> str:
    lines = [f"{result['frames']} frames of {result['cameras']} cameras, ms per frame on one core "
             f"(segmentation of all cameras + reconstruction), k = {result['tolerance']}, "
             f"floor blobs under {result['min_top']} m dropped", HEADER]
    lines += [format_row(r) for r in result["rows"]]
    lines.append(f"{'voxel':>5} {'recall':>7} {'min':>6} {'precision':>9} {'spurious':>9} {'ghost':>7} "
                 f"{'shadow blob>20':>15} {'largest':>8}")
    for vs, a in result["accuracy"].items():
        if a:
            lines.append(f"{float(vs) * 100:4.0f}cm {a['recall']:7.3f} {a['recall_min']:6.3f} {a['precision']:9.3f} "
                         f"{a['spurious_mean']:9.1f} {a['ghost_mean']:7.0f} {100 * a['frames_with_floor_blob_over_20']:14.1f}% "
                         f"{a['floor_blob_max']:8d}")
    return "\n".join(lines)


# -- issue 8: how tight is the hull, and what segmentation and carving each lose --------

#: The carving variants of the hull table: (name, Reconstructor options).
HULL_VARIANTS = (
    ("k=0", {"tolerance": 0}),
    ("k=1", {"tolerance": 1}),
    ("occluders", {"tolerance": 0, "occlusion": "learnt"}),
    ("fused", {"tolerance": 0, "method": "fused"}),
    # the silhouette-edge (footprint) test alone, and with low learnt occluders (issue 8)
    ("k=0 edge", {"tolerance": 0, "footprint": 0.34}),
    ("tight", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0}),
    # the same learning from every 4th frame, one piece of evidence enough: a quarter of the learning's cost
    ("tight/4", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0, "learn_every": 4,
                 "occlusion_evidence": 1}),
    # occlusion learnt per 8 cm cell and camera instead of per pixel (app/reconstruction/occlusion_cells.py)
    ("cells", {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 1.0}),
    # and without the components no camera needs (app/reconstruction/ghosts.py)
    ("tight+g", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0, "ghost_share": 0.2}),
    ("cells+g", {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 1.0, "ghost_share": 0.2}),
    # occlusion only below 0.8 m (the simulated room's tables are lower): the phantoms' volume above it goes
    ("cells+g .8", {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 0.8,
                    "ghost_share": 0.2}),
)


def fused_distances(recording, images: list[dict], scale: int, noise_frames: int = 10) -> list[dict]:
    """Per-pixel squared Mahalanobis distance maps (Caillette's fused method) of the
    frames' images at the mask size: the background model from the recording's
    empty-room image (or the median of its frames), its covariance from the first
    ``noise_frames`` frames."""
    from app.recording import Recording
    from app.segmentation import YuvBackground, estimate_background

    rec = Recording(recording)
    models = {}
    for cam in images[0]:
        bg = rec.background(cam)
        bg = bg if bg is not None else estimate_background(rec.sample(cam, 25))
        models[cam] = YuvBackground(shrink(bg, scale))
        models[cam].fit_noise([f[cam] for f in images[:noise_frames]])
    out, ms = [], []
    for f in images:
        t0 = time.perf_counter()
        out.append({cam: models[cam].distance(im) for cam, im in f.items()})
        ms.append((time.perf_counter() - t0) * 1e3)
    fused_distances.last_ms = ms
    return out
HULL_TARGET = {"volume_ratio": 2.5, "recall": 0.97, "largest_share": 0.9}


def true_silhouettes(recording, frames: int, scale: int) -> list[dict]:
    """The simulator's true silhouettes (every person pixel, whoever's) of the first
    ``frames`` frames of a simulated recording at ``1/scale`` of the image size: a
    pixel is foreground when at least half of it is person (evaluation only: the
    product never sees them)."""
    import json

    import cv2

    from app.errors import InputError
    from app.recording import Recording
    from app.simulation.simulator import Simulator

    path = Path(recording) / "simulation.json"
    if not path.is_file():
        raise InputError(f"{recording}: no simulation.json, so no true silhouettes (a simulated recording is needed)")
    meta = json.loads(path.read_text())
    calib = Recording(recording).calibration
    cam0 = calib.cameras[0]
    sim = Simulator(meta["scene"], seed=meta["seed"], fps=meta["fps"], seconds=meta["seconds"],
                    width=cam0.width, height=cam0.height, zenithal=meta.get("zenithal", False),
                    cameras=list(calib.names))
    out = []
    for i in range(frames):
        _, labels, _ = sim.render(i, noise=False)
        masks = {}
        for cam in calib.cameras:
            w, h = cam.width // scale, cam.height // scale
            person = (labels[cam.name] >= 0).astype(np.float32)
            masks[cam.name] = cv2.resize(person, (w, h), interpolation=cv2.INTER_AREA) >= 0.5
        out.append(masks)
    return out


class HullInput(NamedTuple):
    """The masks the hull benchmarks carve at one voxel size: the matched mask scale,
    the segmented frames (masks, colour images), segmentation ms per frame, frame
    indices, ``[(source, masks per frame)]`` (``mog2`` and, with ``truth``, ``true``) and
    the mask sizes per camera."""
    scale: int
    segmented: list
    seg_ms: np.ndarray
    indices: list
    sources: list
    sizes: dict


def hull_input(recording, calib, frames: int, voxel_size: float, truth: bool = True) -> HullInput:
    """:class:`HullInput` of the first ``frames`` frames of a simulated recording."""
    from app.segmentation import matched_scale

    scale = matched_scale(calib, voxel_size)
    _, segmented, seg_ms, indices = segment_frames(recording, frames, scale)
    sources = [("mog2", [m for m, _ in segmented])]
    if truth:
        sources.append(("true", true_silhouettes(recording, len(indices), scale)))
    sizes = {c: m.shape[::-1] for c, m in segmented[0][0].items()}
    return HullInput(scale, segmented, seg_ms, indices, sources, sizes)


def hull_table(recording, frames: int = 250, voxel_sizes=(0.02, 0.04), warmup: int = 10, min_top: float = 0.25,
               variants=HULL_VARIANTS, truth: bool = True, verbose: bool = True) -> list[dict]:
    """Issue 8's before/after table: for every voxel size, carving variant and mask
    source (the segmentation's MOG2 masks at the matched scale, and the simulator's
    true silhouettes), the hull's volume over the true body volume, recall and the
    fragmentation (largest connected component near each person), scored with
    :func:`app.evaluation.reconstruction.score_frame` on the frames after ``warmup``.
    Every frame is carved in order (learnt occluders learn over the run); carve ms
    p50 per frame is timed on the scored frames, and the segmentation of all cameras
    (MOG2 masks, or the fused method's distance maps from the images at mask size)."""
    from app.evaluation.reconstruction import score_frame, summarise_scores
    from app.reconstruction import Reconstructor
    from app.recording import Recording
    from app.simulation.occupancy import load_bodies, true_occupancy

    calib = Recording(recording).calibration
    bodies = {r["frame"]: r for r in load_bodies(recording)}
    rows = []
    for vs in voxel_sizes:
        scale, segmented, seg_ms, indices, sources, sizes = hull_input(recording, calib, frames, vs, truth)
        truths = {}
        for name, options in variants:
            runs = sources
            if options.get("method") == "fused":     # Caillette: its own per-pixel statistics, no masks
                runs = [("yuv", fused_distances(recording, [im for _, im in segmented], scale))]
            for source, masks_list in runs:
                r = Reconstructor(calib, vs, mask_sizes=sizes, colouring="none", min_top=min_top, **options)
                scores, ms = [], []
                for n, (masks, i) in enumerate(zip(masks_list, indices)):
                    t0 = time.perf_counter()
                    idx = r.carve(masks)
                    if n < warmup:
                        continue
                    ms.append((time.perf_counter() - t0) * 1e3)
                    if i not in truths:
                        truths[i] = true_occupancy(bodies[i], r.grid.origin, vs, r.grid.dims, with_person=True)
                    truth_idx, who = truths[i]
                    scores.append(score_frame(i, idx, truth_idx, r.grid.dims, vs, truth_person=who))
                s = summarise_scores(scores)
                row = {"voxel_size": vs, "mask_scale": scale, "variant": name, "masks": source,
                       "carve_p50": float(np.percentile(ms, 50)) if ms else None,
                       "segmentation_p50": float(np.percentile(seg_ms[warmup:], 50)) if source == "mog2" else
                       float(np.percentile(fused_distances.last_ms[warmup:], 50)) if source == "yuv" else None,
                       "occluder_share": {k: round(v, 4) for k, v in r.occluder_share().items()}, **s}
                rows.append(row)
                if verbose:
                    print(format_hull_row(row), flush=True)
    return rows


HULL_HEADER = (f"{'voxel':>5} {'mask':>5} {'variant':<10} {'masks':<5} {'recall':>6} {'min':>6} {'volume':>7} "
               f"{'near':>6} {'share min':>9} {'in pieces':>9} {'carve ms':>8} {'seg ms':>6}  target")


def format_hull_row(r: dict) -> str:
    ok = (r["recall"] >= HULL_TARGET["recall"] and r["volume_ratio"] <= HULL_TARGET["volume_ratio"]
          and r["largest_share_min"] >= HULL_TARGET["largest_share"])
    return (f"{r['voxel_size'] * 100:4.0f}cm {'1/' + str(r['mask_scale']):>5} {r['variant']:<10} {r['masks']:<5} "
            f"{r['recall']:6.3f} {r['recall_min']:6.3f} {r['volume_ratio']:6.2f}x {r['volume_ratio_near']:5.2f}x "
            f"{r['largest_share_min']:9.3f} {100 * r['frames_in_pieces']:8.0f}% {r['carve_p50'] or 0:8.1f} "
            f"{r['segmentation_p50'] or 0:6.1f}  "
            f"{'met' if ok else 'not met'}")


def format_hull_table(rows: list[dict], recording, frames: int) -> str:
    lines = [f"hull of {recording}: {frames} frames scored; volume = occupied / true body voxels (near: within "
             f"10 cm of a body); share min = the least share of a person's nearby voxels in one component; "
             f"target: recall >= {HULL_TARGET['recall']} at volume <= {HULL_TARGET['volume_ratio']}x, "
             f"share >= {HULL_TARGET['largest_share']}", HULL_HEADER]
    lines += [format_hull_row(r) for r in rows]
    return "\n".join(lines)


#: issue 8's speed rows: (name, segmentation, Reconstructor options)
SPEED_VARIANTS = (
    ("mog2 k=1 (today)", "mog2", {"tolerance": 1}),
    ("mog2 occluders", "mog2", {"tolerance": 0, "occlusion": "learnt"}),
    ("mog2 occluders/8", "mog2", {"tolerance": 0, "occlusion": "learnt", "learn_every": 8}),
    ("fused", "yuv", {"tolerance": 0, "method": "fused"}),
    ("mog2 tight", "mog2", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0}),
    ("mog2 tight/8", "mog2", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0,
                              "learn_every": 8}),
    ("mog2 tight/4", "mog2", {"tolerance": 0, "footprint": 0.34, "occlusion": "learnt", "occlusion_top": 1.0,
                              "learn_every": 4, "occlusion_evidence": 1}),
    ("mog2 cells", "mog2", {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 1.0}),
    ("mog2 cells+g", "mog2", {"tolerance": 0, "footprint": 0.34, "occlusion": "cells", "occlusion_top": 1.0,
                              "ghost_share": 0.2}),
)
SPEED_BUDGET_MS = 30.0


def speed_table(recording, frames: int = 60, voxel_size: float = 0.02, warmup: int = 10, min_top: float = 0.25,
                variants=SPEED_VARIANTS, verbose: bool = True) -> list[dict]:
    """ms per frame on one core of segmentation (every camera, from the full-size
    frames: downscale + MOG2, or downscale + the fused method's distance maps) +
    reconstruction + visibility colouring + surface, for the variants, at one voxel
    size (issue 8: <= 30 ms at 2 cm with 5 cameras at 640x480). Frames are decoded
    before timing."""
    from app.recording import Recording
    from app.reconstruction import Reconstructor
    from app.segmentation import (SegmentationParams, YuvBackground, camera_segmenter, recording_background,
                                  matched_scale)

    rec = Recording(recording)
    calib = rec.calibration
    scale = matched_scale(calib, voxel_size)
    decoded = [images for _, images in rec.frames(stop=frames)]
    backgrounds = {cam: recording_background(rec, cam) for cam in rec.cameras}
    sizes = {c.name: (c.width // scale, c.height // scale) for c in calib.cameras}
    rows = []
    for name, seg_kind, options in variants:
        if seg_kind == "mog2":
            segs = {c: camera_segmenter(SegmentationParams(scale=scale), backgrounds[c], calib, c) for c in rec.cameras}
        else:
            segs = {c: YuvBackground(shrink(backgrounds[c], scale)) for c in rec.cameras}
            for c in rec.cameras:
                segs[c].fit_noise([shrink(f[c], scale) for f in decoded[:warmup]])
        r = Reconstructor(calib, voxel_size, mask_sizes=sizes, colour_sizes=sizes, colouring="visibility",
                          min_top=min_top, **options)
        seg_ms, rec_ms = [], []
        for n, images in enumerate(decoded):
            t0 = time.perf_counter()
            masks, small = {}, {}
            for cam, img in images.items():
                if seg_kind == "mog2":
                    masks[cam] = segs[cam].apply(img)
                    small[cam] = segs[cam].small
                else:
                    small[cam] = shrink(img, scale)
                    masks[cam] = segs[cam].distance(small[cam])
            t1 = time.perf_counter()
            r.reconstruct(masks, small)
            t2 = time.perf_counter()
            if n >= warmup:
                seg_ms.append((t1 - t0) * 1e3)
                rec_ms.append((t2 - t1) * 1e3)
        total = np.add(seg_ms, rec_ms)
        row = {"variant": name, "voxel_size": voxel_size, "mask_scale": scale, "cameras": len(rec.cameras),
               "frames": len(total), "segmentation_p50": float(np.median(seg_ms)),
               "reconstruction_p50": float(np.median(rec_ms)), "frame_p50": float(np.median(total)),
               "frame_p95": float(np.percentile(total, 95))}
        rows.append(row)
        if verbose:
            print(format_speed_row(row), flush=True)
    return rows


SPEED_HEADER = (f"{'variant':<20} {'voxel':>5} {'mask':>5} {'seg p50':>8} {'recon p50':>9} {'frame p50':>9} "
                f"{'p95':>6}  budget {SPEED_BUDGET_MS:.0f} ms")


def format_speed_row(r: dict) -> str:
    return (f"{r['variant']:<20} {r['voxel_size'] * 100:4.0f}cm {'1/' + str(r['mask_scale']):>5} "
            f"{r['segmentation_p50']:8.1f} {r['reconstruction_p50']:9.1f} {r['frame_p50']:9.1f} {r['frame_p95']:6.1f}  "
            f"{'ok' if r['frame_p50'] <= SPEED_BUDGET_MS else 'OVER'}")


# -- issue 8: what k = 0 loses, and why --------------------------------------------------

def _footprint_boxes(cam, centres: np.ndarray, size: float):
    """Pixel boxes ``u0 v0 u1 v1`` (clipped to the image) of the projections of the
    8 corners of voxel cubes of side ``size`` centred at ``centres`` (N, 3)."""
    corners = np.array([[dx, dy, dz] for dx in (-.5, .5) for dy in (-.5, .5) for dz in (-.5, .5)]) * size
    uv = cam.project((centres[:, None, :] + corners[None]).reshape(-1, 3)).reshape(len(centres), 8, 2)
    lo = np.floor(uv.min(axis=1) + 0.5).astype(np.int64)
    hi = np.floor(uv.max(axis=1) + 0.5).astype(np.int64)
    return (np.clip(lo[:, 0], 0, cam.width - 1), np.clip(lo[:, 1], 0, cam.height - 1),
            np.clip(hi[:, 0], 0, cam.width - 1), np.clip(hi[:, 1], 0, cam.height - 1))


def hull_losses(recording, frames: int = 70, voxel_sizes=(0.02, 0.04), warmup: int = 10,
                verbose: bool = True) -> list[dict]:
    """Where the body that ``k = 0`` loses goes (issue 8): for every true body voxel the
    carving (centre-pixel test, no floor filter) does not keep, the cameras that call
    it background, and for each such camera whether the voxel's footprint (the pixel
    box of its projected cube) holds foreground (an *edge* miss: the silhouette's
    outline cuts the voxel) or not (a *hidden* miss: furniture, or a hole in the
    mask). Per voxel size and mask source (MOG2 at the matched scale, the true
    silhouettes): the share of the body lost, and of the lost voxels the share with
    only edge misses, with one hidden camera and with two or more."""
    import cv2

    from app.reconstruction import Reconstructor
    from app.recording import Recording
    from app.simulation.occupancy import load_bodies, true_occupancy

    calib = Recording(recording).calibration
    bodies = {r["frame"]: r for r in load_bodies(recording)}
    rows = []
    for vs in voxel_sizes:
        scale, _, _, indices, sources, sizes = hull_input(recording, calib, frames, vs)
        for source, masks_list in sources:
            r = Reconstructor(calib, vs, mask_sizes=sizes, colouring="none", tolerance=0)
            body = lost = 0
            classes = np.zeros(3, dtype=np.int64)        # edge only, one hidden, 2+ hidden
            missing = np.zeros(4, dtype=np.int64)        # cameras missing a lost voxel: 1, 2, 3, 4+
            for n, (masks, i) in enumerate(zip(masks_list, indices)):
                idx = r.carve(masks)
                if n < warmup:
                    continue
                truth = true_occupancy(bodies[i], r.grid.origin, vs, r.grid.dims)
                dims = np.asarray(r.grid.dims, dtype=np.int64)
                flat = lambda a: (a[:, 0] * dims[1] + a[:, 1]) * dims[2] + a[:, 2]   # noqa: E731
                gone = truth[~np.isin(flat(truth), flat(idx.astype(np.int64)))]
                body += len(truth)
                lost += len(gone)
                if not len(gone):
                    continue
                pix = r.table.pixels(gone)
                centres = r.grid.centres(gone)
                hidden = np.zeros(len(gone), dtype=np.int64)
                misses = np.zeros(len(gone), dtype=np.int64)
                for c, name in enumerate(r.names):
                    m = masks[name]
                    seen = pix[:, c] >= 0
                    bg = seen & ~m.reshape(-1)[np.maximum(pix[:, c], 0)]
                    sel = np.flatnonzero(bg)
                    misses[sel] += 1
                    if not len(sel):
                        continue
                    u0, v0, u1, v1 = _footprint_boxes(r.mask_cameras[c], centres[sel], vs)
                    sat = cv2.integral(m.astype(np.uint8), sdepth=cv2.CV_32S)
                    count = sat[v1 + 1, u1 + 1] - sat[v0, u1 + 1] - sat[v1 + 1, u0] + sat[v0, u0]
                    hidden[sel[count == 0]] += 1
                classes += [(hidden == 0).sum(), (hidden == 1).sum(), (hidden >= 2).sum()]
                missing += np.bincount(np.clip(misses, 1, 4) - 1, minlength=4)
            row = {"voxel_size": vs, "mask_scale": scale, "masks": source, "lost": lost / max(body, 1),
                   "edge_only": classes[0] / max(lost, 1), "one_hidden": classes[1] / max(lost, 1),
                   "two_hidden": classes[2] / max(lost, 1),
                   "cameras_missing": {str(k + 1) + ("+" if k == 3 else ""): round(v / max(lost, 1), 3)
                                       for k, v in enumerate(missing)}}
            rows.append(row)
            if verbose:
                print(format_losses_row(row), flush=True)
    return rows


def one_miss_bound(r, carved: np.ndarray, truth: np.ndarray) -> dict:
    """What the best possible selection among the voxels one camera misses keeps of one
    frame (issue 8; evaluation only, it reads the truth). ``r`` a
    :class:`~app.reconstruction.Reconstructor` carved at ``tolerance = 1`` whose last
    carved frame gave ``carved``; ``truth`` the true body voxels (N, 3).

    The bound keeps every voxel no camera misses (``k = 0``), exactly the body among
    the voxels one camera misses (a per-frame oracle: no learnt occlusion, colour test or
    other rule that works on the one-miss voxels can keep more body with less), and then
    only the connected components that hold body (a perfect ghost filter). Its recall is
    the ``k = 1`` hull's; its volume is the least any such selection needs for it.
    Returns voxel counts: ``true``, ``k0`` / ``k0_body``, ``k1`` / ``k1_body``,
    ``bound`` / ``bound_body``."""
    from app.components import label_voxels

    dims = np.asarray(r.grid.dims, dtype=np.int64)

    def flat(a):
        a = np.asarray(a, dtype=np.int64).reshape(-1, 3)
        return (a[:, 0] * dims[1] + a[:, 1]) * dims[2] + a[:, 2]
    body = np.isin(flat(carved), flat(truth))
    misses = r.misses_of(carved)
    agreed = misses == 0
    keep = agreed | ((misses == 1) & body)
    kept = carved[keep]
    labels, count = label_voxels(kept, r.grid.dims)
    has_body = np.zeros(count, dtype=np.bool_)
    has_body[labels[body[keep]]] = True
    whole = has_body[labels]
    return {"true": len(truth), "k0": int(agreed.sum()), "k0_body": int((agreed & body).sum()),
            "k1": len(carved), "k1_body": int(body.sum()),
            "bound": int(whole.sum()), "bound_body": int(body[keep][whole].sum())}


def hull_bounds(recording, frames: int = 70, voxel_sizes=(0.02, 0.04), warmup: int = 10, min_top: float = 0.25,
                footprints=(0.0, 0.34), truth: bool = True, verbose: bool = True) -> list[dict]:
    """Issue 8's target against the best any selection of one-miss voxels can do
    (:func:`one_miss_bound`): per voxel size, mask source (MOG2 at the matched scale,
    the true silhouettes) and edge test (``footprint``), recall and volume of ``k = 0``,
    of ``k = 1`` and of the bound, summed over the frames after ``warmup``."""
    from app.reconstruction import Reconstructor
    from app.recording import Recording
    from app.simulation.occupancy import load_bodies, true_occupancy

    calib = Recording(recording).calibration
    bodies = {r["frame"]: r for r in load_bodies(recording)}
    rows = []
    for vs in voxel_sizes:
        scale, _, _, indices, sources, sizes = hull_input(recording, calib, frames, vs, truth)
        for source, masks_list in sources:
            for footprint in footprints:
                r = Reconstructor(calib, vs, mask_sizes=sizes, colouring="none", min_top=min_top, tolerance=1,
                                  footprint=footprint)
                total = {}
                for n, (masks, i) in enumerate(zip(masks_list, indices)):
                    carved = r.carve(masks)
                    if n < warmup:
                        continue
                    counts = one_miss_bound(r, carved, true_occupancy(bodies[i], r.grid.origin, vs, r.grid.dims))
                    total = {k: total.get(k, 0) + v for k, v in counts.items()}
                body = max(total.get("true", 0), 1)
                row = {"voxel_size": vs, "mask_scale": scale, "masks": source, "footprint": footprint}
                for name in ("k0", "k1", "bound"):
                    row[name] = {"recall": total.get(name + "_body", 0) / body, "volume_ratio": total.get(name, 0) / body}
                rows.append(row)
                if verbose:
                    print(format_bounds_row(row), flush=True)
    return rows


BOUNDS_HEADER = (f"{'voxel':>5} {'mask':>5} {'masks':<5} {'edge':>4}  {'k=0 recall / volume':>19}  "
                 f"{'k=1 recall / volume':>19}  {'bound recall / volume':>21}  target")


def format_bounds_row(r: dict) -> str:
    b = r["bound"]
    ok = b["recall"] >= HULL_TARGET["recall"] and b["volume_ratio"] <= HULL_TARGET["volume_ratio"]
    cells = "  ".join(f"{r[k]['recall']:>9.3f} / {r[k]['volume_ratio']:5.2f}x" for k in ("k0", "k1"))
    return (f"{r['voxel_size'] * 100:4.0f}cm {'1/' + str(r['mask_scale']):>5} {r['masks']:<5} {r['footprint']:4.2f}  "
            f"{cells}  {b['recall']:>11.3f} / {b['volume_ratio']:5.2f}x  {'within reach' if ok else 'out of reach'}")


LOSSES_HEADER = (f"{'voxel':>5} {'mask':>5} {'masks':<5} {'body lost':>9} {'edge only':>9} {'1 hidden':>8} "
                 f"{'2+ hidden':>9}  cameras missing a lost voxel (1/2/3/4+)")


def format_losses_row(r: dict) -> str:
    cm = r["cameras_missing"]
    return (f"{r['voxel_size'] * 100:4.0f}cm {'1/' + str(r['mask_scale']):>5} {r['masks']:<5} {r['lost']:9.3f} "
            f"{r['edge_only']:9.3f} {r['one_hidden']:8.3f} {r['two_hidden']:9.3f}  "
            f"{cm['1']:.2f}/{cm['2']:.2f}/{cm['3']:.2f}/{cm['4+']:.2f}")
