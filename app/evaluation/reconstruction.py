"""Reconstruction scores against the true body volume (simulated recordings).

For each frame: recall (true body voxels reconstructed), precision (reconstructed
voxels inside a body: the visual hull is larger than the body, so this is well under
1 by nature), spurious voxels farther than ``near`` from every body (shadows,
segmentation noise, the excess of the visual hull where few cameras see), the
largest flat blob on the floor that is not connected to any body (a shadow
reconstructed as matter, which a tracker could take for a person), and ghost voxels
(taller blobs with no body in them).

Issue 8's hull figures: ``volume_ratio``, the occupied volume over the true body
volume (the visual hull's excess, ghosts included: 1 is the body itself),
``volume_ratio_near`` the same for the voxels within ``near`` of a body, and, given
the person of each true voxel, the fragmentation (``largest_share``): for each
person, the share of the reconstructed voxels near that person (nearer to that body
than ``near``) held by the largest connected component among them; a person "in
pieces" scores under 0.9 (``largest_share`` is the frame's worst, lowest, share).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from app.components import component_sizes, label_voxels

__all__ = ["FrameScore", "score_frame", "summarise_scores", "SHADOW_BLOB_VOXELS", "PIECES_SHARE"]

SHADOW_BLOB_VOXELS = 20     # issue 4: no floor blob larger than this ...
SHADOW_FRAMES_MAX = 0.05    # ... in more than 5 % of frames
PIECES_SHARE = 0.9          # issue 8: a person whose largest nearby component holds less is in pieces


@dataclass
class FrameScore:
    frame: int
    true_voxels: int
    voxels: int
    recall: float
    precision: float
    spurious: int
    floor_blob: int
    ghost: int
    volume_ratio: float = 0.0     # occupied voxels / true body voxels
    volume_ratio_near: float = 0.0  # occupied voxels near the bodies / true body voxels
    largest_share: float = 1.0    # the lowest, over people, share of the largest component near them

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def _flat(idx: np.ndarray, dims) -> np.ndarray:
    idx = np.asarray(idx, dtype=np.int64).reshape(-1, 3)
    return (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]


@njit(cache=True, nogil=True)
def _dilate_ids(idx, ids, dims, r, grid):
    """Write person ``ids[n] + 1`` around each true voxel (Chebyshev radius ``r``) into
    ``grid`` where no person is written yet."""
    for n in range(idx.shape[0]):
        x, y, z = idx[n, 0], idx[n, 1], idx[n, 2]
        for i in range(max(0, x - r), min(dims[0], x + r + 1)):
            for j in range(max(0, y - r), min(dims[1], y + r + 1)):
                for k in range(max(0, z - r), min(dims[2], z + r + 1)):
                    if grid[i, j, k] == 0:
                        grid[i, j, k] = ids[n] + 1


@njit(cache=True, nogil=True)
def _dilate(idx, dims, r, grid):
    for n in range(idx.shape[0]):
        x, y, z = idx[n, 0], idx[n, 1], idx[n, 2]
        for i in range(max(0, x - r), min(dims[0], x + r + 1)):
            for j in range(max(0, y - r), min(dims[1], y + r + 1)):
                for k in range(max(0, z - r), min(dims[2], z + r + 1)):
                    grid[i, j, k] = 1


def score_frame(frame: int, indices: np.ndarray, truth: np.ndarray, dims, voxel_size: float,
                near: float = 0.10, floor: float = 0.10, shadow_height: float = 0.20,
                truth_person: np.ndarray | None = None) -> FrameScore:
    """Score one frame's reconstruction (N, 3) against the true body voxels (M, 3).

    ``near``: a reconstructed voxel within this distance (m, Chebyshev) of a body is
    not spurious. The frame's floor (shadow) blob is the largest connected component
    of the reconstruction that holds no body voxel, reaches below ``floor`` (m) and
    stays below ``shadow_height`` (m): a shadow reconstructed as matter, which
    connected components would present to the tracker as an object on the floor.
    Taller components without a body are ghosts (``ghost`` voxels): silhouettes of
    different people meeting where few cameras see. ``truth_person`` (M,), the person
    of each true voxel, enables the per-person fragmentation (``largest_share``).
    """
    dims = np.asarray(dims, dtype=np.int64)
    rec = np.unique(_flat(indices, dims))
    tru = np.unique(_flat(truth, dims))
    hit = np.intersect1d(rec, tru, assume_unique=True).size
    recall = hit / tru.size if tru.size else 1.0
    precision = hit / rec.size if rec.size else 1.0
    near_grid = np.zeros(tuple(dims), dtype=np.uint8)
    r = max(0, int(round(near / voxel_size)))
    if truth.size:
        _dilate(np.asarray(truth, dtype=np.int64).reshape(-1, 3), dims, r, near_grid)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    far = idx[near_grid[idx[:, 0], idx[:, 1], idx[:, 2]] == 0] if idx.size else idx
    floor_blob = ghost = 0
    if len(idx):  # components of the reconstruction with no body voxel in them
        labels, n = label_voxels(idx, dims)
        sizes = component_sizes(labels, n)
        in_body = np.zeros(n, dtype=bool)
        body = np.zeros(tuple(dims), dtype=np.uint8)
        if truth.size:
            body[tuple(np.asarray(truth, dtype=np.int64).reshape(-1, 3).T)] = 1
        in_body[labels[body[idx[:, 0], idx[:, 1], idx[:, 2]] == 1]] = True
        lowest = np.full(n, np.iinfo(np.int64).max)
        highest = np.full(n, -1)
        np.minimum.at(lowest, labels, idx[:, 2])
        np.maximum.at(highest, labels, idx[:, 2])
        flat = ~in_body & ((lowest + 0.5) * voxel_size < floor) & ((highest + 0.5) * voxel_size < shadow_height)
        floor_blob = int(sizes[flat].max()) if flat.any() else 0
        ghost = int(sizes[~in_body & ~flat].sum())
    volume_ratio = rec.size / tru.size if tru.size else 0.0
    volume_ratio_near = (len(idx) - len(far)) / tru.size if tru.size else 0.0
    largest_share = 1.0
    if truth_person is not None and truth.size and len(idx):
        largest_share = _largest_share(idx, labels, np.asarray(truth, dtype=np.int64).reshape(-1, 3),
                                       np.asarray(truth_person, dtype=np.int64), dims, r)
    return FrameScore(frame=int(frame), true_voxels=int(tru.size), voxels=int(rec.size), recall=float(recall),
                      precision=float(precision), spurious=int(len(far)), floor_blob=floor_blob, ghost=ghost,
                      volume_ratio=float(volume_ratio), volume_ratio_near=float(volume_ratio_near),
                      largest_share=float(largest_share))


def _largest_share(idx, labels, truth, person, dims, r) -> float:
    """The lowest, over the people, share of a person's nearby reconstructed voxels
    (those within ``r`` voxels of that body, the nearest body first written wins where
    two people's neighbourhoods overlap) held by one connected component."""
    near = np.zeros(tuple(dims), dtype=np.int32)
    # each person's own voxels first, so a voxel inside one body never goes to another
    _dilate_ids(truth, person, dims, 0, near)
    _dilate_ids(truth, person, dims, r, near)
    who = near[idx[:, 0], idx[:, 1], idx[:, 2]] - 1
    worst = 1.0
    for pid in np.unique(person):
        mine = labels[who == pid]
        if len(mine) == 0:
            worst = 0.0
            continue
        worst = min(worst, float(np.bincount(mine).max()) / len(mine))
    return worst


def summarise_scores(scores: list[FrameScore]) -> dict:
    """Means over frames with people, and the shadow criterion of issue 4."""
    with_people = [s for s in scores if s.true_voxels]
    if not scores:
        return {"frames": 0}
    blobs = np.array([s.floor_blob for s in scores])
    frac = float(np.mean(blobs > SHADOW_BLOB_VOXELS))
    return {
        "frames": len(scores),
        "recall": round(float(np.mean([s.recall for s in with_people])), 4) if with_people else None,
        "recall_min": round(float(np.min([s.recall for s in with_people])), 4) if with_people else None,
        "precision": round(float(np.mean([s.precision for s in with_people])), 4) if with_people else None,
        "spurious_mean": round(float(np.mean([s.spurious for s in scores])), 1),
        "volume_ratio": round(float(np.mean([s.volume_ratio for s in with_people])), 3) if with_people else None,
        "volume_ratio_max": round(float(np.max([s.volume_ratio for s in with_people])), 3) if with_people else None,
        "volume_ratio_near": round(float(np.mean([s.volume_ratio_near for s in with_people])), 3)
        if with_people else None,
        "largest_share_min": round(float(np.min([s.largest_share for s in with_people])), 4) if with_people else None,
        "frames_in_pieces": round(float(np.mean([s.largest_share < PIECES_SHARE for s in with_people])), 4)
        if with_people else None,
        "ghost_mean": round(float(np.mean([s.ghost for s in scores])), 1),
        "floor_blob_max": int(blobs.max()),
        "frames_with_floor_blob_over_20": round(frac, 4),
        "shadow_target_met": frac <= SHADOW_FRAMES_MAX,
    }
