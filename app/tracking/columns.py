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

__all__ = ["column_starts", "frame_runs", "near", "disc_support", "voronoi_sum", "ellipsoid_voxels", "neighbourhood",
           "free_runs", "run_sums", "share_owners", "component_sums", "run_positions"]


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
def frame_runs(idx, ny, nz, col_start, col_run, run_start, run_z0, run_z1, run_col):
    """Column starts (as :func:`column_starts`) and the runs of consecutive z of each
    column (see :func:`app.components.voxel_runs`): the runs of column ``c`` are
    ``col_run[c] .. col_run[c + 1]``. Returns the number of runs (-1: not sorted)."""
    col_start[:] = 0
    col_run[:] = 0
    m = 0
    prev = -1
    last_col = -1
    last_z = -2
    for a in range(idx.shape[0]):
        col = np.int64(idx[a, 0]) * ny + idx[a, 1]
        z = np.int64(idx[a, 2])
        key = col * nz + z
        if key <= prev:
            return -1
        prev = key
        col_start[col + 1] += 1
        if col == last_col and z == last_z + 1:
            run_z1[m - 1] = z
        else:
            run_start[m] = a
            run_z0[m] = z
            run_z1[m] = z
            run_col[m] = col
            col_run[col + 1] += 1
            m += 1
        last_col = col
        last_z = z
    run_start[m] = idx.shape[0]
    for c in range(1, col_start.shape[0]):
        col_start[c] += col_start[c - 1]
        col_run[c] += col_run[c - 1]
    return m


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
def disc_support(col_run, run_z0, run_z1, run_label, nx, ny, ox, oy, s, x, y, r, scratch):
    """``(count, host)``: the voxels within ``r`` (xy) of ``(x, y)`` and the label most of
    them carry (the smallest such label on a tie; -1 when there are none), counted by
    runs. ``scratch`` (labels' count) is zero and left so."""
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
                for q in range(col_run[c], col_run[c + 1]):
                    lab = run_label[q]
                    k = run_z1[q] - run_z0[q] + 1
                    if scratch[lab] == 0:
                        if nt == touched.shape[0]:
                            grown = np.empty(2 * nt, dtype=np.int64)
                            grown[:nt] = touched
                            touched = grown
                        touched[nt] = lab
                        nt += 1
                    scratch[lab] += k
                    count += k
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
def voronoi_sum(col_start, idx, nx, ny, ox, oy, oz, s, xs, me, close, r, z_min, out):
    """Sum of the centres (``out`` (3,)) and count of the voxels within ``r`` (xy) of
    target ``me`` that are nearer (xy) to it than to the other targets of ``close``
    (rows of ``xs``; the first nearest wins a tie, as ``argmin``) and whose centre is
    at least ``z_min`` high."""
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
                z = oz + (idx[a, 2] + 0.5) * s
                if z < z_min:
                    continue
                out[0] += cx
                out[1] += cy
                out[2] += z
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
def neighbourhood(samples, col_run, run_start, run_z0, run_z1, nx, ny, bins, ref, gamma, use_colour, r, raw, col):
    """Eq. 4.20 and 4.21 on the (2r+1)^3 neighbourhood of every sample: the runs of
    each of the (2r+1)^2 columns around it that overlap its z range."""
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
                for q in range(col_run[c], col_run[c + 1]):
                    lo = max(run_z0[q], z0)
                    hi = min(run_z1[q], z1)
                    if lo > hi:
                        if run_z0[q] > z1:
                            break
                        continue
                    occ += hi - lo + 1
                    if use_colour:
                        base = run_start[q] - run_z0[q]
                        for z in range(lo, hi + 1):
                            b = bins[base + z]
                            if b >= 0:
                                ncol += 1
                                if ref[b] >= gamma:
                                    similar += 1
        raw[a] = 1.0 - abs(2.0 * occ / size - 1.0)
        col[a] = similar / ncol if ncol > 0 else 0.0


