"""Shape from silhouette with tolerance (thesis §2.2.4), flat and coarse-to-fine.

Occupancy test of one voxel ``V`` (thesis §2.2.4): project its centre into every camera
that has a mask this frame and whose image contains the projection (``N_visible`` such
cameras) and count the foreground answers ``N_fg``. ``V`` is occupied when

    N_fg >= N_visible - tolerance      and      N_fg >= min_views,

i.e. at most ``tolerance`` cameras that see it call it background ("some tolerance is
permitted to cope with faulty segmentations"), and it is never occupied on the word of
fewer than ``min_views`` cameras. A camera without a mask this frame lowers
``N_visible``. With ``miss_support`` > 0 (not in the thesis) a voxel that any camera
calls background also needs ``N_fg >= miss_support``: the tolerance serves a body seen
by many cameras, not a place only two or three cones reach (see :func:`carve_cells`).

Two ways to evaluate it, with the same occupied set:

* ``flat``: :func:`carve_cells` over every voxel of the grid, one table gather per voxel
  and camera until the answer is known.
* ``hierarchical`` (coarse-to-fine, Caillette et al. §6.1): the grid is cut into coarse
  cells (bricks of 8^3 voxels, then their octants, ...) and :func:`classify_cells` sorts
  each cell into background, foreground or "edge" (Caillette's three classes) from the
  silhouettes alone: with each camera's summed-area table it counts the foreground
  pixels in the bounding box of the pixels of the cell's voxel centres (precomputed,
  lens distortion included, :class:`~.projection.ProjectionTable`).

  - a camera with no foreground in the box calls every voxel of the cell it sees
    background; if it sees them all, it *surely* calls them background;
  - a camera with foreground in the box *may* call some voxel foreground; with only
    foreground in the box it *surely* calls every voxel it sees foreground.

  A cell is background (dropped) when fewer than ``min_views`` cameras may say
  foreground or more than ``tolerance`` surely say background: then no voxel of it can
  pass the test above. It is foreground (all its voxels occupied, no voxel tested) when
  at least ``min_views`` cameras that see all of it surely say foreground and at most
  ``tolerance`` cameras may say background. Otherwise its children are tested, down to
  the voxels, where the exact centre test decides. Both shortcuts agree with the
  per-voxel test by construction, so ``hierarchical`` and ``flat`` give the same set,
  and empty space costs one box test per coarse cell.

Occupied voxels are written as sort keys ``(i << si) | (j << sj) | k``
(:class:`~.grid.BrickLayout`), whose order is the flat-id order.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["classify_cells", "carve_cells", "fill_cells", "mask_votes", "occluded_votes", "dissent_cells",
           "carve_cells_occluded", "OCC_VOTE",
           "MAX_CAMERAS"]


@njit(cache=True, nogil=True)
def classify_cells(cells, boxes, cams, sat, sat_offset, sat_stride, tolerance, min_views, expand, out_edge, out_full,
                   sat_fg=None, full_views=0, miss_support=0):
    """Classify ``cells`` (ids at one box level) from the summed-area tables ``sat`` of
    the cameras ``cams`` (those with a mask this frame).

    ``boxes`` (n_cells, C, 5) int16: u0 v0 u1 v1 status per cell and camera. Edge cells
    (or, with ``expand``, their 8 children) go to ``out_edge``, foreground cells to
    ``out_full``; background cells are dropped. Returns ``(n_edge, n_full)``.

    With occluder masks (:mod:`.occlusion`) ``sat`` counts the pixels that *may* vote
    foreground (foreground, or background behind a learnt occluder, which abstains) and
    ``sat_fg`` the foreground pixels alone: a camera surely says foreground only when
    its whole box is foreground in ``sat_fg``. A cell is foreground only with at least
    ``max(min_views, full_views)`` cameras surely saying so.

    ``miss_support`` (see :func:`carve_cells`): a cell some camera surely calls
    background is dropped when fewer than ``miss_support`` cameras may say foreground,
    and a cell is foreground only if no camera may say background or at least
    ``miss_support`` surely say foreground.
    """
    fill_views = max(min_views, full_views)
    n_edge = 0
    n_full = 0
    n_cams = cams.shape[0]
    for ci in range(cells.shape[0]):
        cell = cells[ci]
        may_fg = 0       # cameras with foreground in the box
        sure_bg = 0      # cameras that see the whole cell, no foreground in the box
        sure_fg = 0      # cameras that see the whole cell, only foreground in the box
        may_bg = 0       # cameras that see part of the cell, not only foreground
        for a in range(n_cams):
            c = cams[a]
            status = boxes[cell, c, 4]
            if status == 0:
                continue
            u0 = np.int64(boxes[cell, c, 0])
            v0 = np.int64(boxes[cell, c, 1])
            u1 = np.int64(boxes[cell, c, 2]) + 1
            v1 = np.int64(boxes[cell, c, 3]) + 1
            base = sat_offset[c]
            st = sat_stride[c]
            count = (sat[base + v1 * st + u1] - sat[base + v0 * st + u1]
                     - sat[base + v1 * st + u0] + sat[base + v0 * st + u0])
            if count > 0:
                may_fg += 1
                if count == (u1 - u0) * (v1 - v0):
                    if status == 2:
                        if sat_fg is None:
                            sure_fg += 1
                        elif (sat_fg[base + v1 * st + u1] - sat_fg[base + v0 * st + u1]
                              - sat_fg[base + v1 * st + u0] + sat_fg[base + v0 * st + u0]) == count:
                            sure_fg += 1
                        else:
                            may_bg += 1
                    elif sat_fg is not None:
                        may_bg += 1
                else:
                    may_bg += 1
            else:
                may_bg += 1
                if status == 2:
                    sure_bg += 1
                    if sure_bg > tolerance:
                        break
            if may_fg + (n_cams - 1 - a) < min_views:
                break
        if sure_bg > tolerance or may_fg < min_views or (sure_bg > 0 and may_fg < miss_support):
            continue
        if sure_fg >= fill_views and may_bg <= tolerance and (may_bg == 0 or sure_fg >= miss_support):
            out_full[n_full] = cell
            n_full += 1
        elif expand:
            for o in range(8):
                out_edge[n_edge] = cell * 8 + o
                n_edge += 1
        else:
            out_edge[n_edge] = cell
            n_edge += 1
    return n_edge, n_full


#: Vote of a mask pixel in :func:`carve_cells`: foreground 1, background 32 (so up to
#: 31 cameras); pixels of cameras without a mask this frame, and the sentinel after the
#: last mask that the table's ``-1`` ("not seen") reads, vote 0.
FG_VOTE, BG_VOTE, VOTE_SHIFT = 1, 32, 5
MAX_CAMERAS = BG_VOTE - 1


@njit(cache=True, nogil=True)
def mask_votes(mask, out):
    """Votes (foreground 1, background 32) of a 0/1 mask, both flat arrays."""
    for q in range(mask.shape[0]):
        out[q] = FG_VOTE if mask[q] else BG_VOTE


#: Vote of a background pixel behind a learnt occluder (:mod:`.occlusion`): the camera
#: abstains on voxels at or past the occluder's depth and votes background on nearer ones.
OCC_VOTE = 2


@njit(cache=True, nogil=True)
def occluded_votes(mask, occluded, out):
    """Votes of a 0/1 mask with learnt occluders (``occluded`` 1): foreground 1,
    background 32, background behind an occluder :data:`OCC_VOTE`."""
    for q in range(mask.shape[0]):
        if mask[q]:
            out[q] = FG_VOTE
        elif occluded[q]:
            out[q] = OCC_VOTE
        else:
            out[q] = BG_VOTE


@njit(cache=True, nogil=True, inline="always")
def _vote(v, c, i, j, k, q, depth_coef, occ_depth, k_top):
    """A camera's vote on voxel (i, j, k); behind an occluder it abstains (0) when the
    voxel lies at or past the occluder's depth and below layer ``k_top`` (furniture is
    low), and says background otherwise."""
    if v != OCC_VOTE:
        return v
    if k >= k_top:
        return BG_VOTE
    z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
    return 0 if z >= occ_depth[q] else BG_VOTE


@njit(cache=True, nogil=True)
def carve_cells_occluded(cells, shift, lut, votes, depth_coef, occ_depth, tolerance, min_views, brick_key, local_key,
                         shift_i, shift_j, out, n, support=0, k_top=1 << 30, miss_support=0):
    """:func:`carve_cells` with learnt occluders: a camera abstains on a voxel behind
    one of its occluders (its pixel votes :data:`OCC_VOTE` and the voxel's depth in
    that camera, ``depth_coef . (i, j, k, 1)``, is at least ``occ_depth`` there). A
    voxel on which a camera abstains needs ``support`` foreground votes (and
    ``min_views``). Cameras abstain only on voxels below layer ``k_top``. A voxel some
    camera calls background needs ``miss_support`` foreground votes (:func:`carve_cells`)."""
    n_cams = lut.shape[1]
    bshift = np.int64(0)
    while (np.int64(1) << bshift) < local_key.shape[0]:
        bshift += 1
    lmask = local_key.shape[0] - 1
    mask_j = (np.int64(1) << (shift_i - shift_j)) - 1
    mask_k = (np.int64(1) << shift_j) - 1
    size = np.int64(1) << shift
    for ci in range(cells.shape[0]):
        start = np.int64(cells[ci]) << shift
        base_key = brick_key[start >> bshift]
        for p in range(start, start + size):
            key = base_key + local_key[p & lmask]
            i = key >> shift_i
            j = (key >> shift_j) & mask_j
            k = key & mask_k
            total = 0
            abstain = 0
            for c in range(n_cams):
                q = lut[p, c]
                v = _vote(votes[q], c, i, j, k, q, depth_coef, occ_depth, k_top)
                total += v
                if v == 0 and votes[q] == OCC_VOTE:
                    abstain += 1
            fg = total & MAX_CAMERAS
            nbg = total >> VOTE_SHIFT
            if nbg <= tolerance and fg >= min_views and (abstain == 0 or fg >= support) \
                    and (nbg == 0 or fg >= miss_support):
                out[n] = key
                n += 1
    return n


@njit(cache=True, nogil=True)
def dissent_cells(cells, shift, lut, votes, raw, depth_coef, occ_depth, dissent, support, brick_key, local_key,
                  shift_i, shift_j, flag, flag_depth, free_depth, k_top=1 << 30):
    """Evidence for occluders (Guan et al. 2006): for every voxel of ``cells`` that
    exactly ``dissent`` cameras call background (``votes`` with the occluders learnt
    so far, as :func:`carve_cells_occluded` reads them) while at least ``support`` call
    it foreground, set ``flag`` (the concatenated masks' pixels, as ``votes``) at the
    pixels where the voxel is background in the masks (``raw`` votes: the dissenting
    cameras and those abstaining behind an occluder) and keep there the least depth of
    such a voxel (``flag_depth``). A camera that sees a voxel all cameras agree on as
    foreground sees the room free up to that depth (``free_depth``, the largest such
    depth per pixel): evidence at or in front of it is a contradiction (a phantom where
    the cones of other people meet, not something hidden) and is not counted.
    Returns the number of voxels that gave evidence."""
    n_cams = lut.shape[1]
    bshift = np.int64(0)
    while (np.int64(1) << bshift) < local_key.shape[0]:
        bshift += 1
    lmask = local_key.shape[0] - 1
    mask_j = (np.int64(1) << (shift_i - shift_j)) - 1
    mask_k = (np.int64(1) << shift_j) - 1
    size = np.int64(1) << shift
    count = 0
    for ci in range(cells.shape[0]):
        start = np.int64(cells[ci]) << shift
        base_key = brick_key[start >> bshift]
        for p in range(start, start + size):
            key = base_key + local_key[p & lmask]
            i = key >> shift_i
            j = (key >> shift_j) & mask_j
            k = key & mask_k
            total = 0
            for c in range(n_cams):
                q = lut[p, c]
                total += _vote(votes[q], c, i, j, k, q, depth_coef, occ_depth, k_top)
            if k >= k_top:      # no evidence for an occluder from above its highest layer
                if (total & MAX_CAMERAS) < support or (total >> VOTE_SHIFT) != 0:
                    continue
            if (total & MAX_CAMERAS) < support:
                continue
            nbg = total >> VOTE_SHIFT
            if nbg == 0:
                for c in range(n_cams):
                    q = lut[p, c]
                    if raw[q] == FG_VOTE:
                        z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
                        if z > free_depth[q]:
                            free_depth[q] = z
            elif nbg == dissent:
                counted = False
                for c in range(n_cams):
                    q = lut[p, c]
                    if raw[q] == BG_VOTE:
                        z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
                        if z <= free_depth[q]:
                            continue
                        counted = True
                        flag[q] = 1
                        if z < flag_depth[q]:
                            flag_depth[q] = z
                if counted:
                    count += 1
    return count


@njit(cache=True, nogil=True)
def carve_cells(cells, shift, lut, votes, tolerance, min_views, brick_key, local_key, out, n, early_exit=False,
                miss_support=0):
    """Exact centre test (§2.2.4) of every voxel of ``cells`` (each ``2^shift``
    consecutive brick-layout positions). Appends the keys of the occupied voxels to
    ``out`` from index ``n``; returns the new count.

    ``lut`` (n_positions, C) int32 indices into ``votes`` (the concatenated masks as
    votes, see :data:`FG_VOTE`; ``-1``, "not seen", wraps to the 0 sentinel at the end).
    The sum of a voxel's votes is ``N_fg + 32 N_bg``: no branch per camera. With
    ``early_exit`` the cameras' votes stop at the ``tolerance + 1``-th background answer
    (faster where most voxels are empty, as in the flat scan; slower on the edge cells
    the hierarchical method leaves, where the branch is unpredictable).

    ``miss_support`` (an addition to the thesis; 0 = §2.2.4 as written): a voxel that
    some camera calls background is occupied only if at least ``miss_support`` cameras
    call it foreground. The tolerance is there for a camera whose segmentation fails on
    a body seen by many; with few cameras it mostly keeps the places where the cones of
    two people cross (phantoms).
    """
    n_cams = lut.shape[1]
    bshift = np.int64(0)
    while (np.int64(1) << bshift) < local_key.shape[0]:
        bshift += 1
    lmask = local_key.shape[0] - 1
    size = np.int64(1) << shift
    for ci in range(cells.shape[0]):
        start = np.int64(cells[ci]) << shift
        base_key = brick_key[start >> bshift]
        for p in range(start, start + size):
            total = 0
            if early_exit:
                for c in range(n_cams):
                    total += votes[lut[p, c]]
                    if (total >> VOTE_SHIFT) > tolerance:
                        break
            else:
                for c in range(n_cams):
                    total += votes[lut[p, c]]
            nbg = total >> VOTE_SHIFT
            fg = total & MAX_CAMERAS
            if nbg <= tolerance and fg >= min_views and (nbg == 0 or fg >= miss_support):
                out[n] = base_key + local_key[p & lmask]
                n += 1
    return n


@njit(cache=True, nogil=True)
def fill_cells(cells, shift, brick_key, local_key, out, n):
    """Append the keys of every voxel of foreground ``cells`` to ``out``; returns the count."""
    bshift = np.int64(0)
    while (np.int64(1) << bshift) < local_key.shape[0]:
        bshift += 1
    lmask = local_key.shape[0] - 1
    size = np.int64(1) << shift
    for ci in range(cells.shape[0]):
        start = np.int64(cells[ci]) << shift
        base_key = brick_key[start >> bshift]
        for p in range(start, start + size):
            out[n] = base_key + local_key[p & lmask]
            n += 1
    return n
