"""One person's measurement ``z_t = {V, V^S}`` (thesis §6.5.1.1) in the form the
likelihood reads: a local box around the person with the occupied voxels (a dense
uint8 grid of the box only, a few hundred thousand cells) and the surface proximity
map ``~V^S`` (Eq. 6.16: surface voxels smoothed by a Gaussian and mapped to 0..1).

The proximity map is built sparsely: a precomputed Gaussian kernel of radius
``radius`` voxels is stamped (by maximum) around every surface voxel, so the cost is
``surface voxels x kernel``; the grid is never scanned by a distance transform.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["Observation", "observe", "surface_flags", "outer_surface_flags", "SURFACES"]

#: how the surface ``V^S`` is made when the voxels come without flags: ``outer`` the
#: occupied voxels 6-adjacent to empty space reachable from outside (cavities, the holes
#: a mask leaves inside a k = 0 hull, are not surface); ``boundary`` every voxel with an
#: empty 6-neighbour (cavity borders included, the earlier behaviour)
SURFACES = ("outer", "boundary")


@njit(cache=True, nogil=True)
def _bounds(centres):
    """Per axis the least and the greatest coordinate of ``centres (N >= 1, 3)`` (numpy's
    ``min`` / ``max`` over axis 0 in one pass)."""
    lo = centres[0].copy()
    hi = centres[0].copy()
    for n in range(1, centres.shape[0]):
        for d in range(3):
            v = centres[n, d]
            if v < lo[d]:
                lo[d] = v
            if v > hi[d]:
                hi[d] = v
    return lo, hi


@njit(cache=True, nogil=True)
def _index(centres, origin, size, idx, occ):
    """``idx = floor((centres - origin) / size)`` (numpy's operations, the same cells) and
    those cells of ``occ`` set, in one pass."""
    for n in range(centres.shape[0]):
        for d in range(3):
            idx[n, d] = np.int64(np.floor((centres[n, d] - origin[d]) / size))
        occ[idx[n, 0], idx[n, 1], idx[n, 2]] = 1

@njit(cache=True, nogil=True)
def _fill(idx, surf, occ, prox, kernel, offs):
    """Marks the voxels in ``occ`` and stamps the Gaussian ``kernel`` (by maximum) around
    every surface voxel into ``prox`` (Eq. 6.16's proximity map). A voxel whose kernel
    lies inside the box (all but those near the floor) is stamped through flat offsets
    with no bounds tests (the maximum is the same in any order)."""
    for n in range(idx.shape[0]):
        i, j, k = idx[n, 0], idx[n, 1], idx[n, 2]
        occ[i, j, k] = 1
    X, Y, Z = prox.shape
    flat = prox.reshape(-1)
    r0 = r1 = r2 = 0
    for m in range(offs.shape[0]):
        r0, r1, r2 = max(r0, abs(offs[m, 0])), max(r1, abs(offs[m, 1])), max(r2, abs(offs[m, 2]))
    step = np.empty(offs.shape[0], dtype=np.int64)
    for m in range(offs.shape[0]):
        step[m] = (offs[m, 0] * Y + offs[m, 1]) * Z + offs[m, 2]
    for n in range(idx.shape[0]):
        if not surf[n]:
            continue
        i, j, k = idx[n, 0], idx[n, 1], idx[n, 2]
        if r0 <= i < X - r0 and r1 <= j < Y - r1 and r2 <= k < Z - r2:
            f = (i * Y + j) * Z + k
            for m in range(step.shape[0]):
                v = kernel[m]
                if v > flat[f + step[m]]:
                    flat[f + step[m]] = v
            continue
        for m in range(offs.shape[0]):
            a, b, c = i + offs[m, 0], j + offs[m, 1], k + offs[m, 2]
            if 0 <= a < X and 0 <= b < Y and 0 <= c < Z:
                v = kernel[m]
                if v > prox[a, b, c]:
                    prox[a, b, c] = v


@njit(cache=True, nogil=True)
def _surface(idx, occ):
    out = np.zeros(idx.shape[0], dtype=np.bool_)
    X, Y, Z = occ.shape
    for n in range(idx.shape[0]):
        i, j, k = idx[n, 0], idx[n, 1], idx[n, 2]
        if (i == 0 or j == 0 or k == 0 or i == X - 1 or j == Y - 1 or k == Z - 1 or occ[i - 1, j, k] == 0
                or occ[i + 1, j, k] == 0 or occ[i, j - 1, k] == 0 or occ[i, j + 1, k] == 0
                or occ[i, j, k - 1] == 0 or occ[i, j, k + 1] == 0):
            out[n] = True
    return out


@njit(cache=True, nogil=True)
def _outer_surface(idx, occ):
    """Occupied voxels with a 6-neighbour that is outside the box or empty and connected
    (6-neighbours, through empty cells) to the box's border: a flood fill of the empty
    cells from the border, so cavities enclosed by voxels do not count.

    Every cell outside the voxels' bounding box is empty and reaches the border in a
    straight line, so the fill runs only in that bounding box grown by one cell, seeded
    from its rim (the same cells come out as with a fill of the whole box: the person's
    box has a 0.35 m margin all round). Within it, a cell above the highest voxel of its
    column (i, j) or below the lowest (or in a column without voxels) reaches the rim
    straight up or down: exterior without a visit. The fill visits only the empty cells
    between a column's lowest and highest voxel, seeded where one of them touches such a
    column cell sideways or lies on the rim: the same exterior as a fill of every empty
    cell of the grown box (which it was), at a tenth of the cells."""
    X, Y, Z = occ.shape
    n = idx.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    if n == 0:
        return out
    lo0, lo1, lo2 = X, Y, Z
    hi0, hi1, hi2 = -1, -1, -1
    for m in range(n):
        lo0, hi0 = min(lo0, idx[m, 0]), max(hi0, idx[m, 0])
        lo1, hi1 = min(lo1, idx[m, 1]), max(hi1, idx[m, 1])
        lo2, hi2 = min(lo2, idx[m, 2]), max(hi2, idx[m, 2])
    a0, b0, c0 = max(lo0 - 1, 0), max(lo1 - 1, 0), max(lo2 - 1, 0)
    SX, SY, SZ = min(hi0 + 1, X - 1) - a0 + 1, min(hi1 + 1, Y - 1) - b0 + 1, min(hi2 + 1, Z - 1) - c0 + 1
    # cell (i, j, k) of the sub-box at (i * SY + j) * SZ + k: 0 empty (not reached), 1 occupied, 2 reached
    cell = np.zeros(SX * SY * SZ, dtype=np.uint8)
    kmin = np.full(SX * SY, SZ, dtype=np.int64)    # per column, the lowest and highest voxel
    kmax = np.full(SX * SY, -1, dtype=np.int64)
    for m in range(n):
        i, j, k = idx[m, 0] - a0, idx[m, 1] - b0, idx[m, 2] - c0
        q = i * SY + j
        cell[q * SZ + k] = 1
        kmin[q] = min(kmin[q], k)
        kmax[q] = max(kmax[q], k)
    stack = np.empty(SX * SY * SZ, dtype=np.int64)
    top = 0
    # seeds: empty cells between a column's lowest and highest voxel on the rim, or beside
    # a cell of a neighbouring column that is above, below or without voxels
    for i in range(SX):
        for j in range(SY):
            q = i * SY + j
            rim = i == 0 or j == 0 or i == SX - 1 or j == SY - 1
            for k in range(kmin[q] + 1, kmax[q]):
                f = q * SZ + k
                if cell[f] != 0:
                    continue
                seed = rim
                if not seed:
                    for p in (q - SY, q + SY, q - 1, q + 1):   # rim columns aside, all inside
                        if k < kmin[p] or k > kmax[p]:
                            seed = True
                            break
                if seed:
                    cell[f] = 2
                    stack[top] = f
                    top += 1
    while top > 0:
        top -= 1
        f = stack[top]
        k = f % SZ
        q = f // SZ
        i = q // SY
        j = q - i * SY
        if cell[f - 1] == 0:   # k - 1 >= kmin: its column's lowest voxel stops the walk
            cell[f - 1] = 2
            stack[top] = f - 1
            top += 1
        if cell[f + 1] == 0:
            cell[f + 1] = 2
            stack[top] = f + 1
            top += 1
        for d in range(4):
            if d == 0:
                if i == 0:
                    continue
                p = q - SY
            elif d == 1:
                if i == SX - 1:
                    continue
                p = q + SY
            elif d == 2:
                if j == 0:
                    continue
                p = q - 1
            else:
                if j == SY - 1:
                    continue
                p = q + 1
            g = p * SZ + k
            if cell[g] == 0 and kmin[p] < k < kmax[p]:
                cell[g] = 2
                stack[top] = g
                top += 1
    for m in range(n):
        i, j, k = idx[m, 0], idx[m, 1], idx[m, 2]
        if i == 0 or j == 0 or k == 0 or i == X - 1 or j == Y - 1 or k == Z - 1:
            out[m] = True   # on the box's border
            continue
        i, j, k = i - a0, j - b0, k - c0   # inside the sub-box with a cell all round
        q = i * SY + j
        for p, kk in ((q - SY, k), (q + SY, k), (q - 1, k), (q + 1, k), (q, k - 1), (q, k + 1)):
            c = cell[p * SZ + kk]
            if c == 2 or (c == 0 and (kk < kmin[p] or kk > kmax[p])):
                out[m] = True
                break
    return out


def outer_surface_flags(idx_local: np.ndarray, occ: np.ndarray) -> np.ndarray:
    """Surface voxels of voxels already marked in ``occ`` whose empty 6-neighbour is
    reachable from the box's border (enclosed cavities are not surface)."""
    return _outer_surface(idx_local, occ)


def surface_flags(idx_local: np.ndarray, occ: np.ndarray) -> np.ndarray:
    """Surface voxels (a 6-neighbour is empty) of voxels already marked in ``occ``."""
    return _surface(idx_local, occ)


@dataclass
class Observation:
    """A person's local box: ``origin`` (world, the corner of cell 0), ``voxel_size``,
    ``occ`` (X, Y, Z) uint8 and ``prox`` (X, Y, Z) float32, the voxel centres and
    surface flags, and the room bounds (Eq. 6.13 counts model voxels outside them)."""

    origin: np.ndarray
    voxel_size: float
    occ: np.ndarray
    prox: np.ndarray
    centres: np.ndarray
    surface: np.ndarray
    room_lo: np.ndarray
    room_hi: np.ndarray

    @property
    def count(self) -> int:
        return len(self.centres)


_KERNELS: dict = {}


def _kernel(radius: int, sigma: float):
    key = (radius, sigma)
    if key not in _KERNELS:
        r = np.arange(-radius, radius + 1)
        offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
        d2 = (offs ** 2).sum(axis=1)
        keep = d2 <= radius * radius
        offs, d2 = offs[keep], d2[keep]
        _KERNELS[key] = (np.ascontiguousarray(offs.astype(np.int64)), np.exp(-0.5 * d2 / sigma ** 2).astype(np.float32))
    return _KERNELS[key]


def observe(centres: np.ndarray, voxel_size: float, room_lo, room_hi, surface=None, margin: float = 0.35,
            radius: int = 2, sigma: float = 1.0, mode: str = "outer") -> Observation:
    """The observation of one person from the world centres ``(N, 3)`` of their voxels.

    ``surface`` (N,) bool is the reconstruction's surface flag ``V^S`` (computed here
    here when None or empty: ``mode`` ``outer`` or ``boundary``, see :data:`SURFACES`;
    the thesis's ``V^S`` is the voxels some camera sees, which ``outer`` approximates
    better on a hull with holes). ``radius`` and ``sigma`` (in voxels) shape the
    Gaussian of the proximity map.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    room_lo, room_hi = np.asarray(room_lo, float), np.asarray(room_hi, float)
    s = float(voxel_size)
    if len(centres):
        lo, hi = _bounds(centres)
        lo, hi = lo - margin, hi + margin
    else:
        lo, hi = room_lo, room_lo + 2 * s
    lo[2] = min(lo[2], room_lo[2])
    origin = np.floor(lo / s) * s
    dims = np.maximum(np.ceil((hi - origin) / s).astype(np.int64) + 1, 1)
    occ = np.zeros(tuple(dims), dtype=np.uint8)
    prox = np.zeros(tuple(dims), dtype=np.float32)
    idx = np.empty((len(centres), 3), dtype=np.int64)
    _index(centres, origin, s, idx, occ)   # (and marks occ)
    if surface is None or len(surface) != len(centres):
        surface = _outer_surface(idx, occ) if mode == "outer" else _surface(idx, occ)
    offs, kern = _kernel(int(radius), float(sigma))
    _fill(idx, np.asarray(surface, dtype=np.bool_), occ, prox, kern, offs)
    return Observation(origin=origin, voxel_size=s, occ=occ, prox=prox, centres=centres,
                       surface=np.asarray(surface, dtype=bool), room_lo=room_lo, room_hi=room_hi)
