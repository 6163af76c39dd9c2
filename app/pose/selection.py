"""Which of a frame's voxels the pose stage poses on.

The pipeline's reconstruction carves with tolerance ``k = 1`` (§2.2.4: a voxel one
camera misses stays), so that the tracker keeps a person a camera loses; that hull is
5-7x the body and holds no limb shape (docs/history/pose-likelihood.md, "Pose on the consensus of
the k = 1 hull"). The pose stage therefore poses on the *consensus* subset, the voxels no camera
misses (``Voxels.misses == 0``, the ``k = 0`` hull). That subset loses thin, fast
limbs where one camera's mask is thin or broken there: walk1's shins (158 of 572 true
shin voxels kept at frame 30), a foot a camera sees behind furniture.

``tolerant`` keeps, besides the consensus, the one-miss voxels (``misses == 1``) that
are likely a limb and not the phantom of the ``k = 1`` hull: below ``low`` (m: shins and
feet), within ``near`` (m, horizontally) of a track, and only where at least ``views``
cameras still call them foreground (frames of ``views + 1`` cameras or more). Measured
through the pipeline (docs/history/pose-likelihood.md, "Round 2"): 0.2 m gained on
gesture1, walk1 and meeting3 with pose seeds 0-2 and lost on all three with seeds 3-5, so
the pose worker keeps ``consensus``; 0.3 m and higher add more phantom than limb
(meeting3's 4 cm hull of 4 cameras loses 0.03-0.07). The phantom cones of ``k = 1`` open upwards and
outwards from the body's silhouette, so near the floor and next to the body they are
narrowest. (Also measured and not kept: an attachment test, one-miss voxels reached from
the consensus subset through 26-neighbours.) The thesis (§2.2.4) poses on one hull;
this subset is ours.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from app.pose.model import posed_tracks

__all__ = ["SUBSETS", "pose_subset", "within_reach", "pose_frame", "silhouette_view", "PosedFrame"]

SUBSETS = ("consensus", "tolerant", "all")


def pose_subset(misses: np.ndarray | None, centres: np.ndarray, positions: np.ndarray,
                mode: str = "consensus", cameras: int = 5, low: float = 0.3, near: float = 0.6,
                views: int = 3) -> np.ndarray | None:
    """Boolean mask of the voxels to pose on, or None for all of them (``mode`` ``all``, or
    voxels without ``misses``). ``misses`` (N,) cameras that miss each voxel, ``centres``
    (N, 3) m (only ``tolerant`` looks at them: None will do otherwise), ``positions`` (T, 3)
    the tracks, ``cameras`` the frame's camera count."""
    if mode == "tolerant" and centres is None:
        raise ValueError("the tolerant subset needs the voxels' centres")
    if (mode == "all" or misses is None or not len(misses)
            or (centres is not None and len(misses) != len(centres))):
        return None
    keep = misses == 0
    if mode == "consensus":
        return keep
    if mode != "tolerant":
        raise ValueError(f"voxel subset {mode!r} is not one of {', '.join(SUBSETS)}")
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if cameras - 1 < views or len(positions) == 0:
        return keep
    cand = (misses == 1) & (centres[:, 2] < low)
    if not cand.any():
        return keep
    where = np.flatnonzero(cand)
    d = np.min(np.hypot(centres[where, 0, None] - positions[None, :, 0],
                        centres[where, 1, None] - positions[None, :, 1]), axis=1)
    where = where[d < near]
    keep = keep.copy()
    keep[where] = True
    return keep


def within_reach(vox, positions: np.ndarray, reach: float, wanted=None) -> np.ndarray:
    """Boolean mask of the voxels of ``vox`` (a :class:`~app.messages.Voxels`) within
    ``reach`` (m, in the floor plane) of a track of ``positions (T, 3)``: of those in
    ``wanted`` (indices; None: every track). Only these can be a posed person's
    (:func:`app.pose.estimator.assign_voxels` gives a voxel farther than ``reach`` from
    every track to nobody), so the centres of the others are never made: a pose shard of
    one person in six skips five sixths of the frame's voxels (issue 26). Read from the
    grid indices in one pass; a hair wider than ``reach`` (1 um), so that rounding never
    leaves out a voxel the ownership would give."""
    idx = np.ascontiguousarray(vox.indices).reshape(-1, 3)
    positions = np.ascontiguousarray(positions, np.float64).reshape(-1, 3)
    pick = posed_tracks(len(positions), wanted)
    out = np.zeros(len(idx), np.bool_)
    if pick.any() and len(idx):
        _within_reach(idx, np.asarray(vox.origin, np.float64), float(vox.voxel_size), positions[pick],
                      float(reach) + 1e-6, out)
    return out


