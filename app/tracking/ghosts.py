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

**A witness must see it.** The hull that the tracker gets keeps voxels that one camera
misses (tolerance k = 1), so a camera that sees the room through a ghost still finds
cells of the ghost that no person covers, and counted as a witness: on tuning seed 55
a ghost beside a person who stood still (a camera whose masks flickered as its own
witness, a camera that saw the floor through it as the second) held a track for 105
frames. With the frame's silhouettes (:meth:`seen_cells`; the voxels bring them, the
CCA worker passes them on) a cell is the candidate's own only where that camera's
silhouette has foreground within ``seen_grow`` cells (2: a real person whose one
camera's mask is thin there stays a witness of it; 0 refused a short person on tuning
seed 28). Chosen on the tuning seeds (docs/benchmarks.md, "A ghost test that asks the
silhouettes").

Pure: cameras in (:class:`calibration.camera.Camera`), verdicts out; no bus.
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit

__all__ = ["GhostTest", "warm_up"]


class GhostTest:
    """``test(centres_mine, centres_others) -> bool`` (ghost or not); see the module
    docstring. ``cameras``: the room's cameras (``project``, ``width``, ``height``)."""

    def __init__(self, cameras, cell: int = 8, min_own: float = 0.2, min_cameras: int = 2, min_cells: int = 4,
                 seen_grow: int = 2):
        self.cameras = tuple(cameras)
        self.seen_grow = int(seen_grow)
        self.min_cameras = int(min_cameras)
        self.cell = int(cell)
        self.min_own = float(min_own)
        self.min_cells = int(min_cells)
        self._kernel = np.ones((3, 3), np.uint8)
        self._covers: dict = {}   # (camera, silhouette size) -> the cells' rows and columns (_cover)

    def _cells(self, camera, centres: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        w, h = -(-int(camera.width) // self.cell), -(-int(camera.height) // self.cell)
        centres = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(centres), np.int64)
        n = _project_cells(centres, camera.R, camera.t, camera.K, camera.dist, float(self.cell), w, h, out)
        return out[:n], (h, w)

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

    def seen_cells(self, masks: dict | None) -> list | None:
        """Per camera, which cells lie within ``seen_grow`` cells of foreground in its
        silhouette ``masks[name]`` (as the reconstruction sends it: the image, reduced by
        a whole factor), flat like :meth:`counts`' grids (None where a camera has none);
        None when no camera has one."""
        if not masks or not any(cam.name in masks for cam in self.cameras):
            return None
        out = []
        for cam in self.cameras:
            mask = masks.get(cam.name)
            if mask is None:
                out.append(None)
                continue
            rows, cols = self._cover(cam, mask.shape)
            seen = ((rows @ np.asarray(mask, np.float32) @ cols) > 0).astype(np.uint8)
            if self.seen_grow > 0:
                seen = cv2.dilate(seen, np.ones((2 * self.seen_grow + 1,) * 2, np.uint8))
            out.append(seen.reshape(-1) > 0)
        return out

    def _cover(self, camera, shape) -> tuple[np.ndarray, np.ndarray]:
        """Which rows ``(h, H')`` and columns ``(W', w)`` of a silhouette of ``shape``
        (H', W') each cell covers, as 0/1 matrices: a cell holds foreground when
        ``rows @ mask @ cols`` > 0, as it does in the silhouette enlarged to the image
        (nearest pixel, OpenCV's) and taken cell by cell, without enlarging it each frame
        (8 cameras: 6.8 ms a frame that way). Cached per camera and size."""
        key = (camera.name, tuple(shape))
        if key not in self._covers:
            W, H = int(camera.width), int(camera.height)
            h, w = -(-H // self.cell), -(-W // self.cell)
            # the silhouette's row and column under each image pixel, by the resize itself
            ys = cv2.resize(np.arange(shape[0], dtype=np.float32)[:, None], (1, H), interpolation=cv2.INTER_NEAREST)
            xs = cv2.resize(np.arange(shape[1], dtype=np.float32)[None, :], (W, 1), interpolation=cv2.INTER_NEAREST)
            rows = np.zeros((h, shape[0]), np.float32)
            rows[np.arange(H) // self.cell, ys.ravel().astype(np.int64)] = 1.0
            cols = np.zeros((shape[1], w), np.float32)
            cols[xs.ravel().astype(np.int64), np.arange(W) // self.cell] = 1.0
            self._covers[key] = rows, cols
        return self._covers[key]

    def own_shares(self, mine: np.ndarray, counts: list, minus: np.ndarray | None = None,
                   seen: list | None = None) -> np.ndarray:
        """Per camera, the share of the candidate's cells no other voxel covers (NaN where
        the camera sees fewer than ``min_cells`` of its cells); ``counts``: the
        :meth:`counts` of the other voxels, less the voxels ``minus`` (those of them
        that are the candidate's own). With ``seen`` (:meth:`seen_cells`) a cell is the
        candidate's own only where that camera's silhouette has foreground: a camera that
        sees the room through the candidate is no witness of it."""
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
            own = cover[cells] == 0
            if seen is not None and seen[k] is not None:
                own &= seen[k][cells]
            out[k] = float(own.mean())
        return out

    def __call__(self, mine: np.ndarray, others: np.ndarray) -> bool:
        """Whether the candidate ``mine`` is a ghost of the voxels ``others``."""
        if len(others) == 0 or len(mine) == 0:
            return False
        return self.verdict(mine, self.counts(others))

    def verdict(self, mine: np.ndarray, counts: list, minus: np.ndarray | None = None, seen: list | None = None) -> bool:
        """:meth:`__call__` with the others' :meth:`counts` computed before (once for
        all the candidates of a frame), less ``minus`` (the candidate's voxels among
        them); the caller knows some other voxel is left. ``seen``: :meth:`own_shares`."""
        if len(mine) == 0:
            return False
        shares = self.own_shares(mine, counts, minus, seen)
        judged = shares[np.isfinite(shares)]
        if not len(judged):
            return False
        return int((judged >= self.min_own).sum()) < min(self.min_cameras, len(judged))


@njit(cache=True, nogil=True)
def _project_cells(points, R, t, K, dist, cell, w, h, out):
    """The cells (``row * w + column`` of ``cell``-pixel cells) of the points (N, 3) in
    front of the camera that project inside its image, into ``out``; how many.
    :meth:`calibration.camera.Camera.project` (Eq. 2.5 with OpenCV's lens model) point
    by point, in one pass: the tracker's ghost test projects every voxel of the known
    people each frame (at 2 cm, 4.6 ms a camera through numpy's temporaries)."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    n = 0
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        if not zc > 1e-9:
            continue                      # behind the camera (project gives NaN)
        inv = 1.0 / zc
        xn, yn = xc * inv, yc * inv
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        u = (K[0, 0] * xd + K[0, 1] * yd + K[0, 2]) / cell
        v = (K[1, 1] * yd + K[1, 2]) / cell
        if u >= 0.0 and u < w and v >= 0.0 and v < h:
            out[n] = np.int64(v) * w + np.int64(u)
            n += 1
    return n


def warm_up() -> None:
    """Compile (or load) the projection kernel before the first frame."""
    out = np.empty(1, np.int64)
    _project_cells(np.ones((1, 3)), np.eye(3), np.zeros(3), np.eye(3), np.zeros(5), 8.0, 4, 4, out)
