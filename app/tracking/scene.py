"""One frame as the filters see it (§4.2.1: ``z_t = {V_t, V_t^C}`` plus ``V_t^S`` and the
components), an occupancy index over the grid, and the colour model of §4.3.2.

:class:`SceneFrame` holds the voxel centres, grid indices, surface flags, YCbCr colour
bins of the coloured (surface) voxels, component labels, features and person verdicts.
:class:`OccupancyIndex` answers "which voxel of the list is at (i, j, k)" for the
neighbourhood queries of Sparse Sampling (Eq. 4.20-4.21) in O(1): it is written for the
occupied voxels and wiped the same way, so a frame costs O(occupied) (DESIGN §3).
"""
from __future__ import annotations

import numpy as np
from numba import njit

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


@njit(cache=True, nogil=True)
def _within(centres, order, a, b, x, y, r2):
    """List positions ``a .. b`` (through ``order`` when given) whose centre lies within
    ``sqrt(r2)`` of ``(x, y)``."""
    out = np.empty(b - a, dtype=np.int64)
    m = 0
    for k in range(a, b):
        i = order[k] if order.shape[0] else k
        dx = centres[i, 0] - x
        dy = centres[i, 1] - y
        if dx * dx + dy * dy <= r2:
            out[m] = i
            m += 1
    return out[:m]


class OccupancyIndex:
    """Grid of list positions (-1: empty), kept between frames."""

    def __init__(self, dims):
        self.dims = tuple(int(d) for d in dims)
        self.grid = np.full(self.dims, -1, dtype=np.int32)
        self._idx = np.zeros((0, 3), dtype=np.int64)

    def load(self, indices: np.ndarray) -> np.ndarray:
        _write(self.grid, self._idx, False)
        self._idx = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1, 3)
        _write(self.grid, self._idx, True)
        return self.grid


class SceneFrame:
    """What the filters need of one frame (see module docstring)."""

    def __init__(self, frame: int, t: float, indices, colours, surface, labels, features, person,
                 origin, voxel_size: float, occupancy: OccupancyIndex | None = None):
        self.frame, self.t = int(frame), float(t)
        self.indices = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1, 3)
        n = len(self.indices)
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(voxel_size)
        self.centres = self.origin + (self.indices + 0.5) * self.voxel_size
        surface = np.asarray(surface, dtype=bool).reshape(-1)
        self.surface = surface if surface.shape == (n,) else np.zeros(n, dtype=bool)
        colours = np.asarray(colours).reshape(-1, 3) if np.asarray(colours).size else np.zeros((0, 3), np.uint8)
        self.has_colour = len(colours) == n and n > 0
        # colour bin of every voxel; -1 where the voxel has no colour (interior, uncoloured)
        self.bins = np.full(n, -1, dtype=np.int64)
        if self.has_colour:
            coloured = self.surface if self.surface.any() else colours.any(axis=1)
            self.bins[coloured] = colour_bins(colours[coloured])
        self.labels = np.asarray(labels, dtype=np.int64).reshape(n)
        self.features = np.asarray(features, dtype=np.float64).reshape(-1, 9)
        self.person = np.asarray(person, dtype=bool).reshape(-1)
        self.occupancy = occupancy
        self._x_sorted = None
        self.grid = occupancy.load(self.indices) if occupancy is not None else None

    @property
    def components(self) -> int:
        return len(self.features)

    def near_xy(self, xy, radius: float) -> np.ndarray:
        """Indices of the voxels within ``radius`` (m) of ``xy`` in the xy plane (the list
        is sorted by grid x first, as the reconstruction publishes it, so only a slab of
        it is looked at; an unsorted list is sorted once)."""
        if self._x_sorted is None:
            ix = self.indices[:, 0]
            self._x_sorted = bool(np.all(ix[1:] >= ix[:-1])) if len(ix) > 1 else True
            if not self._x_sorted:
                self._order = np.argsort(ix, kind="stable")
                self._ix = ix[self._order]
        lo_x = int(np.floor((xy[0] - radius - self.origin[0]) / self.voxel_size - 0.5))
        hi_x = int(np.ceil((xy[0] + radius - self.origin[0]) / self.voxel_size - 0.5))
        ix = self.indices[:, 0] if self._x_sorted else self._ix
        a, b = np.searchsorted(ix, lo_x, "left"), np.searchsorted(ix, hi_x, "right")
        order = self._order if not self._x_sorted else np.zeros(0, dtype=np.int64)
        return _within(self.centres, order, int(a), int(b), float(xy[0]), float(xy[1]), radius * radius)
