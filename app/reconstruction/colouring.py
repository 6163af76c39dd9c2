"""Voxel colouring with visibility and the surface set ``V^S`` (thesis §2.2.4).

The colour of a voxel is the mean of the colours found at the projection of its centre
in the cameras that have *direct vision* of it; the voxels seen by at least one camera
form the surface set ``V^S`` (the ``surface`` flag), the others are interior. Three
methods, selected by name:

* ``"naive"``: the thesis's first approach, the mean over every camera whose image
  contains the projection, visibility ignored (biased: a camera looking at a person's
  back colours the front voxels too). Every occupied voxel is coloured; no surface set.
* ``"raymarch"``: the thesis's reference. The segment from the voxel centre to the
  camera's optical centre is walked through the grid (a 3D DDA, Amanatides & Woo, which
  visits every voxel the segment crosses: the 6-connected form of the thesis's 3D
  Bresenham line), and the camera has direct vision when none of the voxels met, the
  voxel itself excluded, is occupied (voxels outside the grid are empty).
* ``"visibility"`` (the fast one, the default): a depth buffer per camera for the far
  part of the line of sight, the ray march for its near part. Each voxel that can be
  seen by the camera splats its camera depth over its projected footprint, a square of
  half-side ``splat * f * s / (2 z)`` pixels at the colour image's resolution; a voxel
  has direct vision of the camera when its depth is within ``depth_tolerance`` voxel
  sides of the nearest depth at its centre pixel (nothing far in front of it) *and*
  the first ``march`` voxels of its line of sight are empty (the steps of the voxel
  surface next to it, which a depth buffer at pixel resolution cannot resolve). Two
  passes over those voxels per camera, plus a short march for the ones that pass the
  depth test. With the defaults (3 voxels, 6 steps) it takes the ray march's decision
  for 99.7-99.8 % of the (boundary voxel, camera) pairs of the test scenes and finds a
  surface set 97.6-98.7 % alike (Jaccard), where a pure depth buffer (``march=0``,
  tolerance 1 voxel) takes it for 94-96 % and finds a surface set only 70-89 % alike.

Only voxels with an *exposed face towards the camera* (a face whose 6-neighbour is
empty and whose plane the optical centre lies in front of) can be seen: a line of sight
leaves its voxel through a face that looks towards the camera, and the first occupied
voxel on a pixel's ray is entered through one. So both visibility methods look only at
the geometric boundary (occupied voxels with an empty 6-neighbour) and, per camera,
only at its voxels with a camera-facing exposed face; for the ray march this changes
nothing, for the depth buffer it removes the back of the body from the buffer.

Visibility is geometric and evaluated for every calibrated camera, so ``V^S`` does not
change when a camera's image is missing; the colour averages the visible cameras that
have an image this frame and whose mask calls the voxel's pixel foreground (with a
tolerance ``k > 0`` a voxel may be occupied although a camera sees background there: its
colour would be the background's). Interior voxels, and surface voxels with no such
camera, get colour (0, 0, 0): as in the thesis, only ``V^C = V^S`` is coloured. With no
image at all the colours are empty. Images are BGR (OpenCV), colours RGB uint8.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

from calibration.camera import Camera

from .grid import VoxelGrid
from .projection import camera_params, project

__all__ = ["VoxelColourer", "COLOURINGS", "boundary_voxels"]

COLOURINGS = ("none", "naive", "visibility", "raymarch")


# -- occupancy of the current frame -----------------------------------------------
@njit(cache=True, nogil=True)
def _mark(indices, occ, sy, sx, value):
    """Set ``occ`` (dense, padded by one voxel on every side) at ``indices`` to ``value``."""
    for n in range(indices.shape[0]):
        i = np.int64(indices[n, 0]) + 1
        occ[i * sx + (np.int64(indices[n, 1]) + 1) * sy + np.int64(indices[n, 2]) + 1] = value


@njit(cache=True, nogil=True)
def _exposed_faces(indices, occ, sy, sx, out):
    """Bits of the faces of each voxel whose 6-neighbour is empty (bit 0: -x, 1: +x,
    2: -y, 3: +y, 4: -z, 5: +z); returns how many voxels have one (the boundary)."""
    n_out = 0
    for n in range(indices.shape[0]):
        p = (np.int64(indices[n, 0]) + 1) * sx + (np.int64(indices[n, 1]) + 1) * sy + np.int64(indices[n, 2]) + 1
        f = ((occ[p - sx] == 0) | ((occ[p + sx] == 0) << 1) | ((occ[p - sy] == 0) << 2)
             | ((occ[p + sy] == 0) << 3) | ((occ[p - 1] == 0) << 4) | ((occ[p + 1] == 0) << 5))
        out[n] = f
        n_out += f != 0
    return n_out


@njit(cache=True, nogil=True)
def _boundary(indices, occ, sy, sx, rows, sub, faces):
    """The boundary voxels (with an empty 6-neighbour): their rows in ``indices``, their
    coordinates and exposed-face bits (see :func:`_exposed_faces`); returns how many."""
    n_out = 0
    for n in range(indices.shape[0]):
        p = (np.int64(indices[n, 0]) + 1) * sx + (np.int64(indices[n, 1]) + 1) * sy + np.int64(indices[n, 2]) + 1
        f = ((occ[p - sx] == 0) | ((occ[p + sx] == 0) << 1) | ((occ[p - sy] == 0) << 2)
             | ((occ[p + sy] == 0) << 3) | ((occ[p - 1] == 0) << 4) | ((occ[p + 1] == 0) << 5))
        if f:
            rows[n_out] = n
            sub[n_out, 0] = indices[n, 0]
            sub[n_out, 1] = indices[n, 1]
            sub[n_out, 2] = indices[n, 2]
            faces[n_out] = f
            n_out += 1
    return n_out


@njit(cache=True, nogil=True, inline="always")
def _facing(faces, X, Y, Z, half, centre):
    """Whether one of the exposed ``faces`` of the voxel centred at (X, Y, Z) looks
    towards the optical ``centre``."""
    f = 0
    if centre[0] < X - half:
        f |= 1
    elif centre[0] > X + half:
        f |= 2
    if centre[1] < Y - half:
        f |= 4
    elif centre[1] > Y + half:
        f |= 8
    if centre[2] < Z - half:
        f |= 16
    elif centre[2] > Z + half:
        f |= 32
    return (faces & f) != 0


class _Occupancy:
    """A dense uint8 volume with a one-voxel empty border, set and cleared per frame
    only where voxels are occupied (O(N), never a scan of the grid)."""

    def __init__(self, grid: VoxelGrid):
        nx, ny, nz = grid.dims
        self.sy = nz + 2
        self.sx = (ny + 2) * (nz + 2)
        self.data = np.zeros((nx + 2) * self.sx, dtype=np.uint8)
        self.data.fill(0)            # touch the pages now, not during the first frames

    def mark(self, indices):
        _mark(indices, self.data, self.sy, self.sx, 1)

    def clear(self, indices):
        _mark(indices, self.data, self.sy, self.sx, 0)

    def faces(self, indices) -> np.ndarray:
        out = np.empty(len(indices), dtype=np.uint8)
        _exposed_faces(indices, self.data, self.sy, self.sx, out)
        return out


def boundary_voxels(grid: VoxelGrid, indices: np.ndarray) -> np.ndarray:
    """Boolean (N,): the voxels of ``indices`` with an empty 6-neighbour (a superset of ``V^S``)."""
    occ = _Occupancy(grid)
    idx = np.ascontiguousarray(indices)
    occ.mark(idx)
    return occ.faces(idx) != 0


# -- visibility ---------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _project_pixels(indices, origin, s, P, out):
    """Pixel index (v * w + u) of each voxel centre, -1 when the camera does not see it."""
    w = int(P[23])
    for n in range(indices.shape[0]):
        X = origin[0] + (indices[n, 0] + 0.5) * s
        Y = origin[1] + (indices[n, 1] + 0.5) * s
        Z = origin[2] + (indices[n, 2] + 0.5) * s
        u, v, z, seen = project(P, X, Y, Z)
        if seen:
            out[n] = int(np.floor(v + 0.5)) * w + int(np.floor(u + 0.5))
        else:
            out[n] = -1


@njit(cache=True, nogil=True)
def _zbuffer_visibility(indices, faces, origin, s, P, centre, zbuf, splat, depth_tolerance,
                        occ, sy, sx, dims, march, out):
    """Depth-buffer visibility of boundary voxels ``indices`` (exposed ``faces``) in
    camera ``P`` (optical centre ``centre``), written to ``out``: the centre pixel index
    of the visible voxels, -1 for the others.

    Pass 1 splats the depth of each voxel with a face towards the camera over its
    footprint (min). Pass 2 keeps those whose depth is within ``depth_tolerance * s`` of
    the buffer at their centre pixel and, with ``march > 0``, whose line of sight is
    free over its first ``march`` voxels (the exact ray march of the near part, where
    the depth buffer cannot resolve the steps of the voxel surface).
    """
    w = int(P[23])
    h = int(P[24])
    n = indices.shape[0]
    nx, ny, nz = dims[0], dims[1], dims[2]
    tx = (centre[0] - origin[0]) / s
    ty = (centre[1] - origin[1]) / s
    tz = (centre[2] - origin[2]) / s
    zbuf[:] = np.inf
    cand = np.empty(n, dtype=np.int64)
    pq = np.empty(n, dtype=np.int64)
    pz = np.empty(n, dtype=np.float32)
    half_u = 0.5 * splat * s * P[12]
    half_v = 0.5 * splat * s * P[15]
    half = 0.5 * s
    m_cand = 0
    for m in range(n):
        out[m] = -1
        X = origin[0] + (indices[m, 0] + 0.5) * s
        Y = origin[1] + (indices[m, 1] + 0.5) * s
        Z = origin[2] + (indices[m, 2] + 0.5) * s
        if not _facing(faces[m], X, Y, Z, half, centre):
            continue
        u, v, z, seen = project(P, X, Y, Z)
        if not seen:
            # outside the image (its footprint may still cover the border: ignored)
            continue
        inv = 1.0 / z
        hu = half_u * inv
        hv = half_v * inv
        x0 = max(int(np.floor(u - hu + 0.5)), 0)
        x1 = min(int(np.floor(u + hu + 0.5)), w - 1)
        y0 = max(int(np.floor(v - hv + 0.5)), 0)
        y1 = min(int(np.floor(v + hv + 0.5)), h - 1)
        zf = np.float32(z)
        for y in range(y0, y1 + 1):
            row = y * w
            for x in range(x0, x1 + 1):
                zbuf[row + x] = min(zbuf[row + x], zf)
        cand[m_cand] = m
        pq[m_cand] = int(np.floor(v + 0.5)) * w + int(np.floor(u + 0.5))
        pz[m_cand] = zf
        m_cand += 1
    tol = np.float32(depth_tolerance * s)
    for a in range(m_cand):
        q = pq[a]
        if pz[a] <= zbuf[q] + tol:
            m = cand[a]
            if march > 0 and not _line_clear(np.int64(indices[m, 0]), np.int64(indices[m, 1]),
                                             np.int64(indices[m, 2]), tx, ty, tz, occ, sy, sx, nx, ny, nz, march):
                continue
            out[m] = q


@njit(cache=True, nogil=True, inline="always")
def _line_clear(i, j, k, tx, ty, tz, occ, sy, sx, nx, ny, nz, max_steps):
    """3D DDA (Amanatides & Woo) from the centre of voxel (i, j, k) towards the grid point
    (tx, ty, tz) (in voxel units): False when it meets an occupied voxel within
    ``max_steps`` voxels (the voxel itself excluded), True when it reaches the point or
    leaves the grid first, or after ``max_steps`` free voxels."""
    dx = tx - (i + 0.5)
    dy = ty - (j + 0.5)
    dz = tz - (k + 0.5)
    sxs = 1 if dx > 0 else -1
    sys_ = 1 if dy > 0 else -1
    szs = 1 if dz > 0 else -1
    ddx = 1.0 / abs(dx) if dx != 0 else np.inf
    ddy = 1.0 / abs(dy) if dy != 0 else np.inf
    ddz = 1.0 / abs(dz) if dz != 0 else np.inf
    mx = 0.5 * ddx
    my = 0.5 * ddy
    mz = 0.5 * ddz
    for _ in range(max_steps):
        if mx <= my and mx <= mz:
            if mx > 1.0:
                return True
            i += sxs
            mx += ddx
        elif my <= mz:
            if my > 1.0:
                return True
            j += sys_
            my += ddy
        else:
            if mz > 1.0:
                return True
            k += szs
            mz += ddz
        if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
            return True
        if occ[(i + 1) * sx + (j + 1) * sy + k + 1]:
            return False
    return True


@njit(cache=True, nogil=True)
def _raymarch_visibility(indices, faces, occ, sy, sx, dims, origin, s, P, centre, out):
    """Line-of-sight visibility (3D DDA from the voxel centre to the optical centre
    through the occupied set ``occ``, the whole way), written to ``out`` as in
    :func:`_zbuffer_visibility`. ``faces`` may be all 63 (no culling)."""
    w = int(P[23])
    nx, ny, nz = dims[0], dims[1], dims[2]
    tx = (centre[0] - origin[0]) / s
    ty = (centre[1] - origin[1]) / s
    tz = (centre[2] - origin[2]) / s
    half = 0.5 * s
    steps = nx + ny + nz + 3
    for m in range(indices.shape[0]):
        out[m] = -1
        i = np.int64(indices[m, 0])
        j = np.int64(indices[m, 1])
        k = np.int64(indices[m, 2])
        X = origin[0] + (i + 0.5) * s
        Y = origin[1] + (j + 0.5) * s
        Z = origin[2] + (k + 0.5) * s
        if not _facing(faces[m], X, Y, Z, half, centre):
            continue
        u, v, z, seen = project(P, X, Y, Z)
        if not seen:
            continue
        if _line_clear(i, j, k, tx, ty, tz, occ, sy, sx, nx, ny, nz, steps):
            out[m] = int(np.floor(v + 0.5)) * w + int(np.floor(u + 0.5))


# -- colours ------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _accumulate(pixels, image, width, height, mask, mask_width, mask_height, sums, counts):
    """Add the BGR colour of ``image`` (height * width, 3) at ``pixels`` (-1: skip)
    to ``sums``, unless the camera's ``mask`` (flat, ``mask_width`` x ``mask_height``;
    empty: no mask) calls that pixel background (pixel centres scaled to the mask)."""
    use_mask = mask.shape[0] > 0
    for m in range(pixels.shape[0]):
        q = pixels[m]
        if q < 0:
            continue
        if use_mask:
            v = q // width
            u = q - v * width
            mv = ((2 * v + 1) * mask_height) // (2 * height)
            mu = ((2 * u + 1) * mask_width) // (2 * width)
            if not mask[mv * mask_width + mu]:
                continue
        sums[m, 0] += image[q, 0]
        sums[m, 1] += image[q, 1]
        sums[m, 2] += image[q, 2]
        counts[m] += 1


@njit(cache=True, nogil=True)
def _finish(pixels, sums, counts, rows, colours, surface):
    """``surface[rows[m]]``: some camera sees voxel m (``pixels`` (C, n)); ``colours[rows[m]]``
    the rounded mean of its BGR ``sums`` as RGB (``surface``, ``colours`` may be empty)."""
    for m in range(pixels.shape[1]):
        r = rows[m]
        if surface.shape[0] > 0:
            seen = False
            for c in range(pixels.shape[0]):
                if pixels[c, m] >= 0:
                    seen = True
            surface[r] = seen
        if sums.shape[0] == 0:
            continue
        k = counts[m]
        if k > 0:
            colours[r, 0] = (sums[m, 2] + k // 2) // k
            colours[r, 1] = (sums[m, 1] + k // 2) // k
            colours[r, 2] = (sums[m, 0] + k // 2) // k


_NO_MASK = np.zeros(0, dtype=np.uint8)


class VoxelColourer:
    """Colours and surface flag of the occupied voxels of a frame (see the module docstring).

    ``cameras`` are the calibrated cameras at the resolution of the colour images
    (:meth:`Camera.scaled`); ``splat``, ``depth_tolerance`` and ``march`` tune the depth
    buffer (``"visibility"``); ``threads > 1`` computes the cameras' visibility on that
    many threads (default 1: see DESIGN §3 on sharing two cores).
    """

    def __init__(self, grid: VoxelGrid, cameras: list[Camera], method: str = "visibility",
                 splat: float = 1.0, depth_tolerance: float = 3.0, march: int = 6, threads: int = 1):
        if method not in COLOURINGS:
            raise ValueError(f"colouring must be one of {', '.join(COLOURINGS)}, got {method!r}")
        self.grid = grid
        self.cameras = list(cameras)
        self.method = method
        self.splat = float(splat)
        self.depth_tolerance = float(depth_tolerance)
        self.march = int(march)
        self.threads = int(threads)
        self._pool = None
        self.params = [camera_params(c) for c in self.cameras]
        self.centres = [np.asarray(c.centre, dtype=np.float64) for c in self.cameras]
        self.sizes = [(c.width, c.height) for c in self.cameras]
        self.zbufs = [np.empty(w * h, dtype=np.float32) for w, h in self.sizes]
        self.dims = np.asarray(grid.dims, dtype=np.int64)
        self._occ = _Occupancy(grid) if method in ("visibility", "raymarch") else None

    def check_image(self, c: int, image) -> np.ndarray | None:
        if image is None:
            return None
        w, h = self.sizes[c]
        if image.shape != (h, w, 3) or image.dtype != np.uint8:
            raise ValueError(f"camera {self.cameras[c].name}: colour image must be {h}x{w}x3 uint8 (BGR), "
                             f"got {'x'.join(map(str, image.shape))} {image.dtype}")
        return np.ascontiguousarray(image).reshape(h * w, 3)

    def _visibility(self, idx: np.ndarray, method: str, cull: bool = True):
        """(rows, pixels): the boundary voxels (rows of ``idx``) and, per camera (C, n), the
        pixel of those visible from it (-1 elsewhere); ``naive``: all voxels, every
        camera that sees the projection."""
        C = len(self.cameras)
        g = self.grid
        if method == "naive":
            rows = np.arange(len(idx), dtype=np.int64)
            pix = np.empty((C, len(idx)), dtype=np.int32)
            self._per_camera(lambda c: _project_pixels(idx, g.origin, g.voxel_size, self.params[c], pix[c]))
            return rows, pix
        occ = self._occ or _Occupancy(g)
        occ.mark(idx)
        try:
            if cull:
                rows = np.empty(len(idx), dtype=np.int64)
                sub = np.empty_like(idx)
                fsub = np.empty(len(idx), dtype=np.uint8)
                nb = _boundary(idx, occ.data, occ.sy, occ.sx, rows, sub, fsub)
                rows, sub, fsub = rows[:nb], sub[:nb], fsub[:nb]
            else:
                rows = np.arange(len(idx), dtype=np.int64)
                sub = idx
                fsub = np.full(len(idx), 63, dtype=np.uint8)
            pix = np.empty((C, len(rows)), dtype=np.int32)
            if method == "raymarch":
                def one(c):
                    _raymarch_visibility(sub, fsub, occ.data, occ.sy, occ.sx, self.dims, g.origin, g.voxel_size,
                                         self.params[c], self.centres[c], pix[c])
            else:
                def one(c):
                    _zbuffer_visibility(sub, fsub, g.origin, g.voxel_size, self.params[c], self.centres[c],
                                        self.zbufs[c], self.splat, self.depth_tolerance, occ.data, occ.sy, occ.sx,
                                        self.dims, self.march, pix[c])
            self._per_camera(one)
        finally:
            occ.clear(idx)
        return rows, pix

    def _per_camera(self, fn) -> None:
        """Run ``fn(c)`` for every camera, on ``threads`` threads (the kernels release the GIL)."""
        if self.threads <= 1:
            for c in range(len(self.cameras)):
                fn(c)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="visibility")
        list(self._pool.map(fn, range(len(self.cameras))))

    def visible_pixels(self, indices: np.ndarray, method: str | None = None, cull: bool = True) -> np.ndarray:
        """(N, C) int32: the centre pixel of each voxel in each camera it is visible from
        (``naive``: every camera that sees its projection), -1 elsewhere. With ``cull``
        off the ray march also walks from interior voxels and back faces (for tests)."""
        idx = np.ascontiguousarray(indices)
        rows, pix = self._visibility(idx, method or self.method, cull)
        out = np.full((len(idx), len(self.cameras)), -1, dtype=np.int32)
        out[rows] = pix.T
        return out

    def colour(self, indices: np.ndarray, images: list,
               masks: list | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
        """Colours (N, 3) RGB uint8 and surface flags (N,) bool of voxels ``indices``.

        ``images`` lists, per camera, a BGR image at the colour resolution or ``None``;
        ``masks`` (optional) the foreground masks (any resolution) or ``None``: a camera
        whose mask calls the voxel's pixel background does not lend it its colour (with a
        shape-from-silhouette tolerance ``k > 0`` a voxel may be occupied although one
        camera sees background there, and that camera would otherwise paint it with the
        background colour).
        Returns ``(colours, surface, timings_ms)``; ``surface`` is empty for ``naive``,
        ``colours`` when no camera has an image, both for ``none``. Timings: ``surface``
        (occupancy, boundary, visibility), ``colour`` (sampling and means).
        """
        n = len(indices)
        if self.method == "none":
            return np.empty((0, 3), np.uint8), np.empty(0, bool), {}
        idx = np.ascontiguousarray(indices)
        imgs = [self.check_image(c, im) for c, im in enumerate(images)]
        have_images = any(im is not None for im in imgs)
        if self.method == "naive" and not have_images:
            return np.empty((0, 3), np.uint8), np.empty(0, bool), {"surface": 0.0, "colour": 0.0}
        t0 = time.perf_counter()
        rows, pix = self._visibility(idx, self.method)
        t1 = time.perf_counter()
        colours = np.zeros((n if have_images else 0, 3), dtype=np.uint8)
        surface = np.zeros(0 if self.method == "naive" else n, dtype=np.bool_)
        sums = np.zeros((len(rows) if have_images else 0, 3), dtype=np.int32)
        counts = np.zeros(len(sums), dtype=np.int32)
        for c in range(len(self.cameras)):
            if imgs[c] is None:
                continue
            m = masks[c] if masks is not None else None
            w, h = self.sizes[c]
            if m is None:
                _accumulate(pix[c], imgs[c], w, h, _NO_MASK, 1, 1, sums, counts)
            else:
                m01 = np.ascontiguousarray(m if m.dtype in (np.bool_, np.uint8) else m != 0).view(np.uint8).reshape(-1)
                _accumulate(pix[c], imgs[c], w, h, m01, m.shape[1], m.shape[0], sums, counts)
        _finish(pix, sums, counts, rows, colours, surface)
        t2 = time.perf_counter()
        if self.method == "naive":
            return colours, surface, {"surface": 0.0, "colour": (t2 - t0) * 1e3}
        return colours, surface, {"surface": (t1 - t0) * 1e3, "colour": (t2 - t1) * 1e3}