@njit(cache=True, nogil=True)
def free_runs(col_run, nx, ny, ox, oy, s, xs, r, run_label, person, free):
    """``free`` (runs,) bool: the runs of person components no target claims (their
    column farther than ``r`` (xy) from every row of ``xs``)."""
    r2 = r * r
    for i in range(nx):
        cx = ox + (i + 0.5) * s
        for j in range(ny):
            c = i * ny + j
            q0 = col_run[c]
            q1 = col_run[c + 1]
            if q0 == q1:
                continue
            cy = oy + (j + 0.5) * s
            claimed = False
            for k in range(xs.shape[0]):
                dx = cx - xs[k, 0]
                dy = cy - xs[k, 1]
                if dx * dx + dy * dy <= r2:
                    claimed = True
                    break
            for q in range(q0, q1):
                free[q] = (not claimed) and person[run_label[q]]


@njit(cache=True, nogil=True)
def run_sums(runs, run_z0, run_z1, run_col, ny, part, k, mins, maxs, sums, counts):
    """Index bounds, index sums and voxel counts per part (``part[t]`` of run
    ``runs[t]``), as :func:`app.tracking.blobs.component_features` accumulates them
    over voxels (the sums of integers are exact, so the order does not matter)."""
    for t in range(runs.shape[0]):
        q = runs[t]
        p = part[t]
        x = run_col[q] // ny
        y = run_col[q] - x * ny
        z0 = run_z0[q]
        z1 = run_z1[q]
        n = z1 - z0 + 1
        counts[p] += n
        sums[p, 0] += x * n
        sums[p, 1] += y * n
        sums[p, 2] += (z0 + z1) * n // 2
        if x < mins[p, 0]:
            mins[p, 0] = x
        if x > maxs[p, 0]:
            maxs[p, 0] = x
        if y < mins[p, 1]:
            mins[p, 1] = y
        if y > maxs[p, 1]:
            maxs[p, 1] = y
        if z0 < mins[p, 2]:
            mins[p, 2] = z0
        if z1 > maxs[p, 2]:
            maxs[p, 2] = z1


@njit(cache=True, nogil=True)
def share_owners(col_run, run_label, nx, ny, ox, oy, s, host_of, xs, groups, group_start, owner):
    """The share of each target of the components hosting several (``host_of[label]``:
    the group's index, -1 for the others): every run of such a component goes to the
    group's target nearest (xy) to its column (first on a tie), ``owner[run]`` the row
    of ``groups`` (-1 for the runs of other components)."""
    for i in range(nx):
        cx = ox + (i + 0.5) * s
        for j in range(ny):
            c = i * ny + j
            for q in range(col_run[c], col_run[c + 1]):
                g = host_of[run_label[q]]
                if g < 0:
                    owner[q] = -1
                    continue
                cy = oy + (j + 0.5) * s
                best = np.inf
                o = -1
                for k in range(group_start[g], group_start[g + 1]):
                    ex = cx - xs[groups[k], 0]
                    ey = cy - xs[groups[k], 1]
                    d = ex * ex + ey * ey
                    if d < best:
                        best = d
                        o = k
                owner[q] = o


@njit(cache=True, nogil=True)
def component_sums(idx, labels, origin, s, sums, counts):
    """Per label: the sum of the voxel centres (``sums`` (K, 3), in list order) and the count."""
    for a in range(idx.shape[0]):
        c = labels[a]
        counts[c] += 1
        for d in range(3):
            sums[c, d] += origin[d] + (idx[a, d] + 0.5) * s


@njit(cache=True, nogil=True)
def run_positions(run_start, runs):
    """List positions (in run order) of the voxels of ``runs``."""
    total = 0
    for t in range(runs.shape[0]):
        total += run_start[runs[t] + 1] - run_start[runs[t]]
    out = np.empty(total, dtype=np.int64)
    m = 0
    for t in range(runs.shape[0]):
        for a in range(run_start[runs[t]], run_start[runs[t] + 1]):
            out[m] = a
            m += 1
    return out
