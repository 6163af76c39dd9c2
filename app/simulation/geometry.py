"""Ray casting and inside tests for the simulator's shapes (numba kernels).

Three shapes make the whole simulated world:

* **round cone** (body limbs, neck, feet): the convex hull of two spheres, centres
  ``a``, ``b`` and radii ``ra``, ``rb`` (a capsule when ``ra == rb``); the thesis's
  body model is "fleshed out with truncated cones" (§6.5.1.1), this is their smooth
  version;
* **ellipsoid** (head, chest, abdomen, pelvis): centre ``c``, rotation ``R`` whose
  columns are the local axes in world coordinates, semi-axes ``s``;
* **box** (furniture): centre, half extents and a yaw about the vertical axis.

Bodies travel as one ``(M, 16)`` float64 array of primitives, one row each:

=========  ====================================================================
kind 0     ``[ax, ay, az, bx, by, bz, ra, rb, 0 ...]``       round cone
kind 1     ``[cx, cy, cz, R00, R01, ..., R22, sx, sy, sz, 0]`` ellipsoid (R row-major)
=========  ====================================================================

The ray-cone intersection is I. Quilez's closed form for the rounded cone
(iquilezles.org/articles/intersectors), the signed distance his ``sdRoundCone``.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "CONE", "ELLIPSOID", "PRIM_WIDTH",
    "ray_cone", "ray_ellipsoid", "ray_box", "ray_primitive", "cone_normal", "ellipsoid_normal",
    "primitive_normal",
    "sdf_cone", "inside_ellipsoid", "inside_primitive", "primitive_bounds",
    "segment_blocked", "point_in_box",
]

CONE = 0
ELLIPSOID = 1
PRIM_WIDTH = 16
_MISS = 1e30


@njit(cache=True, nogil=True, error_model="numpy")
def ray_cone(ox, oy, oz, dx, dy, dz, p):
    """Distance ``t`` along the ray ``o + t d`` (|d| = 1) to its first hit with a round
    cone row ``p``, ``1e30`` on a miss (normal: :func:`cone_normal`)."""
    ax, ay, az, bx, by, bz, ra, rb = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    bax, bay, baz = bx - ax, by - ay, bz - az
    oax, oay, oaz = ox - ax, oy - ay, oz - az
    obx, oby, obz = ox - bx, oy - by, oz - bz
    rr = ra - rb
    m0 = bax * bax + bay * bay + baz * baz
    m1 = bax * oax + bay * oay + baz * oaz
    m2 = bax * dx + bay * dy + baz * dz
    m3 = dx * oax + dy * oay + dz * oaz
    m5 = oax * oax + oay * oay + oaz * oaz
    m6 = obx * dx + oby * dy + obz * dz
    m7 = obx * obx + oby * oby + obz * obz
    d2 = m0 - rr * rr
    h1 = m3 * m3 - m5 + ra * ra
    h2 = m6 * m6 - m7 + rb * rb
    if d2 > 1e-12:
        k2 = d2 - m2 * m2
        k1 = d2 * m3 - m1 * m2 + m2 * rr * ra
        k0 = d2 * m5 - m1 * m1 + m1 * rr * ra * 2.0 - m0 * ra * ra
        h = k1 * k1 - k0 * k2
        if h < 0.0:
            return _MISS
        if abs(k2) > 1e-12:
            t = (-math.sqrt(h) - k1) / k2
            y = m1 - ra * rr + t * m2
            if y > 0.0 and y < d2 and t > 0.0:
                return t
    elif ra >= rb:  # one sphere holds the other: the bigger sphere alone
        h2 = -1.0
    else:
        h1 = -1.0
    best = _MISS
    if h1 > 0.0:
        t = -m3 - math.sqrt(h1)
        if t > 0.0:
            best = t
    if h2 > 0.0:
        t = -m6 - math.sqrt(h2)
        if t > 0.0 and t < best:
            best = t
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def cone_normal(p, x, y, z):
    """Outward unit normal of a round cone at a surface point."""
    ax, ay, az, bx, by, bz, ra, rb = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    bax, bay, baz = bx - ax, by - ay, bz - az
    qx, qy, qz = x - ax, y - ay, z - az
    rr = ra - rb
    d2 = bax * bax + bay * bay + baz * baz - rr * rr
    yy = qx * bax + qy * bay + qz * baz - ra * rr
    if d2 > 1e-12 and 0.0 < yy < d2:
        nx, ny, nz = d2 * qx - bax * yy, d2 * qy - bay * yy, d2 * qz - baz * yy
    elif yy <= 0.0 or (d2 <= 1e-12 and ra >= rb):
        nx, ny, nz = qx, qy, qz
    else:
        nx, ny, nz = x - bx, y - by, z - bz
    inv = 1.0 / max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
    return nx * inv, ny * inv, nz * inv


@njit(cache=True, nogil=True, error_model="numpy")
def ray_ellipsoid(ox, oy, oz, dx, dy, dz, p):
    """Distance to the first hit of the ray with an ellipsoid row ``p`` (``1e30``: miss)."""
    qx, qy, qz = ox - p[0], oy - p[1], oz - p[2]
    sx, sy, sz = p[12], p[13], p[14]
    # local (scaled) origin and direction: R^T v / s
    olx = (p[3] * qx + p[6] * qy + p[9] * qz) / sx
    oly = (p[4] * qx + p[7] * qy + p[10] * qz) / sy
    olz = (p[5] * qx + p[8] * qy + p[11] * qz) / sz
    dlx = (p[3] * dx + p[6] * dy + p[9] * dz) / sx
    dly = (p[4] * dx + p[7] * dy + p[10] * dz) / sy
    dlz = (p[5] * dx + p[8] * dy + p[11] * dz) / sz
    a = dlx * dlx + dly * dly + dlz * dlz
    b = olx * dlx + oly * dly + olz * dlz
    c = olx * olx + oly * oly + olz * olz - 1.0
    h = b * b - a * c
    if h < 0.0:
        return _MISS
    t = (-b - math.sqrt(h)) / a
    if t <= 0.0:
        return _MISS
    return t


@njit(cache=True, nogil=True, error_model="numpy")
def ellipsoid_normal(p, x, y, z):
    """Outward unit normal of an ellipsoid at a surface point."""
    qx, qy, qz = x - p[0], y - p[1], z - p[2]
    hx = (p[3] * qx + p[6] * qy + p[9] * qz) / (p[12] * p[12])
    hy = (p[4] * qx + p[7] * qy + p[10] * qz) / (p[13] * p[13])
    hz = (p[5] * qx + p[8] * qy + p[11] * qz) / (p[14] * p[14])
    nx = p[3] * hx + p[4] * hy + p[5] * hz
    ny = p[6] * hx + p[7] * hy + p[8] * hz
    nz = p[9] * hx + p[10] * hy + p[11] * hz
    inv = 1.0 / max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
    return nx * inv, ny * inv, nz * inv


@njit(cache=True, nogil=True, error_model="numpy")
def ray_primitive(ox, oy, oz, dx, dy, dz, kind, p):
    """Distance to the first hit with a primitive (:data:`CONE` or :data:`ELLIPSOID`)."""
    if kind == CONE:
        return ray_cone(ox, oy, oz, dx, dy, dz, p)
    return ray_ellipsoid(ox, oy, oz, dx, dy, dz, p)


@njit(cache=True, nogil=True, error_model="numpy")
def primitive_normal(kind, p, x, y, z):
    """Outward unit normal of a primitive at a surface point."""
    if kind == CONE:
        return cone_normal(p, x, y, z)
    return ellipsoid_normal(p, x, y, z)


@njit(cache=True, nogil=True, error_model="numpy")
def ray_box(ox, oy, oz, dx, dy, dz, box):
    """Entry of the ray into an oriented box ``[cx, cy, cz, hx, hy, hz, yaw, ...]``.

    Returns ``(t, nx, ny, nz)`` (world normal of the entry face), ``1e30`` on a miss or
    when the origin is inside the box.
    """
    c, s = math.cos(box[6]), math.sin(box[6])
    px, py, pz = ox - box[0], oy - box[1], oz - box[2]
    lx, ly = c * px + s * py, -s * px + c * py
    ldx, ldy = c * dx + s * dy, -s * dx + c * dy
    o = (lx, ly, pz + 0.0)
    d = (ldx, ldy, dz + 0.0)
    h = (box[3], box[4], box[5])
    tmin, tmax = -_MISS, _MISS
    axis, sign = -1, 0.0
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if o[k] < -h[k] or o[k] > h[k]:
                return _MISS, 0.0, 0.0, 0.0
            continue
        inv = 1.0 / d[k]
        t1 = (-h[k] - o[k]) * inv
        t2 = (h[k] - o[k]) * inv
        sg = -1.0
        if t1 > t2:
            t1, t2 = t2, t1
            sg = 1.0
        if t1 > tmin:
            tmin, axis, sign = t1, k, sg
        if t2 < tmax:
            tmax = t2
    if tmin > tmax or tmin <= 0.0 or axis < 0:
        return _MISS, 0.0, 0.0, 0.0
    nlx, nly, nz = 0.0, 0.0, 0.0
    if axis == 0:
        nlx = sign
    elif axis == 1:
        nly = sign
    else:
        nz = sign
    return tmin, c * nlx - s * nly, s * nlx + c * nly, nz


@njit(cache=True, nogil=True, error_model="numpy")
def point_in_box(x, y, z, box, margin):
    """True when the point lies inside the box grown by ``margin`` on every side."""
    c, s = math.cos(box[6]), math.sin(box[6])
    px, py, pz = x - box[0], y - box[1], z - box[2]
    lx, ly = c * px + s * py, -s * px + c * py
    return (abs(lx) <= box[3] + margin and abs(ly) <= box[4] + margin
            and abs(pz) <= box[5] + margin)


@njit(cache=True, nogil=True, error_model="numpy")
def sdf_cone(x, y, z, p):
    """Signed distance from a point to a round cone row (negative inside)."""
    ax, ay, az, bx, by, bz, r1, r2 = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    bax, bay, baz = bx - ax, by - ay, bz - az
    l2 = bax * bax + bay * bay + baz * baz
    rr = r1 - r2
    if l2 <= rr * rr + 1e-18:  # one sphere holds the other
        if r1 >= r2:
            dx, dy, dz = x - ax, y - ay, z - az
            return math.sqrt(dx * dx + dy * dy + dz * dz) - r1
        dx, dy, dz = x - bx, y - by, z - bz
        return math.sqrt(dx * dx + dy * dy + dz * dz) - r2
    a2 = l2 - rr * rr
    il2 = 1.0 / l2
    pax, pay, paz = x - ax, y - ay, z - az
    yy = pax * bax + pay * bay + paz * baz
    zz = yy - l2
    qx, qy, qz = pax * l2 - bax * yy, pay * l2 - bay * yy, paz * l2 - baz * yy
    x2 = qx * qx + qy * qy + qz * qz
    y2 = yy * yy * l2
    z2 = zz * zz * l2
    k = (1.0 if rr > 0 else (-1.0 if rr < 0 else 0.0)) * rr * rr * x2
    sz = 1.0 if zz > 0 else (-1.0 if zz < 0 else 0.0)
    sy = 1.0 if yy > 0 else (-1.0 if yy < 0 else 0.0)
    if sz * a2 * z2 > k:
        return math.sqrt(x2 + z2) * il2 - r2
    if sy * a2 * y2 < k:
        return math.sqrt(x2 + y2) * il2 - r1
    return (math.sqrt(x2 * a2 * il2) + yy * rr) * il2 - r1


@njit(cache=True, nogil=True, error_model="numpy")
def inside_ellipsoid(x, y, z, p, margin):
    """True when the point is inside the ellipsoid with every semi-axis grown by ``margin``."""
    qx, qy, qz = x - p[0], y - p[1], z - p[2]
    lx = (p[3] * qx + p[6] * qy + p[9] * qz) / (p[12] + margin)
    ly = (p[4] * qx + p[7] * qy + p[10] * qz) / (p[13] + margin)
    lz = (p[5] * qx + p[8] * qy + p[11] * qz) / (p[14] + margin)
    return lx * lx + ly * ly + lz * lz <= 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def inside_primitive(x, y, z, kind, p, margin):
    """True when the point is inside the primitive grown by ``margin``."""
    if kind == CONE:
        return sdf_cone(x, y, z, p) <= margin
    return inside_ellipsoid(x, y, z, p, margin)


@njit(cache=True, nogil=True, error_model="numpy")
def primitive_bounds(kind, p, out):
    """Axis-aligned bounds of one primitive into ``out[0:3]`` (min) and ``out[3:6]`` (max)."""
    if kind == CONE:
        for k in range(3):
            out[k] = min(p[k] - p[6], p[3 + k] - p[7])
            out[3 + k] = max(p[k] + p[6], p[3 + k] + p[7])
    else:
        for k in range(3):
            # half extent along world axis k: sqrt(sum_j (R[k, j] s_j)^2)
            e = 0.0
            for j in range(3):
                v = p[3 + 3 * k + j] * p[12 + j]
                e += v * v
            e = math.sqrt(e)
            out[k] = p[k] - e
            out[3 + k] = p[k] + e


@njit(cache=True, nogil=True, error_model="numpy")
def segment_blocked(ox, oy, oz, px, py, pz, boxes, kinds, prims, owner, skip_owner):
    """True when the segment from ``o`` to ``p`` passes through a box or through a
    primitive whose owner differs from ``skip_owner`` (used for joint visibility)."""
    dx, dy, dz = px - ox, py - oy, pz - oz
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    if length < 1e-9:
        return False
    dx, dy, dz = dx / length, dy / length, dz / length
    for i in range(boxes.shape[0]):
        t = ray_box(ox, oy, oz, dx, dy, dz, boxes[i])[0]
        if t < length:
            return True
    for i in range(prims.shape[0]):
        if owner[i] == skip_owner:
            continue
        t = ray_primitive(ox, oy, oz, dx, dy, dz, kinds[i], prims[i])
        if t < length:
            return True
    return False


def cone_row(a, b, ra, rb) -> np.ndarray:
    """A round cone primitive row."""
    row = np.zeros(PRIM_WIDTH)
    row[0:3] = a
    row[3:6] = b
    row[6] = ra
    row[7] = rb
    return row


def ellipsoid_row(c, R, s) -> np.ndarray:
    """An ellipsoid primitive row (``R`` columns: the local axes in world coordinates)."""
    row = np.zeros(PRIM_WIDTH)
    row[0:3] = c
    row[3:12] = np.asarray(R, dtype=np.float64).reshape(9)
    row[12:15] = s
    return row
