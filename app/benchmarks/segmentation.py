"""``smartroom bench segmentation``: the segmentation's masks against the simulator's
true silhouettes (issue 8: per-camera misses compound in the hull at k = 0, false
foreground fattens it at k = 1).

For every camera and frame of a simulated recording the mask of
:class:`app.segmentation.CameraSegmenter` (at the scale matched to a voxel size, as the
pipeline runs it) is compared with the true silhouette at the same size (a pixel is a
person when half of it is, as in :func:`app.benchmarks.reconstruction.true_silhouettes`):

- **recall** = true person pixels in the mask, **precision** = mask pixels that are
  person; **cam min** = the worst camera's recall over the run;
- where the **misses** are, in % of the true person pixels: ``edge`` (a pixel of the
  silhouette's outline), ``thin`` (inside a part narrower than 5 pixels: arms, legs at
  reduced size), ``inner`` (holes inside the body; ``camo``: the share of them where the
  frame differs from the empty room by less than 15 grey levels in every channel, i.e.
  clothing close to the background's colour);
- where the **false foreground** is, in % of the true person pixels: ``edge`` (next to
  the silhouette), ``shadow`` (the people's floor and contact shadows: pixels the
  noise-free render shows darker than the empty room by more than 3 %), ``other``.

The truth is rendered once per frame (noise-free) from ``simulation.json``; the masks
come from the recording's videos (compression and sensor noise included).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

__all__ = ["truth_frames", "score_masks", "mask_table", "format_mask_table", "hull_rows", "format_hull_rows",
           "MASK_VARIANTS"]

#: named parameter sets compared by the bench: ``(name, SegmentationParams overrides)``
MASK_VARIANTS = (
    ("before", {"shadow_floor": 0.0, "fill_holes": 0, "second_chance": 0.0}),   # MOG2 + closing alone
    ("default", {}),
)

_EDGE = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))
_THIN = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))


def _simulator(recording):
    from app.errors import InputError
    from app.recording import Recording
    from app.simulation.simulator import Simulator

    path = Path(recording) / "simulation.json"
    if not path.is_file():
        raise InputError(f"{recording}: no simulation.json, so no true silhouettes (a simulated recording is needed)")
    meta = json.loads(path.read_text())
    calib = Recording(recording).calibration
    cam0 = calib.cameras[0]
    return Simulator(meta["scene"], seed=meta["seed"], fps=meta["fps"], seconds=meta["seconds"],
                     width=cam0.width, height=cam0.height, zenithal=meta.get("zenithal", False),
                     cameras=list(calib.names)), calib


def truth_frames(recording, frames: int, scales=(2, 4)) -> dict:
    """``{scale: [{cam: (person, shadow)}]}`` for the first ``frames`` frames: the true
    silhouette (a pixel is person when half of it is) and the people's shadows on the
    room (noise-free render darker than the empty room by more than 3 %, away from the
    person) at ``1/scale`` of the image size, bool arrays."""
    sim, calib = _simulator(recording)
    empty = {c: sim.background(c, noise=False).astype(np.float32).sum(axis=2) for c in calib.names}
    out = {s: [] for s in scales}
    for i in range(frames):
        images, labels, _ = sim.render(i, noise=False)
        per = {s: {} for s in scales}
        for c, cam in enumerate(calib.cameras):
            person = (labels[cam.name] >= 0).astype(np.uint8)
            near = cv2.dilate(person, cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5)))
            lum = images[cam.name].astype(np.float32).sum(axis=2)
            shadow = ((lum < 0.97 * sim.gain(i, c) * empty[cam.name] - 3) & (near == 0)).astype(np.float32)
            for s in scales:
                w, h = cam.width // s, cam.height // s
                per[s][cam.name] = (cv2.resize(person.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5,
                                    cv2.resize(shadow, (w, h), interpolation=cv2.INTER_AREA) >= 0.5)
        for s in scales:
            out[s].append(per[s])
    return out


def _add(acc: dict, key: str, value) -> None:
    acc[key] = acc.get(key, 0) + int(value)


def score_masks(recording, truth: list[dict], scale: int, params: dict | None = None, warmup: int = 10) -> dict:
    """The segmentation (``SegmentationParams`` with ``params`` over the defaults) of the
    recording's first ``len(truth)`` frames at ``1/scale`` against the true silhouettes:
    recall, precision, worst camera's recall, misses and false foreground by place (in
    % of true person pixels), and the ms of segmentation per frame (all cameras, p50)."""
    from app.recording import Recording
    from app.segmentation import SegmentationParams, camera_segmenter, recording_background, shrink

    rec = Recording(recording)
    sp = SegmentationParams.from_params({**(params or {}), "scale": scale})
    segs, backs = {}, {}
    for cam in rec.cameras:
        bg = recording_background(rec, cam)
        segs[cam] = camera_segmenter(sp, bg, rec.calibration, cam)
        backs[cam] = shrink(bg, scale).astype(np.int16)
    acc: dict = {}
    per_cam: dict = {}
    ms = []
    for i, images in rec.frames(stop=len(truth)):
        t0 = time.perf_counter()
        masks = {cam: segs[cam].apply(img) for cam, img in images.items()}
        if i < warmup:
            continue
        ms.append((time.perf_counter() - t0) * 1e3)
        for cam, mask in masks.items():
            person, shadow = truth[i][cam]
            p8 = person.view(np.uint8)
            edge_in = person & ~cv2.erode(p8, _EDGE, borderType=cv2.BORDER_REPLICATE).view(bool)
            thin = person & ~edge_in & ~cv2.morphologyEx(p8, cv2.MORPH_OPEN, _THIN).view(bool)
            near = cv2.dilate(p8, _EDGE).view(bool) & ~person
            miss = person & ~mask
            false = mask & ~person
            inner = miss & ~edge_in & ~thin
            camo = (np.abs(segs[cam].small.astype(np.int16) - backs[cam]).max(axis=2) < 15) & inner
            hit = int((person & mask).sum())
            _add(acc, "person", person.sum())
            _add(acc, "hit", hit)
            _add(acc, "mask", mask.sum())
            _add(acc, "miss_edge", (miss & edge_in).sum())
            _add(acc, "miss_thin", (miss & thin).sum())
            _add(acc, "miss_inner", inner.sum())
            _add(acc, "miss_camo", camo.sum())
            _add(acc, "false_edge", (false & near).sum())
            _add(acc, "false_shadow", (false & ~near & shadow).sum())
            _add(acc, "false_other", (false & ~near & ~shadow).sum())
            c = per_cam.setdefault(cam, [0, 0])
            c[0] += hit
            c[1] += int(person.sum())
    n = max(1, acc.get("person", 0))
    pct = {k: 100.0 * v / n for k, v in acc.items() if k.startswith(("miss_", "false_"))}
    pct["miss_camo"] = 100.0 * acc.get("miss_camo", 0) / max(1, acc.get("miss_inner", 0))   # share of inner
    return {"scale": scale, "params": params or {}, "frames": len(ms), "recall": acc.get("hit", 0) / n,
            "precision": acc.get("hit", 0) / max(1, acc.get("mask", 0)),
            "camera_recall_min": min(h / max(1, t) for h, t in per_cam.values()) if per_cam else 0.0,
            "segmentation_p50": float(np.median(ms)) if ms else 0.0, **pct}


def mask_table(recording, frames: int = 70, scales=(2, 4), variants=MASK_VARIANTS, warmup: int = 10,
               verbose: bool = True) -> list[dict]:
    """:func:`score_masks` for every mask scale x variant (the truth rendered once)."""
    truth = truth_frames(recording, frames, scales)
    rows = []
    for scale in scales:
        for name, params in variants:
            row = {"variant": name, **score_masks(recording, truth[scale], scale, params, warmup)}
            rows.append(row)
            if verbose:
                print(format_mask_row(row), flush=True)
    return rows


MASK_HEADER = (f"{'mask':>4} {'variant':<14} {'recall':>6} {'prec':>6} {'cam min':>7} | misses % of person: "
               f"{'edge':>5} {'thin':>5} {'inner':>5} {'camo':>5} | false fg %: {'edge':>5} {'shadow':>6} "
               f"{'other':>5} | {'seg ms':>6}")


def format_mask_row(r: dict) -> str:
    return (f"{'1/' + str(r['scale']):>4} {r['variant']:<14} {r['recall']:6.3f} {r['precision']:6.3f} "
            f"{r['camera_recall_min']:7.3f} | {'':19}{r['miss_edge']:5.1f} {r['miss_thin']:5.1f} "
            f"{r['miss_inner']:5.1f} {r['miss_camo']:4.0f}% | {'':11}{r['false_edge']:5.1f} {r['false_shadow']:6.1f} "
            f"{r['false_other']:5.1f} | {r['segmentation_p50']:6.1f}")


def format_mask_table(rows: list[dict], recording, frames: int) -> str:
    lines = [f"masks of {recording} against the true silhouettes: {frames} frames scored, every camera; camo = share "
             f"of the inner misses within 15 grey levels of the empty room; seg ms = p50 of all cameras per frame",
             MASK_HEADER]
    lines += [format_mask_row(r) for r in rows]
    return "\n".join(lines)


# -- the masks' effect on the hull (issue 8's scorer, k = 0 and k = 1) -----------------

def hull_rows(recording, frames: int = 70, voxel_sizes=(0.02, 0.04), variants=MASK_VARIANTS,
              tolerances=(0, 1), warmup: int = 10, min_top: float = 0.25, truth: bool = True,
              verbose: bool = True) -> list[dict]:
    """The hull scored as ``smartroom bench reconstruction --hull`` does (same scorer,
    same carving), for masks of each segmentation variant (and the true silhouettes,
    ``masks = true``) at the matched scale, with tolerance k in ``tolerances``."""
    from app.benchmarks.reconstruction import true_silhouettes
    from app.evaluation.reconstruction import score_frame, summarise_scores
    from app.recording import Recording
    from app.reconstruction import Reconstructor
    from app.segmentation import SegmentationParams, camera_segmenter, recording_background, matched_scale
    from app.simulation.occupancy import load_bodies, true_occupancy

    rec = Recording(recording)
    calib = rec.calibration
    bodies = {r["frame"]: r for r in load_bodies(recording)}
    backgrounds = {c: recording_background(rec, c) for c in rec.cameras}
    rows = []
    for vs in voxel_sizes:
        scale = matched_scale(calib, vs)
        sources = []
        for name, params in variants:
            sp = SegmentationParams.from_params({**params, "scale": scale})
            segs = {c: camera_segmenter(sp, backgrounds[c], calib, c) for c in rec.cameras}
            sources.append((name, [{c: segs[c].apply(im) for c, im in images.items()}
                                   for _, images in rec.frames(stop=frames)]))
        if truth:
            sources.append(("true", true_silhouettes(recording, frames, scale)))
        sizes = {c: m.shape[::-1] for c, m in sources[0][1][0].items()}
        truths = {}
        for k in tolerances:
            for source, masks_list in sources:
                r = Reconstructor(calib, vs, mask_sizes=sizes, colouring="none", min_top=min_top, tolerance=k)
                scores = []
                for i, masks in enumerate(masks_list):
                    idx = r.carve(masks)
                    if i < warmup:
                        continue
                    if i not in truths:
                        truths[i] = true_occupancy(bodies[i], r.grid.origin, vs, r.grid.dims, with_person=True)
                    truth_idx, who = truths[i]
                    scores.append(score_frame(i, idx, truth_idx, r.grid.dims, vs, truth_person=who))
                row = {"voxel_size": vs, "mask_scale": scale, "tolerance": k, "masks": source,
                       **summarise_scores(scores)}
                rows.append(row)
                if verbose:
                    print(format_hull_row(row), flush=True)
    return rows


HULL_HEADER = (f"{'voxel':>5} {'mask':>5} {'k':>2} {'masks':<14} {'recall':>6} {'min':>6} {'volume':>7} {'near':>6} "
               f"{'share min':>9} {'in pieces':>9}")


def format_hull_row(r: dict) -> str:
    return (f"{r['voxel_size'] * 100:4.0f}cm {'1/' + str(r['mask_scale']):>5} {r['tolerance']:>2} {r['masks']:<14} "
            f"{r['recall']:6.3f} {r['recall_min']:6.3f} {r['volume_ratio']:6.2f}x {r['volume_ratio_near']:5.2f}x "
            f"{r['largest_share_min']:9.3f} {100 * r['frames_in_pieces']:8.0f}%")


def format_hull_rows(rows: list[dict], recording, frames: int) -> str:
    lines = [f"hull of {recording} with each variant's masks ({frames} frames scored; as `smartroom bench "
             f"reconstruction --hull`)", HULL_HEADER]
    lines += [format_hull_row(r) for r in rows]
    return "\n".join(lines)
