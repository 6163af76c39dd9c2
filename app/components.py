"""Connected components of a voxel set (thesis §4.2.3, Eq. 4.1).

The reconstruction occupies ~1 % of the grid, so components are found on the list of
occupied voxels, never on the dense grid (DESIGN §3): a union-find over the voxels,
whose neighbours are looked up by binary search in the sorted flat ids.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["label_voxels", "component_sizes"]


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
def _label(flat, idx, dims, offsets, labels):
    n = flat.shape[0]
    parent = np.arange(n)
    for a in range(n):
        x, y, z = idx[a, 0], idx[a, 1], idx[a, 2]
        for o in range(offsets.shape[0]):
            dx, dy, dz = offsets[o, 0], offsets[o, 1], offsets[o, 2]
            nx, ny, nz = x + dx, y + dy, z + dz
            if nx < 0 or ny < 0 or nz < 0 or nx >= dims[0] or ny >= dims[1] or nz >= dims[2]:
                continue
            key = (nx * dims[1] + ny) * dims[2] + nz
            b = np.searchsorted(flat, key)
            if b < n and flat[b] == key:
                ra, rb = _find(parent, a), _find(parent, b)
                if ra != rb:
                    if ra < rb:
                        parent[rb] = ra
                    else:
                        parent[ra] = rb
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


def label_voxels(indices: np.ndarray, dims, connectivity: int = 26) -> tuple[np.ndarray, int]:
    """Component label (N,) of each voxel of ``indices`` (N, 3) and the number of components.

    Labels are numbered in the order of the voxels' flat ids (x-major, z fastest).
    """
    if connectivity not in (6, 18, 26):
        raise ValueError("connectivity must be 6, 18 or 26")
    idx = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    dims = np.asarray(dims, dtype=np.int64)
    flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    order = np.argsort(flat, kind="stable")
    labels_sorted = np.empty(len(idx), dtype=np.int64)
    n = _label(flat[order], idx[order], dims, _half_offsets(connectivity), labels_sorted)
    labels = np.empty_like(labels_sorted)
    labels[order] = labels_sorted
    return labels, int(n)


def component_sizes(labels: np.ndarray, n: int) -> np.ndarray:
    """Voxels per component (n,)."""
    return np.bincount(labels, minlength=n)
