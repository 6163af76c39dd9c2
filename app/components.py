"""Connected components of a voxel set (thesis §4.2.3, Eq. 4.1).

The reconstruction occupies ~1 % of the grid, so components are found by a
union-find over the list of occupied voxels, never by a scan of the dense grid
(DESIGN §3). Neighbours are found through an index grid holding each occupied
voxel's position in the list: it is written for the occupied voxels only and wiped
the same way, so a frame costs O(occupied voxels), whatever the grid size.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["Labeller", "label_voxels", "component_sizes"]


@njit(cache=True, nogil=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True, nogil=True)
def _label(idx, grid, offsets, labels):
    n = idx.shape[0]
    nx, ny, nz = grid.shape
    for a in range(n):
        grid[idx[a, 0], idx[a, 1], idx[a, 2]] = a
    parent = np.arange(n)
    for a in range(n):
        x, y, z = idx[a, 0], idx[a, 1], idx[a, 2]
        for o in range(offsets.shape[0]):
            qx, qy, qz = x + offsets[o, 0], y + offsets[o, 1], z + offsets[o, 2]
            if qx < 0 or qy < 0 or qz < 0 or qx >= nx or qy >= ny or qz >= nz:
                continue
            b = grid[qx, qy, qz]
            if b >= 0:
                ra, rb = _find(parent, a), _find(parent, b)
                if ra != rb:
                    if ra < rb:
                        parent[rb] = ra
                    else:
                        parent[ra] = rb
    for a in range(n):
        grid[idx[a, 0], idx[a, 1], idx[a, 2]] = -1
    count = 0
    remap = -np.ones(n, dtype=np.int64)
    for a in range(n):
        r = _find(parent, a)
        if remap[r] < 0:
            remap[r] = count
            count += 1
        labels[a] = remap[r]
    return count


def _half_offsets(connectivity: int) -> np.ndarray:
    """Neighbour offsets with a positive lexicographic sign (each pair visited once)."""
    offs = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                d = abs(dx) + abs(dy) + abs(dz)
                if d == 0 or (connectivity == 6 and d > 1) or (connectivity == 18 and d > 2):
                    continue
                if (dx, dy, dz) > (0, 0, 0):
                    offs.append((dx, dy, dz))
    return np.asarray(offs, dtype=np.int64)


class Labeller:
    """Connected components of voxel lists on one grid (its index grid is kept between
    frames: 4 bytes per grid voxel)."""

    def __init__(self, dims, connectivity: int = 26):
        if connectivity not in (6, 18, 26):
            raise ValueError("connectivity must be 6, 18 or 26")
        self.grid = np.full(tuple(int(d) for d in dims), -1, dtype=np.int32)
        self.offsets = _half_offsets(connectivity)

    def __call__(self, indices: np.ndarray) -> tuple[np.ndarray, int]:
        """Component label (N,) of each voxel of ``indices`` (N, 3), and the count.
        Labels are numbered in the order of first appearance in ``indices``."""
        idx = np.asarray(indices).reshape(-1, 3)
        labels = np.empty(len(idx), dtype=np.int64)
        n = _label(idx, self.grid, self.offsets, labels)
        return labels, int(n)


def label_voxels(indices: np.ndarray, dims, connectivity: int = 26) -> tuple[np.ndarray, int]:
    """One-off :class:`Labeller` call (a worker keeps a Labeller instead)."""
    return Labeller(dims, connectivity)(indices)


def component_sizes(labels: np.ndarray, n: int) -> np.ndarray:
    """Voxels per component (n,)."""
    return np.bincount(labels, minlength=n)
