"""The regular voxel grid of the analysed room (thesis §2.2.4) and its brick layout.

A voxel ``V`` has integer coordinates ``V_x = (i, j, k)`` and its centre at
``origin + (V_x + 0.5) * voxel_size`` (the :class:`~app.messages.Voxels` convention).
Its *flat id* is the C-order index ``(i * ny + j) * nz + k``: the order in which the
reconstruction lists occupied voxels.

Internally the reconstruction stores per-voxel tables in a *brick layout* (Caillette
et al. §6.1: a coarse grid whose cells are subdivided coarse-to-fine): the grid is cut
into cubic bricks of ``B = 2^L`` voxels a side (padded up to whole bricks) and each
brick is laid out in Morton (Z-) order, so that every cell of every level of the octree
``B, B/2, ..., 1`` is one contiguous run of positions. The *position* of a voxel is
``brick_id * B^3 + morton(i % B, j % B, k % B)`` with ``brick_id`` the C-order index of
the brick; the cell of side ``B >> l`` that contains it has id ``position >> 3 (L - l)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["VoxelGrid", "BrickLayout", "radix_sort", "keys_to_indices", "brick_position"]


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid of cubic voxels: ``dims = (nx, ny, nz)`` voxels of side ``voxel_size``
    metres from the corner ``origin`` (the room's minimum corner)."""

    origin: np.ndarray
    voxel_size: float
    dims: tuple[int, int, int]

    def __post_init__(self):
        object.__setattr__(self, "origin", np.asarray(self.origin, dtype=np.float64).reshape(3))
        object.__setattr__(self, "voxel_size", float(self.voxel_size))
        dims = tuple(int(d) for d in self.dims)
        if len(dims) != 3 or min(dims) < 1 or max(dims) > 65535:
            raise ValueError(f"voxel grid dims must be 3 integers in 1..65535, got {self.dims}")
        if not self.voxel_size > 0:
            raise ValueError(f"voxel size must be positive, got {self.voxel_size}")
        object.__setattr__(self, "dims", dims)

    @classmethod
    def from_room(cls, room_min, room_max, voxel_size: float) -> "VoxelGrid":
        """The grid covering the room ``[room_min, room_max]`` with voxels of ``voxel_size`` m.

        The number of voxels per axis is rounded up, so the grid may end up to one voxel
        past ``room_max``.
        """
        lo = np.asarray(room_min, dtype=np.float64).reshape(3)
        hi = np.asarray(room_max, dtype=np.float64).reshape(3)
        dims = np.ceil((hi - lo) / float(voxel_size) - 1e-6).astype(int)
        return cls(lo, voxel_size, tuple(np.maximum(dims, 1)))

    @property
    def n_voxels(self) -> int:
        nx, ny, nz = self.dims
        return nx * ny * nz

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.dims

    @property
    def room_max(self) -> np.ndarray:
        return self.origin + np.asarray(self.dims) * self.voxel_size

    def centres(self, indices: np.ndarray) -> np.ndarray:
        """World coordinates (N, 3) of the centres of voxels ``indices`` (N, 3)."""
        idx = np.asarray(indices).reshape(-1, 3)
        return self.origin + (idx.astype(np.float64) + 0.5) * self.voxel_size

    def index_of(self, points: np.ndarray) -> np.ndarray:
        """Integer voxel coordinates (N, 3) int64 of the voxels containing ``points``
        (may lie outside the grid: check with :meth:`contains`)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.floor((p - self.origin) / self.voxel_size).astype(np.int64)

    def contains(self, indices: np.ndarray) -> np.ndarray:
        """Boolean (N,): the integer coordinates lie inside the grid."""
        idx = np.asarray(indices).reshape(-1, 3)
        return np.all((idx >= 0) & (idx < np.asarray(self.dims)), axis=1)

    def flat(self, indices: np.ndarray) -> np.ndarray:
        """Flat ids (N,) int64 of voxels ``indices`` (N, 3): ``(i * ny + j) * nz + k``."""
        idx = np.asarray(indices).reshape(-1, 3).astype(np.int64)
        _, ny, nz = self.dims
        return (idx[:, 0] * ny + idx[:, 1]) * nz + idx[:, 2]

    def unflat(self, flat_ids: np.ndarray, dtype=np.uint16) -> np.ndarray:
        """Integer coordinates (N, 3) of flat ids (N,)."""
        f = np.asarray(flat_ids).reshape(-1).astype(np.int64)
        _, ny, nz = self.dims
        out = np.empty((f.size, 3), dtype=dtype)
        out[:, 2] = f % nz
        f = f // nz
        out[:, 1] = f % ny
        out[:, 0] = f // ny
        return out

    def dense(self, indices: np.ndarray) -> np.ndarray:
        """A dense boolean volume (nx, ny, nz) with ``indices`` set (for tests and tools;
        the per-frame pipeline never builds one)."""
        vol = np.zeros(self.dims, dtype=bool)
        idx = np.asarray(indices).reshape(-1, 3).astype(np.int64)
        vol[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        return vol

    def key(self) -> tuple:
        """A hashable description (for caches)."""
        return (tuple(np.round(self.origin, 9)), round(self.voxel_size, 9), self.dims)


def _morton_table(levels: int) -> np.ndarray:
    """(B^3, 3) uint16: local (i, j, k) of each Morton code in a brick of side ``2^levels``.

    Bit ``b`` of i, j, k goes to bits ``3b + 2``, ``3b + 1``, ``3b`` of the code, so the
    top three bits pick the octant (the first subdivision) and so on down.
    """
    n = 1 << (3 * levels)
    codes = np.arange(n)
    out = np.zeros((n, 3), dtype=np.uint16)
    for b in range(levels):
        out[:, 0] |= ((codes >> (3 * b + 2)) & 1).astype(np.uint16) << b
        out[:, 1] |= ((codes >> (3 * b + 1)) & 1).astype(np.uint16) << b
        out[:, 2] |= ((codes >> (3 * b)) & 1).astype(np.uint16) << b
    return out


class BrickLayout:
    """The brick/Morton layout of a :class:`VoxelGrid` (see the module docstring).

    ``brick`` is the side ``B = 2^levels`` of the coarsest cells (Caillette's coarse
    grid); ``n_positions = n_bricks * B^3`` includes the padding voxels past the grid.
    """

    def __init__(self, grid: VoxelGrid, brick: int = 8):
        if brick < 1 or brick & (brick - 1):
            raise ValueError(f"brick size must be a power of two, got {brick}")
        self.grid = grid
        self.brick = int(brick)
        self.levels = int(round(math.log2(brick)))
        self.brick_dims = tuple(-(-d // self.brick) for d in grid.dims)
        self.n_bricks = int(np.prod(self.brick_dims))
        self.brick_volume = self.brick ** 3
        self.n_positions = self.n_bricks * self.brick_volume
        self.morton = _morton_table(self.levels)
        self.dims_arr = np.asarray(grid.dims, dtype=np.int64)
        self.brick_dims_arr = np.asarray(self.brick_dims, dtype=np.int64)
        # sort keys: (i << shift_i) | (j << shift_j) | k over the padded grid; ordering
        # by key is ordering by flat id, and decoding is shifts and masks
        bits = [max(1, int(nb * self.brick - 1).bit_length()) for nb in self.brick_dims]
        self.key_bits = sum(bits)
        self.key_shift_j = bits[2]
        self.key_shift_i = bits[1] + bits[2]
        bi, bj, bk = np.meshgrid(*[np.arange(n, dtype=np.int64) for n in self.brick_dims], indexing="ij")
        B = self.brick
        self.brick_key = (((bi * B) << self.key_shift_i) | ((bj * B) << self.key_shift_j) | (bk * B)).ravel()
        m = self.morton.astype(np.int64)
        self.local_key = (m[:, 0] << self.key_shift_i) | (m[:, 1] << self.key_shift_j) | m[:, 2]

    def n_cells(self, level: int) -> int:
        """Cells of side ``B >> level`` (level 0: bricks; level ``levels``: voxels)."""
        return self.n_bricks << (3 * level)

    def cell_size(self, level: int) -> int:
        return self.brick >> level

    def keys_to_indices(self, keys: np.ndarray, dtype=np.uint16) -> np.ndarray:
        """Integer coordinates (N, 3) of sort keys (N,)."""
        out = np.empty((len(keys), 3), dtype=dtype)
        keys_to_indices(np.asarray(keys, dtype=np.int64), self.key_shift_i, self.key_shift_j, out)
        return out

    def positions_to_indices(self, positions: np.ndarray) -> np.ndarray:
        """Integer coordinates (N, 3) int64 of brick-layout positions (N,)."""
        out = np.empty((len(positions), 3), dtype=np.int64)
        _positions_to_ijk(np.asarray(positions, dtype=np.int64), self.levels, self.brick_dims_arr, self.morton, out)
        return out

    def indices_to_positions(self, indices: np.ndarray) -> np.ndarray:
        """Brick-layout positions (N,) int64 of integer coordinates (N, 3)."""
        idx = np.asarray(indices).reshape(-1, 3).astype(np.int64)
        B, L = self.brick, self.levels
        b = idx // B
        loc = idx % B
        brick = (b[:, 0] * self.brick_dims[1] + b[:, 1]) * self.brick_dims[2] + b[:, 2]
        code = np.zeros(len(idx), dtype=np.int64)
        for bit in range(L):
            code |= ((loc[:, 0] >> bit) & 1) << (3 * bit + 2)
            code |= ((loc[:, 1] >> bit) & 1) << (3 * bit + 1)
            code |= ((loc[:, 2] >> bit) & 1) << (3 * bit)
        return brick * (B ** 3) + code


@njit(cache=True, nogil=True)
def brick_position(i, j, k, levels, nby, nbz):
    """Brick-layout position of voxel (i, j, k) (int64): the brick's C-order id times
    ``B^3`` plus the Morton code of (i, j, k) within it (``nby``, ``nbz``: bricks along y, z)."""
    B = np.int64(1) << levels
    lmask = B - 1
    brick = ((i >> levels) * nby + (j >> levels)) * nbz + (k >> levels)
    li, lj, lk = i & lmask, j & lmask, k & lmask
    code = np.int64(0)
    for b in range(levels):
        code |= ((li >> b) & 1) << (3 * b + 2)
        code |= ((lj >> b) & 1) << (3 * b + 1)
        code |= ((lk >> b) & 1) << (3 * b)
    return (brick << (3 * levels)) + code


@njit(cache=True, nogil=True)
def _positions_to_ijk(positions, levels, brick_dims, morton, out):
    B = 1 << levels
    shift = 3 * levels
    mask = (1 << shift) - 1
    nby = brick_dims[1]
    nbz = brick_dims[2]
    for n in range(positions.shape[0]):
        p = positions[n]
        brick = p >> shift
        code = p & mask
        bk = brick % nbz
        rest = brick // nbz
        bj = rest % nby
        bi = rest // nby
        out[n, 0] = bi * B + morton[code, 0]
        out[n, 1] = bj * B + morton[code, 1]
        out[n, 2] = bk * B + morton[code, 2]


@njit(cache=True, nogil=True)
def keys_to_indices(keys, shift_i, shift_j, out):
    """Integer coordinates (N, 3) of sort keys ``(i << shift_i) | (j << shift_j) | k``."""
    mask_j = (np.int64(1) << (shift_i - shift_j)) - 1
    mask_k = (np.int64(1) << shift_j) - 1
    for n in range(keys.shape[0]):
        key = keys[n]
        out[n, 0] = key >> shift_i
        out[n, 1] = (key >> shift_j) & mask_j
        out[n, 2] = key & mask_k


@njit(cache=True, nogil=True)
def radix_sort(keys, bits, tmp):
    """Sort non-negative int64 ``keys`` of at most ``bits`` bits in place (LSD radix sort,
    digits of at most 12 bits; ``tmp`` is scratch of the same length)."""
    n = keys.shape[0]
    if n < 2 or bits <= 0:
        return
    passes = (bits + 11) // 12
    digit = (bits + passes - 1) // passes
    nb = 1 << digit
    mask = nb - 1
    count = np.empty(nb, dtype=np.int64)
    src = keys
    dst = tmp[:n]
    for p in range(passes):
        shift = p * digit
        count[:] = 0
        for m in range(n):
            count[(src[m] >> shift) & mask] += 1
        total = 0
        for b in range(nb):
            c = count[b]
            count[b] = total
            total += c
        for m in range(n):
            d = (src[m] >> shift) & mask
            dst[count[d]] = src[m]
            count[d] += 1
        src, dst = dst, src
    if passes % 2 == 1:
        keys[:] = src
