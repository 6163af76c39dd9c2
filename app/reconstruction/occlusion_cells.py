"""Occlusion learnt per voxel cell and camera (issue 8; Guan, Franco and Pollefeys,
"Visual hull construction in the presence of partial occlusion", 3DPVT 2006, with the
occlusion kept in 3D rather than in the image).

Shape from silhouette with ``tolerance = 0`` (thesis §2.2.4: a voxel is occupied when
``N_fg >= N_visible - k`` with ``k = 0``) loses every part of a body that one camera
cannot see (legs under the table, behind a chair); ``k = 1`` keeps it and pays for it
everywhere. :mod:`.occlusion` learns occluders per *pixel* (with a depth): a camera
then abstains on the whole ray segment behind an occluder pixel, which lets in the
phantoms of the other views all along it, whoever's body gave the evidence.

Here the evidence is kept per coarse *cell* of the room (``cell`` metres, e.g. 8 cm)
and camera ``c``: camera ``c`` may miss a voxel (call it background while every other
camera that sees it calls it foreground) only inside cells where, over the past
frames, ``c`` has repeatedly been the one dissenter on voxels the others support, and
has seldom seen a person itself. Per cell ``X`` and camera ``c`` the model counts

    ``evidence(X, c)``: frames with a voxel of ``X`` that exactly ``k + 1`` cameras, one
        of them ``c``, call background, at least ``support`` cameras call foreground,
        below ``top`` metres (furniture is low; the phantoms of the cones of other
        people reach head height), and that lies *behind* everything ``c`` has ever
        seen through that pixel (see below);
    ``seen(X, c)``: frames with a voxel of ``X`` on which all cameras agree
        (foreground) and ``c`` calls foreground: ``c`` sees people in ``X``;

and ``c`` may miss a voxel of ``X`` once ``evidence >= min_evidence`` (default 1)
and ``evidence >= ratio * (evidence + seen)`` (default 0.4; 2 and 0.5, or cells of 4
or 12 cm, move along the same recall-volume curve, docs/history/reconstruction-hull.md).
Learning is causal (a frame is carved with what the earlier frames taught, then
teaches), deterministic for a recording, and
bounded (two counters per cell and camera: at 8 cm, 5 cameras and a 5 x 4 x 2.5 m room
about 0.5 M of each, ~4 MB).

Seen free space (Guan et al.'s argument that an occluder lies between the camera and
what it hides): per pixel, the deepest point at which ``c`` has seen a person that all
cameras agree on. Nothing static hides anything in front of that depth, so a dissent
of ``c`` at or in front of it is a phantom of the other views, no evidence. Without
this test the phantoms' evidence dominates (measured offline on meeting3 at 4 cm with
the true silhouettes: 0.94 of the body at 4.2-4.6x against 0.94 / 2.6x with it).

Against the per-pixel occluders (the ``tight`` hull) on meeting3 and crowd6 at 2 and
4 cm, with the segmentation's masks and with the true silhouettes, it keeps as much
of the body or more at 0.1-0.35x less volume; with the ghost filter
(:mod:`.ghosts`) meeting3 at 2 cm with the true silhouettes keeps 0.968 of the body at
2.48x (docs/benchmarks.md, "Reconstruction": the hull table).

Implementation: the frame is carved at tolerance ``k + 1`` (the ordinary coarse-to-
fine carving, :mod:`.carving`), then :func:`select_and_learn` visits the carved voxels
once: a voxel with at most ``k`` misses is kept; one with ``k + 1`` is kept only where
every dissenting camera is learnt occluded at its cell (and it has ``support``
foreground votes, below ``top``); the same visit gathers the frame's evidence.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .carving import BG_VOTE, FG_VOTE, MAX_CAMERAS, VOTE_SHIFT
from .grid import brick_position

__all__ = ["CellOccluders", "select_and_learn", "MISSES_SHIFT"]


#: bit of a key above which :func:`select_and_learn` stores the voxel's misses
MISSES_SHIFT = 56


@njit(cache=True, nogil=True)
def select_and_learn(keys, shift_i, shift_j, levels, brick_dims, lut, votes, depth_coef, tolerance, support, k_top,
                     cell, cell_dims, occluded, learn, free_depth, seen_flag, evidence_flag):
    """Select the voxels of a hull carved at ``tolerance + 1`` and gather one frame's
    evidence (module docstring).

    ``keys`` the carved voxels' sort keys ``(i << shift_i) | (j << shift_j) | k`` in
    the carving's (brick) order, so the table rows are read nearly in sequence;
    ``lut``/``votes`` the carving's projection table and vote buffer
    (:data:`.carving.BG_VOTE` background, ``FG_VOTE`` foreground, 0 unseen / no mask);
    ``depth_coef`` (C, 4): depth of voxel (i, j, k) in camera ``c`` is
    ``depth_coef[c] . (i, j, k, 1)``; ``cell`` voxels per cell side, ``cell_dims`` the
    cell grid; ``occluded`` (n_cells * C) uint8 the learnt model. With ``learn``:
    ``free_depth`` (per pixel of the concatenated masks) is raised by the agreed
    voxels, and ``seen_flag`` / ``evidence_flag`` (n_cells * C) are set for this frame.
    The kept keys are moved to the front of ``keys``, each with its misses (the
    cameras calling it background) in the bits from :data:`MISSES_SHIFT` up; returns
    how many."""
    n_cams = lut.shape[1]
    nby = np.int64(brick_dims[1])
    nbz = np.int64(brick_dims[2])
    cy = np.int64(cell_dims[1])
    cz = np.int64(cell_dims[2])
    mask_j = (np.int64(1) << (shift_i - shift_j)) - 1
    mask_k = (np.int64(1) << shift_j) - 1
    if learn:
        # free space and "seen" from the voxels every camera agrees on, before any evidence
        for n in range(keys.shape[0]):
            key = keys[n]
            i = key >> shift_i
            j = (key >> shift_j) & mask_j
            k = key & mask_k
            p = brick_position(i, j, k, levels, nby, nbz)
            nbg = 0
            for c in range(n_cams):
                if votes[lut[p, c]] == BG_VOTE:
                    nbg += 1
            if nbg:
                continue
            base = (((i // cell) * cy + (j // cell)) * cz + (k // cell)) * n_cams
            for c in range(n_cams):
                q = lut[p, c]
                if votes[q] == FG_VOTE:
                    seen_flag[base + c] = 1
                    z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
                    if z > free_depth[q]:
                        free_depth[q] = z
    kept = 0
    for n in range(keys.shape[0]):
        key = keys[n]
        i = key >> shift_i
        j = (key >> shift_j) & mask_j
        k = key & mask_k
        p = brick_position(i, j, k, levels, nby, nbz)
        total = 0
        for c in range(n_cams):
            total += votes[lut[p, c]]
        nbg = total >> VOTE_SHIFT
        nfg = total & MAX_CAMERAS
        ok = nbg <= tolerance
        if not ok and nbg == tolerance + 1 and nfg >= support and k < k_top:
            base = (((i // cell) * cy + (j // cell)) * cz + (k // cell)) * n_cams
            ok = True
            for c in range(n_cams):
                q = lut[p, c]
                if votes[q] == BG_VOTE:
                    if learn:   # evidence: behind the free space this frame included
                        z = depth_coef[c, 0] * i + depth_coef[c, 1] * j + depth_coef[c, 2] * k + depth_coef[c, 3]
                        if z > free_depth[q]:
                            evidence_flag[base + c] = 1
                    if occluded[base + c] == 0:
                        ok = False
        if ok:
            keys[kept] = key | (nbg << MISSES_SHIFT)
            kept += 1
    return kept


@njit(cache=True, nogil=True)
def _fold(evidence, seen, evidence_flag, seen_flag, occluded, min_evidence, ratio):
    """Add one frame's flags to the counts and update the occluded cells."""
    for x in range(evidence.shape[0]):
        if evidence_flag[x] or seen_flag[x]:
            evidence[x] += evidence_flag[x]
            seen[x] += seen_flag[x]
            evidence_flag[x] = 0
            seen_flag[x] = 0
            e = evidence[x]
            occluded[x] = 1 if (e >= min_evidence and e >= ratio * (e + seen[x])) else 0