@njit(cache=True, nogil=True)
def _within_reach(idx, origin, size, points, reach, out):
    for i in range(idx.shape[0]):
        x = origin[0] + (idx[i, 0] + 0.5) * size
        y = origin[1] + (idx[i, 1] + 0.5) * size
        for k in range(points.shape[0]):
            dx, dy = x - points[k, 0], y - points[k, 1]
            if dx * dx + dy * dy <= reach * reach:
                out[i] = True
                break


class PosedFrame(NamedTuple):
    result: dict                # {track: (joints (15, 3), active (15,))}
    kept: float | None          # share of the frame's voxels posed on (a subset), or None
    no_silhouettes: str | None  # why the silhouette term was off although asked for, or None


def silhouette_view(masks: list, names: list, calibration, settings):
    """``(view, why not)``: the frame's :class:`~app.pose.silhouette.SilhouetteView` of the
    silhouettes ``masks`` of cameras ``names`` (the run's
    :class:`~calibration.Calibration`), or None and why (None when the term is off)."""
    if settings.silhouette <= 0:
        return None, None
    if calibration is None:
        return None, "no calibration (the recording's, or --calibration)"
    if not masks:
        return None, "the voxels carry no silhouettes (reconstruction.silhouettes = 0, or an older reconstruction)"
    unknown = [n for n in names if n not in calibration.names]
    if unknown:
        return None, f"camera {unknown[0]} is not in the calibration"
    from app.pose.silhouette import SilhouetteView
    return SilhouetteView(masks, [calibration.camera(n) for n in names], reach=settings.silhouette_reach), None


def pose_frame(estimator, vox, ids: np.ndarray, positions: np.ndarray, params: dict, only=None,
               calibration=None, keypoints=None) -> PosedFrame:
    """One frame through a :class:`~app.pose.estimator.PoseEstimator` as the pose worker
    poses it: the voxel subset of ``params`` (the worker's ``voxels``, ``tolerant_*``), its
    surface recomputed where a subset is taken, the silhouettes the voxels carry
    (with the run's ``calibration``; :func:`silhouette_view`). ``vox``: a
    :class:`~app.messages.Voxels`; ``keypoints``: ``{track: PersonKeypoints}`` or None."""
    n = len(vox.indices)
    # every voxel's centre only where the subset looks at them (tolerant); else those posed on
    full = vox.centres() if params["voxels"] == "tolerant" else None
    surface = vox.surface if vox.surface is not None and len(vox.surface) == n else None
    misses = vox.misses if vox.misses is not None and len(vox.misses) == n else None
    keep = pose_subset(misses, full, positions, mode=params["voxels"], cameras=len(vox.cameras),
                       low=float(params["tolerant_low"]), near=float(params["tolerant_near"]),
                       views=int(params["tolerant_views"]))
    kept = None if keep is None else float(keep.mean())
    # of those, the voxels a posed person may own: the others are nobody's to pose
    wanted = None if only is None else [k for k, t in enumerate(ids) if only(int(t))]
    take = within_reach(vox, positions, estimator.settings.reach, wanted)
    if keep is not None:
        take &= keep
        surface = None   # the subset's own boundary (app.pose.observation)
    centres = vox.centres(take) if full is None else full[take]
    surface = None if surface is None else surface[take]
    colours = vox.colours[take] if (estimator.settings.method == "behaviour" and vox.colours is not None
                                    and len(vox.colours) == n) else None   # only the blobs look at them
    masks = vox.silhouette_masks() if estimator.settings.silhouette > 0 else []
    view, why = silhouette_view(masks, vox.cameras, calibration, estimator.settings)
    return PosedFrame(estimator.update(centres, surface, ids, positions, only=only, view=view, keypoints=keypoints,
                                       colours=colours), kept, why)
