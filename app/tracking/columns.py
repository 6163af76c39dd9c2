"""Column index of a sorted voxel list and the neighbourhood kernels of the trackers.

The reconstruction publishes its voxels sorted by grid (x, y, z), so the voxels of one
(x, y) column are consecutive in the list: ``col_start[i * ny + j]`` .. ``col_start[i *
ny + j + 1]`` (built in one pass, O(voxels + columns)). Every question the trackers ask
about the xy plane (voxels within a radius, support, the host component, the voxels
nearer to one target than to the others, the 5x5x5 neighbourhood of Eq. 4.20-4.21) is
answered by visiting the columns it covers, in numba, without building the dense
occupancy grid or any array the size of the frame (DESIGN §3). The column centres are
computed as the voxel centres are, ``origin + (i + 0.5) s``, so the answers are the
same, bit for bit, as those of the arrays of centres they replace.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["column_starts", "near", "disc_support", "voronoi_sum", "ellipsoid_voxels", "neighbourhood",
           "free_voxels", "share_sums", "component_sums"]


@njit(cache=True, nogil=True)
def column_starts(idx, nx, ny, nz, out, strict=True):
    """``out`` (nx * ny + 1): start of each column's voxels in a list sorted by (x, y, z).
    Returns False (``out`` undefined) when the list is not sorted (strictly: no voxel
    twice)."""
    out[:] = 0
    prev = -1
    for a in range(idx.shape[0]):
        col = np.int64(idx[a, 0]) * ny + idx[a, 1]
        key = col * nz + idx[a, 2]
        if key < prev or (strict and key == prev):
            return False
        prev = key
        out[col + 1] += 1
    for c in range(1, out.shape[0]):
        out[c] += out[c - 1]
    return True


@njit(cache=True, nogil=True)
def _span(centre, radius, origin, s, n):
    lo = int(np.floor((centre - radius - origin) / s - 0.5))
    hi = int(np.ceil((centre + radius - origin) / s - 0.5))
    return max(lo, 0), min(hi, n - 1)


@njit(cache=True, nogil=True)
def near(col_start, nx, ny, ox, oy, s, x, y, r):
    """List positions (ascending) of the voxels whose centre lies within ``r`` of
    ``(x, y)`` in the xy plane."""
    r2 = r * r
    i0, i1 = _span(x, r, ox, s, nx)
    j0, j1 = _span(y, r, oy, s, ny)
    count = 0
    for i in range(i0, i1 + 1):
        dx = ox + (i + 0.5) * s - x
        for j in range(j0, j1 + 1):
            dy = oy + (j + 0.5) * s - y
            if dx * dx + dy * dy <= r2:
                c = i * ny + j
                count += col_start[c + 1] - col_start[c]
    out = np.empty(count, dtype=np.int64)
    m = 0
    for i in range(i0, i1 + 1):
        dx = ox + (i + 0.5) * s - x
        for j in range(j0, j1 + 1):
            dy = oy + (j + 0.5) * s - y
            if dx * dx + dy * dy <= r2:
                c = i * ny + j
                for a in range(col_start[c], col_start[c + 1]):
                    out[m] = a
                    m += 1
    return out


@njit(cache=True, nogil=True)
def disc_support(col_start, nx, ny, ox, oy, s, x, y, r, labels, scratch):
    """``(count, host)``: the voxels within ``r`` (xy) of ``(x, y)`` and the label most of
    them carry (the smallest such label on a tie; -1 when there are none). ``scratch``
    (labels' count) is zero and left so."""
    r2 = r * r
    i0, i1 = _span(x, r, ox, s, nx)
    j0, j1 = _span(y, r, oy, s, ny)
    count = 0
    touched = np.empty(64, dtype=np.int64)
    nt = 0
    for i in range(i0, i1 + 1):
        dx = ox + (i + 0.5) * s - x
        for j in range(j0, j1 + 1):
            dy = oy + (j + 0.5) * s - y
            if dx * dx + dy * dy <= r2:
                c = i * ny + j
                for a in range(col_start[c], col_start[c + 1]):
                    lab = labels[a]
                    if scratch[lab] == 0:
                        if nt == touched.shape[0]:
                            grown = np.empty(2 * nt, dtype=np.int64)
                            grown[:nt] = touched
                            touched = grown
                        touched[nt] = lab
                        nt += 1
                    scratch[lab] += 1
                    count += 1
    host = -1
    best = 0
    for t in range(nt):
        lab = touched[t]
        k = scratch[lab]
        if k > best or (k == best and lab < host):
            best = k
            host = lab
        scratch[lab] = 0
    return count, host


@njit(cache=True, nogil=True)
def voronoi_sum(col_start, idx, nx, ny, ox, oy, oz, s, xs, me, close, r, out):
    """Sum of the centres (``out`` (3,)) and count of the voxels within ``r`` (xy) of
    target ``me`` that are nearer (xy) to it than to the other targets of ``close``
    (rows of ``xs``; the first nearest wins a tie, as ``argmin``)."""
    x, y = xs[me, 0], xs[me, 1]
    r2 = r * r
    i0, i1 = _span(x, r, ox, s, nx)
    j0, j1 = _span(y, r, oy, s, ny)
    out[:] = 0.0
    count = 0
    for i in range(i0, i1 + 1):
        cx = ox + (i + 0.5) * s
        dx = cx - x
        for j in range(j0, j1 + 1):
            cy = oy + (j + 0.5) * s
            dy = cy - y
            if dx * dx + dy * dy > r2:
                continue
            if close.shape[0] > 1:
                best = np.inf
                owner = -1
                for k in range(close.shape[0]):
                    ex = cx - xs[close[k], 0]
                    ey = cy - xs[close[k], 1]
                    d = ex * ex + ey * ey
                    if d < best:
                        best = d
                        owner = close[k]
                if owner != me:
                    continue
            c = i * ny + j
            for a in range(col_start[c], col_start[c + 1]):
                out[0] += cx
                out[1] += cy
                out[2] += oz + (idx[a, 2] + 0.5) * s
                count += 1
    return count


@njit(cache=True, nogil=True)
def ellipsoid_voxels(col_start, idx, nx, ny, ox, oy, oz, s, x, sx, exclude):
    """List positions (ascending) of the voxels in the ellipsoid at ``x`` (axes sx, sx,
    max(z, 0.05)) that are not nearer (xy) to one of ``exclude`` (rows x, y) than to
    ``x``."""
    sz = max(x[2], 0.05)
    r2 = sx * sx
    i0, i1 = _span(x[0], sx, ox, s, nx)
    j0, j1 = _span(x[1], sx, oy, s, ny)
    total = 0
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            c = i * ny + j
            total += col_start[c + 1] - col_start[c]
    out = np.empty(total, dtype=np.int64)
    m = 0
    for i in range(i0, i1 + 1):
        dx = ox + (i + 0.5) * s - x[0]
        for j in range(j0, j1 + 1):
            dy = oy + (j + 0.5) * s - x[1]
            if dx * dx + dy * dy > r2:
                continue
            own = dx * dx + dy * dy
            keep = True
            for k in range(exclude.shape[0]):
                ex = ox + (i + 0.5) * s - exclude[k, 0]
                ey = oy + (j + 0.5) * s - exclude[k, 1]
                if ex * ex + ey * ey < own:
                    keep = False
                    break
            if not keep:
                continue
            c = i * ny + j
            for a in range(col_start[c], col_start[c + 1]):
                dz = oz + (idx[a, 2] + 0.5) * s - x[2]
                if (dx * dx + dy * dy) / r2 + (dz / sz) ** 2 <= 1.0:
                    out[m] = a
                    m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def neighbourhood(samples, col_start, idx, nx, ny, nz, bins, ref, gamma, use_colour, r, raw, col):
    """Eq. 4.20 and 4.21 on the (2r+1)^3 neighbourhood of every sample: the occupied
    voxels of each of the (2r+1)^2 columns around it with z within r (binary search in
    the column, whose voxels are sorted by z)."""
    size = (2 * r + 1) ** 3
    for a in range(samples.shape[0]):
        occ = 0
        ncol = 0
        similar = 0
        z0 = samples[a, 2] - r
        z1 = samples[a, 2] + r
        for i in range(samples[a, 0] - r, samples[a, 0] + r + 1):
            if i < 0 or i >= nx:
                continue
            for j in range(samples[a, 1] - r, samples[a, 1] + r + 1):
                if j < 0 or j >= ny:
                    continue
                c = i * ny + j
                lo = col_start[c]
                hi = col_start[c + 1]
                while lo < hi:   # first voxel with z >= z0
                    mid = (lo + hi) >> 1
                    if idx[mid, 2] < z0:
                        lo = mid + 1
                    else:
                        hi = mid
                end = col_start[c + 1]
                v = lo
                while v < end and idx[v, 2] <= z1:
                    occ += 1
                    if use_colour:
                        b = bins[v]
                        if b >= 0:
                            ncol += 1
                            if ref[b] >= gamma:
                                similar += 1
                    v += 1
        raw[a] = 1.0 - abs(2.0 * occ / size - 1.0)
        col[a] = similar / ncol if ncol > 0 else 0.0


@njit(cache=True, nogil=True)
def free_voxels(col_start, nx, ny, ox, oy, s, xs, r, labels, person, free):
    """``free`` (N,) bool: the voxels of person components no target claims (farther
    than ``r`` (xy) from every row of ``xs``); returns how many."""
    r2 = r * r
    count = 0
    for i in range(nx):
        cx = ox + (i + 0.5) * s
        for j in range(ny):
            c = i * ny + j
            a0 = col_start[c]
            a1 = col_start[c + 1]
            if a0 == a1:
                continue
            cy = oy + (j + 0.5) * s
            claimed = False
            for k in range(xs.shape[0]):
                dx = cx - xs[k, 0]
                dy = cy - xs[k, 1]
                if dx * dx + dy * dy <= r2:
                    claimed = True
                    break
            for a in range(a0, a1):
                f = (not claimed) and person[labels[a]]
                free[a] = f
                if f:
                    count += 1
    return count


@njit(cache=True, nogil=True)
def share_sums(idx, labels, ox, oy, s, host_of, xs, groups, group_start, mins, maxs, sums, counts):
    """The share of each target of the components hosting several (``host_of[label]``:
    the group's index, -1 for the others): every voxel of such a component goes to the
    group's target nearest (xy) to it (first on a tie); per group entry (a row of
    ``groups``), the index bounds, index sums and voxel count of its share, as
    :func:`app.tracking.blobs.component_features` accumulates them."""
    for a in range(idx.shape[0]):
        g = host_of[labels[a]]
        if g < 0:
            continue
        cx = ox + (idx[a, 0] + 0.5) * s
        cy = oy + (idx[a, 1] + 0.5) * s
        best = np.inf
        owner = -1
        for k in range(group_start[g], group_start[g + 1]):
            ex = cx - xs[groups[k], 0]
            ey = cy - xs[groups[k], 1]
            d = ex * ex + ey * ey
            if d < best:
                best = d
                owner = k
        counts[owner] += 1
        for d in range(3):
            v = idx[a, d]
            sums[owner, d] += v
            if v < mins[owner, d]:
                mins[owner, d] = v
            if v > maxs[owner, d]:
                maxs[owner, d] = v


@njit(cache=True, nogil=True)
def component_sums(idx, labels, origin, s, sums, counts):
    """Per label: the sum of the voxel centres (``sums`` (K, 3), in list order) and the count."""
    for a in range(idx.shape[0]):
        c = labels[a]
        counts[c] += 1
        for d in range(3):
            sums[c, d] += origin[d] + (idx[a, d] + 0.5) * s
