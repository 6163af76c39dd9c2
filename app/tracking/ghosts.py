"""Ghost test for new tracks: a blob where other people's silhouette cones cross (beyond
the thesis; issue 22).

Shape-from-silhouette keeps every voxel that all cameras see inside a silhouette, so
where the viewing cones of two or more people cross, away from all of them, the hull
holds volume that is nobody's body: a *ghost* (phantom volume). With few cameras (3-4)
or several people such blobs are common, and with the size and height of a short or
seated person the classifier cannot tell them from one. What it cannot see, the cameras
can: a ghost exists only because, in every camera, each of its voxels lies on a ray that
meets another person; a real person has pixels of their own in more than one camera.

:class:`GhostTest` projects the voxels of a candidate and those of the people already
known (the components the tracks hold: not every other voxel, since ghosts explain the
people's pixels as much as people explain theirs) into each camera, on a grid of ``cell``-pixel cells (the other voxels' cells
grown by one cell: a voxel covers about a cell); the candidate's *own share* in a
camera is the fraction of its cells no other voxel covers. The candidate is a ghost
unless its own share reaches ``min_own`` in at least ``min_cameras`` cameras (two: a
ghost can own the pixels of one camera whose foreground there is a shadow or noise, a
person in view is seen by more than one; with fewer cameras seeing it, all of them). The tracker asks
before a candidate may count towards a new track (:class:`~app.tracking.tracker.MultiTracker`,
``ghost_test``); tracks are kept, and people behind others in every view wait until
some camera sees them.

Pure: cameras in (:class:`calibration.camera.Camera`), verdicts out; no bus.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["GhostTest"]


class GhostTest:
    """``test(centres_mine, centres_others) -> bool`` (ghost or not); see the module
    docstring. ``cameras``: the room's cameras (``project``, ``width``, ``height``)."""

    def __init__(self, cameras, cell: int = 8, min_own: float = 0.2, min_cameras: int = 2, min_cells: int = 4):
        self.cameras = tuple(cameras)
        self.min_cameras = int(min_cameras)
        self.cell = int(cell)
        self.min_own = float(min_own)
        self.min_cells = int(min_cells)
        self._kernel = np.ones((3, 3), np.uint8)

    def _cells(self, camera, centres: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        w, h = -(-int(camera.width) // self.cell), -(-int(camera.height) // self.cell)
        uv = camera.project(centres) / self.cell
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)   # NaN (behind): False
        uv = uv[ok].astype(np.int64)
        return uv[:, 1] * w + uv[:, 0], (h, w)

    def counts(self, others: np.ndarray) -> list[np.ndarray]:
        """Per camera, how many of the voxels ``others`` fall in each cell (flat grids):
        what :meth:`own_shares` tests candidates against, projected once for all the
        candidates of a frame (at 2 cm, projecting the known people for every candidate
        cost crowd6's tracking 100-400 ms a frame: issue 26)."""
        others = np.asarray(others, np.float64)
        out = []
        for cam in self.cameras:
            cells, (h, w) = self._cells(cam, others)
            out.append(np.bincount(cells, minlength=h * w))
        return out

    def own_shares(self, mine: np.ndarray, counts: list, minus: np.ndarray | None = None) -> np.ndarray:
        """Per camera, the share of the candidate's cells no other voxel covers (NaN where
        the camera sees fewer than ``min_cells`` of its cells); ``counts``: the
        :meth:`counts` of the other voxels, less the voxels ``minus`` (those of them
        that are the candidate's own)."""
        out = np.full(len(self.cameras), np.nan)
        mine = np.asarray(mine, np.float64)
        for k, cam in enumerate(self.cameras):
            cells, (h, w) = self._cells(cam, mine)
            cells = np.unique(cells)
            if len(cells) < self.min_cells:
                continue
            n = counts[k]
            if minus is not None and len(minus):
                n = n - np.bincount(self._cells(cam, np.asarray(minus, np.float64))[0], minlength=h * w)
            cover = cv2.dilate((n > 0).astype(np.uint8).reshape(h, w), self._kernel).reshape(-1)
            out[k] = float((cover[cells] == 0).mean())
        return out

    def __call__(self, mine: np.ndarray, others: np.ndarray) -> bool:
        """Whether the candidate ``mine`` is a ghost of the voxels ``others``."""
        if len(others) == 0 or len(mine) == 0:
            return False
        return self.verdict(mine, self.counts(others))

    def verdict(self, mine: np.ndarray, counts: list, minus: np.ndarray | None = None) -> bool:
        """:meth:`__call__` with the others' :meth:`counts` computed before (once for
        all the candidates of a frame), less ``minus`` (the candidate's voxels among
        them); the caller knows some other voxel is left."""
        if len(mine) == 0:
            return False
        shares = self.own_shares(mine, counts, minus)
        seen = shares[np.isfinite(shares)]
        if not len(seen):
            return False
        return int((seen >= self.min_own).sum()) < min(self.min_cameras, len(seen))
