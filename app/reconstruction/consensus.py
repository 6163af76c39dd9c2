"""Per-voxel camera misses of a reconstructed hull: how many of the frame's cameras call
each occupied voxel background (thesis §2.2.4, the ``N_visible - N_fg`` of the
occupancy test).

The pipeline carves with tolerance ``k = 1`` (one camera may miss a voxel, if at least
``miss_support`` others see it: :data:`.reconstructor.PIPELINE_CARVING`): tracking
and its person classifier need the complete hull, furniture hides limbs from one
camera. That hull is 5-7x the body; the voxels no camera misses, the ``k = 0`` hull
(every camera agrees), are 1.4-2x, which is what the pose likelihood (Ch. 6) can fit.
:func:`count_misses` gives every published voxel its miss count, so one carving
serves both: ``misses == 0`` is the ``k = 0`` subset of the ``k = 1`` hull
(:class:`app.messages.Voxels` ``misses``).

The count reads exactly what the carving's final, per-voxel level reads
(:func:`.carving.carve_cells` / :func:`.carving.carve_cells_occluded`): the votes of the
concatenated masks (after the silhouette-edge footprint test, if any) through the
projection table ``lut``; a camera without a mask this frame, or that does not see the
voxel, votes 0 and is no miss; with learnt occluders a camera that abstains behind an
occluder is no miss, and one whose occluder is nearer than the voxel (or above
``k_top``) votes background, a miss. Only the output voxels are visited (a few
thousand to a few tens of thousands): each needs its brick-layout position (bit
interleaving) and one table gather per camera.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .carving import BG_VOTE, OCC_VOTE
from .grid import brick_position

__all__ = ["count_misses", "select_misses"]


@njit(cache=True, nogil=True)
def _misses(indices, levels, brick_dims, lut, votes, occluded, depth_coef, occ_depth, k_top, out):
    n_cams = lut.shape[1]
    nby = np.int64(brick_dims[1])
    nbz = np.int64(brick_dims[2])
    for n in range(indices.shape[0]):
        i = np.int64(indices[n, 0])
        j = np.int64(indices[n, 1])
        k = np.int64(indices[n, 2])
        p = brick_position(i, j, k, levels, nby, nbz)
        m = 0
        for c in range(n_cams):
            q = lut[p, c]
            v = votes[q]
            if v == BG_VOTE:
                m += 1
            elif occluded and v == OCC_VOTE:
                if k >= k_top:
                    m += 1
                else:
                    z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
                    if z < occ_depth[q]:
                        m += 1
        out[n] = m


def count_misses(indices: np.ndarray, layout, lut: np.ndarray, votes: np.ndarray, depth_coef=None, occ_depth=None,
                 k_top: int = 1 << 30) -> np.ndarray:
    """Misses (N,) uint8 of the voxels ``indices`` (N, 3): the cameras whose vote in
    ``votes`` (the carving's buffer, :data:`.carving.BG_VOTE` = background) at the
    voxel's entry of ``lut`` is background. ``layout`` is the
    :class:`~.grid.BrickLayout` of the table. With learnt occluders pass their
    ``depth_coef`` / ``occ_depth`` (and ``k_top``): votes :data:`.carving.OCC_VOTE`
    count as a miss only where the carving reads them as background."""
    idx = np.ascontiguousarray(np.asarray(indices).reshape(-1, 3))
    out = np.empty(len(idx), dtype=np.uint8)
    occluded = depth_coef is not None
    if not occluded:
        depth_coef = np.zeros((lut.shape[1], 4), dtype=np.float64)
        occ_depth = np.zeros(1, dtype=np.float32)
    _misses(idx, np.int64(layout.levels), layout.brick_dims_arr, lut, votes, occluded, depth_coef, occ_depth,
            np.int64(k_top), out)
    return out


def select_misses(carved: np.ndarray, kept: np.ndarray, misses: np.ndarray, dims) -> np.ndarray:
    """The misses of ``kept``, a subset of ``carved`` (both (N, 3), sorted by flat id, as
    the floor and ghost filters leave them), from the misses of ``carved``."""
    if len(kept) == len(carved):
        return misses
    _, ny, nz = (int(d) for d in dims)

    def flat(a):
        a = a.astype(np.int64)
        return (a[:, 0] * ny + a[:, 1]) * nz + a[:, 2]
    return misses[np.searchsorted(flat(carved), flat(kept))]
