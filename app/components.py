"""Connected components of a voxel set (thesis §4.2.3, Eq. 4.1).

The reconstruction occupies a few % of the grid, so components are found over the
list of occupied voxels, never by a scan of the dense grid (DESIGN §3).

The list comes sorted by grid (x, y, z), as the reconstruction publishes it, so the
voxels of one (x, y) column are consecutive and split into *runs* of consecutive z.
Two runs of neighbouring columns are 26-connected when their z intervals, widened by
one voxel, overlap (6: face columns, strict overlap; 18: face columns widened,
diagonal columns strict); runs of one column never touch. A union-find over the runs
(~10x fewer than voxels on a body-shaped hull) labels the voxels in one pass over the
list and one over the runs: a frame costs O(occupied voxels) with a small constant,
whatever the grid size. An unsorted list is sorted first (``argsort``, slower). The
per-voxel union-find of the first version (:func:`label_voxels_union_find`) stays
as the reference the tests compare against.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["Labeller", "label_voxels", "label_voxels_union_find", "component_sizes", "is_sorted", "voxel_runs",
           "label_runs"]


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
def _union(parent, a, b):
    ra, rb = _find(parent, a), _find(parent, b)
    if ra != rb:
        if ra < rb:
            parent[rb] = ra
        else:
            parent[ra] = rb


@njit(cache=True, nogil=True)
def _is_sorted(idx, ny, nz):
    """Whether the list is strictly increasing in the linear index (x, y, z)."""
    prev = -1
    for a in range(idx.shape[0]):
        key = (np.int64(idx[a, 0]) * ny + idx[a, 1]) * nz + idx[a, 2]
        if key <= prev:
            return False
        prev = key
    return True


@njit(cache=True, nogil=True)
def voxel_runs(idx, ny, nz, run_start, run_z0, run_z1, run_col):
    """Split a list sorted by (x, y, z) into runs of consecutive z in one (x, y) column:
    run ``r`` holds list positions ``run_start[r] .. run_start[r + 1]``, z from
    ``run_z0[r]`` to ``run_z1[r]``, column ``run_col[r] = x * ny + y`` (arrays of
    N + 1 / N entries). Returns the number of runs, -1 when the list is not strictly
    sorted."""
    n = idx.shape[0]
    m = 0
    prev = -1
    for a in range(n):
        col = np.int64(idx[a, 0]) * ny + idx[a, 1]
        z = np.int64(idx[a, 2])
        key = col * nz + z
        if key <= prev:
            return -1
        prev = key
        if m > 0 and run_col[m - 1] == col and run_z1[m - 1] == z - 1:
            run_z1[m - 1] = z
        else:
            run_start[m] = a
            run_z0[m] = z
            run_z1[m] = z
            run_col[m] = col
            m += 1
    run_start[m] = n
    return m


@njit(cache=True, nogil=True)
def label_runs(run_z0, run_z1, run_col, m, ny, connectivity, col_first, run_label):
    """Connected components of runs ``0 .. m`` (sorted by column, then z): two runs of
    neighbouring columns touch when their z intervals, widened by one voxel for the
    neighbours the connectivity allows across an edge, overlap. ``col_first`` (nx * ny)
    is scratch filled with -1 (left so). ``run_label`` gets labels numbered in run
    order; returns their count."""
    # first run of each column (runs of a column are consecutive and sorted by z)
    for r in range(m - 1, -1, -1):
        col_first[run_col[r]] = r
    parent = np.arange(m)
    # the half of the neighbour columns that come earlier in the list
    dxs = (-1, -1, -1, 0)
    dys = (-1, 0, 1, -1)
    for r in range(m):
        col = run_col[r]
        x = col // ny
        y = col - x * ny
        for o in range(4):
            diagonal = dxs[o] != 0 and dys[o] != 0
            if connectivity == 6 and diagonal:
                continue
            widen = 0 if (connectivity == 6 or (connectivity == 18 and diagonal)) else 1
            qx, qy = x + dxs[o], y + dys[o]
            if qx < 0 or qy < 0 or qy >= ny:
                continue
            q = col_first[qx * ny + qy]
            if q < 0:
                continue
            qcol = run_col[q]
            while q < m and run_col[q] == qcol:
                if run_z0[q] > run_z1[r] + widen:
                    break
                if run_z1[q] + widen >= run_z0[r]:
                    _union(parent, r, q)
                q += 1
    for r in range(m):
        col_first[run_col[r]] = -1
    remap = -np.ones(m, dtype=np.int64)
    count = 0
    for r in range(m):
        root = _find(parent, r)
        if remap[root] < 0:
            remap[root] = count
            count += 1
        run_label[r] = remap[root]
    return count


@njit(cache=True, nogil=True)
def _label_runs(idx, nx, ny, nz, connectivity, col_first, labels):
    """Run-based labelling of a list sorted by (x, y, z) (see the module docstring).
    Labels in the order of first appearance. Returns ``(count, runs, run_start,
    run_z0, run_z1, run_col, run_label)``; count -1 when the list is not strictly
    sorted."""
    n = idx.shape[0]
    run_start = np.empty(n + 1, dtype=np.int64)
    run_z0 = np.empty(n, dtype=np.int64)
    run_z1 = np.empty(n, dtype=np.int64)
    run_col = np.empty(n, dtype=np.int64)
    run_label = np.empty(n, dtype=np.int64)
    m = voxel_runs(idx, ny, nz, run_start, run_z0, run_z1, run_col)
    if m < 0:
        return -1, 0, run_start, run_z0, run_z1, run_col, run_label
    count = label_runs(run_z0, run_z1, run_col, m, ny, connectivity, col_first, run_label)
    for r in range(m):
        lab = run_label[r]
        for a in range(run_start[r], run_start[r + 1]):
            labels[a] = lab
    return count, m, run_start, run_z0, run_z1, run_col, run_label


@njit(cache=True, nogil=True)
def _relabel_first_appearance(labels, count):
    """Renumber labels in the order of their first appearance in ``labels``."""
    remap = -np.ones(count, dtype=np.int64)
    k = 0
    for a in range(labels.shape[0]):
        c = labels[a]
        if remap[c] < 0:
            remap[c] = k
            k += 1
        labels[a] = remap[c]


@njit(cache=True, nogil=True)
def _label(idx, grid, offsets, labels):
    """The per-voxel union-find over an index grid (the first version, the reference)."""
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
                _union(parent, a, b)
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


def is_sorted(indices: np.ndarray, dims) -> bool:
    """Whether ``indices`` (N, 3) is strictly increasing in grid (x, y, z) order."""
    idx = np.asarray(indices).reshape(-1, 3)
    return bool(_is_sorted(idx, int(dims[1]), int(dims[2])))


class Labeller:
    """Connected components of voxel lists on one grid (keeps a column table of
    8 bytes per grid column between frames)."""

    def __init__(self, dims, connectivity: int = 26):
        if connectivity not in (6, 18, 26):
            raise ValueError("connectivity must be 6, 18 or 26")
        self.dims = tuple(int(d) for d in dims)
        self.connectivity = int(connectivity)
        self.col_first = np.full(self.dims[0] * self.dims[1], -1, dtype=np.int64)
        #: the runs of the last sorted list labelled: (start (R+1), z0, z1, column, label)
        self.runs = None

    def __call__(self, indices: np.ndarray) -> tuple[np.ndarray, int]:
        """Component label (N,) of each voxel of ``indices`` (N, 3), and the count.
        Labels are numbered in the order of first appearance in ``indices``."""
        idx = np.asarray(indices).reshape(-1, 3)
        labels = np.empty(len(idx), dtype=np.int64)
        nx, ny, nz = self.dims
        n, m, start, z0, z1, col, run_label = _label_runs(idx, nx, ny, nz, self.connectivity, self.col_first, labels)
        if n >= 0:
            self.runs = (start[:m + 1], z0[:m], z1[:m], col[:m], run_label[:m])
            return labels, int(n)
        self.runs = None
        # unsorted (or a voxel listed twice): label the sorted distinct voxels, map back
        key = (idx[:, 0].astype(np.int64) * ny + idx[:, 1]) * nz + idx[:, 2]
        uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        ulabels = np.empty(len(uniq), dtype=np.int64)
        n = _label_runs(np.ascontiguousarray(idx[first]), nx, ny, nz, self.connectivity, self.col_first, ulabels)[0]
        labels[:] = ulabels[inverse.reshape(-1)]
        _relabel_first_appearance(labels, n)
        return labels, int(n)


def label_voxels(indices: np.ndarray, dims, connectivity: int = 26) -> tuple[np.ndarray, int]:
    """One-off :class:`Labeller` call (a worker keeps a Labeller instead)."""
    return Labeller(dims, connectivity)(indices)


def label_voxels_union_find(indices: np.ndarray, dims, connectivity: int = 26) -> tuple[np.ndarray, int]:
    """The per-voxel union-find over a dense index grid (the first version; kept as the
    reference of the tests and for comparison in timings)."""
    idx = np.asarray(indices).reshape(-1, 3)
    grid = np.full(tuple(int(d) for d in dims), -1, dtype=np.int32)
    labels = np.empty(len(idx), dtype=np.int64)
    n = _label(idx, grid, _half_offsets(connectivity), labels)
    return labels, int(n)


def component_sizes(labels: np.ndarray, n: int) -> np.ndarray:
    """Voxels per component (n,)."""
    return np.bincount(labels, minlength=n)
