"""One frame as the filters see it (§4.2.1: ``z_t = {V_t, V_t^C}`` plus ``V_t^S`` and the
components), and the colour model of §4.3.2.

:class:`SceneFrame` holds the grid indices (sorted by (x, y, z), as the reconstruction
publishes them; an unsorted list is sorted once), surface flags, YCbCr colour bins of
the coloured (surface) voxels, component labels, features and person verdicts, and
the column index of :mod:`app.tracking.columns` through which every neighbourhood
query is answered in O(visited voxels) (DESIGN §3). Voxel centres are computed for
the voxels asked for (:meth:`SceneFrame.centres_at`), never for the whole frame.
:class:`OccupancyIndex` keeps the grid's per-frame buffers between frames (and a dense
grid of list positions for whoever still asks for ``scene.grid``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.tracking import columns

__all__ = ["SceneFrame", "OccupancyIndex", "colour_bins", "histogram", "bhattacharyya", "coverage_threshold",
           "BINS"]

BINS = 21   # per YCbCr channel (§4.3.2)


def colour_bins(rgb: np.ndarray) -> np.ndarray:
    """Joint YCbCr bin (0 .. 21^3-1) of RGB uint8 colours (N, 3) (ITU-R BT.601, full range)."""
    c = np.asarray(rgb, dtype=np.float32).reshape(-1, 3)
    r, g, b = c[:, 0], c[:, 1], c[:, 2]
    y = 0.299 * r + 0.587 * g + 0.114 * b
    cb = 128.0 - 0.168736 * r - 0.331264 * g + 0.5 * b
    cr = 128.0 + 0.5 * r - 0.418688 * g - 0.081312 * b
    q = lambda v: np.clip((v * (BINS / 256.0)).astype(np.int32), 0, BINS - 1)  # noqa: E731
    return (q(y) * BINS + q(cb)) * BINS + q(cr)


def histogram(bins: np.ndarray) -> np.ndarray | None:
    """Normalised joint histogram (21^3,) of colour bins, or None when there are none."""
    bins = np.asarray(bins)
    if bins.size == 0:
        return None
    h = np.bincount(bins, minlength=BINS ** 3).astype(np.float64)
    return h / h.sum()


def bhattacharyya(h1: np.ndarray, h2: np.ndarray) -> float:
    """Bhattacharyya coefficient sum sqrt(h1 h2) (1: same distribution); Eq. 4.10's ``B``
    is used as a similarity, so this is the coefficient, not the distance."""
    return float(np.sqrt(h1 * h2).sum())


def coverage_threshold(h: np.ndarray, coverage: float = 0.8) -> float:
    """The threshold gamma of Eq. 4.21: the smallest histogram value among the highest
    bins that together hold ``coverage`` of the histogram's mass."""
    v = np.sort(h[h > 0])[::-1]
    if v.size == 0:
        return np.inf
    k = int(np.searchsorted(np.cumsum(v), coverage * v.sum()))
    return float(v[min(k, v.size - 1)])


@njit(cache=True, nogil=True)
def _write(grid, idx, value_from_index):
    for a in range(idx.shape[0]):
        grid[idx[a, 0], idx[a, 1], idx[a, 2]] = a if value_from_index else -1


class OccupancyIndex:
    """The per-grid buffers of the scene frames, kept between frames: the column
    starts of voxels and runs (16 bytes per grid column) and, on demand, a dense grid of list positions
    (-1: empty) written for the occupied voxels and wiped the same way."""

    def __init__(self, dims):
        self.dims = tuple(int(d) for d in dims)
        self.col_start = np.zeros(self.dims[0] * self.dims[1] + 1, dtype=np.int64)
        self.col_run = np.zeros(self.dims[0] * self.dims[1] + 1, dtype=np.int64)
        self._grid = None
        self._idx = np.zeros((0, 3), dtype=np.int64)

    def load(self, indices: np.ndarray) -> np.ndarray:
        if self._grid is None:
            self._grid = np.full(self.dims, -1, dtype=np.int32)
        _write(self._grid, self._idx, False)
        self._idx = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1, 3)
        _write(self._grid, self._idx, True)
        return self._grid

    @property
    def grid(self) -> np.ndarray:
        return self._grid