class CellOccluders:
    """Occlusion per cell of ``cell`` voxels and camera, learnt over a run (module
    docstring). ``dims`` the voxel grid, ``n_cameras``, ``mask_total`` the pixels of
    the concatenated masks (:class:`~.projection.ProjectionTable`)."""

    def __init__(self, dims, cell: int, n_cameras: int, mask_total: int, min_evidence: int = 1, ratio: float = 0.4,
                 support: int = 3):
        if cell < 1 or min_evidence < 1 or not 0.0 < ratio <= 1.0 or support < 1:
            raise ValueError("occlusion cells: cell >= 1 voxel, min_evidence >= 1, 0 < ratio <= 1, support >= 1")
        self.cell = int(cell)
        self.cell_dims = np.array([(int(d) + self.cell - 1) // self.cell for d in dims], dtype=np.int64)
        self.n_cameras = int(n_cameras)
        n = int(np.prod(self.cell_dims)) * self.n_cameras
        self.min_evidence = int(min_evidence)
        self.ratio = float(ratio)
        self.support = int(support)
        self.evidence = np.zeros(n, dtype=np.float32)
        self.seen = np.zeros(n, dtype=np.float32)
        self.evidence_flag = np.zeros(n, dtype=np.uint8)
        self.seen_flag = np.zeros(n, dtype=np.uint8)
        self.occluded = np.zeros(n, dtype=np.uint8)
        self.free_depth = np.zeros(mask_total + 1, dtype=np.float32)   # + the "not seen" sentinel
        self.updates = 0

    @property
    def nbytes(self) -> int:
        return int(self.evidence.nbytes + self.seen.nbytes + self.evidence_flag.nbytes + self.seen_flag.nbytes
                   + self.occluded.nbytes + self.free_depth.nbytes)

    def fold(self) -> None:
        """Fold the frame's flags (set by :func:`select_and_learn`) into the model."""
        _fold(self.evidence, self.seen, self.evidence_flag, self.seen_flag, self.occluded, self.min_evidence,
              self.ratio)
        self.updates += 1

    def share(self, camera: int) -> float:
        """Fraction of the cells in which camera ``camera`` may miss a voxel."""
        return float(self.occluded[camera:: self.n_cameras].mean())

    def reset(self) -> None:
        for a in (self.evidence, self.seen, self.evidence_flag, self.seen_flag, self.occluded, self.free_depth):
            a[:] = 0
        self.updates = 0