class SceneFrame:
    """What the filters need of one frame (see module docstring)."""

    def __init__(self, frame: int, t: float, indices, colours, surface, labels, features, person,
                 origin, voxel_size: float, occupancy: OccupancyIndex | None = None, silhouettes: dict | None = None):
        self.frame, self.t = int(frame), float(t)
        #: the frame's silhouettes (camera name -> boolean mask, reduced as the
        #: reconstruction sends them) for the ghost test, or None
        self.silhouettes = silhouettes
        idx = np.asarray(indices).reshape(-1, 3)   # any integer type (the bus's uint16 kept: no copy)
        if idx.dtype.kind not in "iu" or not idx.flags.c_contiguous:
            idx = np.ascontiguousarray(idx, dtype=np.int64)
        n = len(idx)
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(voxel_size)
        if occupancy is None:
            occupancy = OccupancyIndex(tuple(int(d) for d in (idx.max(0) + 1 if n else (1, 1, 1))))
        self.occupancy = occupancy
        self.dims = occupancy.dims
        surface = np.asarray(surface, dtype=bool).reshape(-1)
        surface = surface if surface.shape == (n,) else np.zeros(n, dtype=bool)
        colours = np.asarray(colours).reshape(-1, 3) if np.asarray(colours).size else np.zeros((0, 3), np.uint8)
        labels = np.asarray(labels).reshape(n)
        if labels.dtype.kind not in "iu":
            labels = labels.astype(np.int64)
        self.has_colour = len(colours) == n and n > 0
        self.col_start = occupancy.col_start
        self.col_run = occupancy.col_run
        m = self._runs(idx)
        if m < 0:   # the column index needs (x, y, z) order, each voxel once
            key = (idx[:, 0].astype(np.int64) * self.dims[1] + idx[:, 1]) * self.dims[2] + idx[:, 2]
            order = np.unique(key, return_index=True)[1]
            idx, surface, labels = idx[order], surface[order], labels[order]
            colours = colours[order] if self.has_colour else colours
            n = len(idx)
            m = self._runs(idx)
        self.indices = idx
        self.surface = surface
        # colour bin of every voxel; -1 where the voxel has no colour (interior, uncoloured)
        self.bins = np.full(n, -1, dtype=np.int32)
        if self.has_colour:
            coloured = self.surface if self.surface.any() else colours.any(axis=1)
            self.bins[coloured] = colour_bins(colours[coloured])
        self.labels = labels
        self.run_label = labels[self.run_start[:-1]]
        self.features = np.asarray(features, dtype=np.float64).reshape(-1, 9)
        self.person = np.asarray(person, dtype=bool).reshape(-1)
        self._centres = None

    def _runs(self, idx: np.ndarray) -> int:
        n = len(idx)
        start, z0, z1, col = np.empty(n + 1, np.int64), np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        m = columns.frame_runs(idx, self.dims[1], self.dims[2], self.col_start, self.col_run, start, z0, z1, col)
        if m >= 0:
            self.run_start, self.run_z0, self.run_z1, self.run_col = start[:m + 1], z0[:m], z1[:m], col[:m]
        return m

    @property
    def n(self) -> int:
        return len(self.indices)

    @property
    def components(self) -> int:
        return len(self.features)

    @property
    def centres(self) -> np.ndarray:
        """Centres (N, 3) of every voxel (computed once, on demand: prefer :meth:`centres_at`)."""
        if self._centres is None:
            self._centres = self.origin + (self.indices + 0.5) * self.voxel_size
        return self._centres

    def centres_at(self, sel: np.ndarray) -> np.ndarray:
        """Centres (len(sel), 3) of the voxels at list positions ``sel``."""
        return self.origin + (self.indices[sel] + 0.5) * self.voxel_size

    @property
    def grid(self) -> np.ndarray:
        """Dense grid of list positions (-1: empty), written on first use."""
        return self.occupancy.load(self.indices) if self.occupancy.grid is None or \
            not np.array_equal(self.occupancy._idx, self.indices) else self.occupancy.grid

    def near_xy(self, xy, radius: float) -> np.ndarray:
        """List positions (ascending) of the voxels within ``radius`` (m) of ``xy`` in the
        xy plane (the columns of the disc)."""
        return columns.near(self.col_start, self.dims[0], self.dims[1], self.origin[0], self.origin[1],
                            self.voxel_size, float(xy[0]), float(xy[1]), float(radius))
