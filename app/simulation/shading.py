"""Procedural textures and the lighting model of the simulated room (numba kernels).

Lighting: the ceiling panels are downward-facing Lambertian emitters and every surface
is Lambertian, so the irradiance at a point ``p`` with normal ``n`` is

    E(p, n) = A (0.7 + 0.3 n_z) + sum_l P_l max(0, n . l) max(0, l_z) / (|L_l - p|^2 + 0.25)

with ``l`` the unit vector towards light ``l`` and ``A`` the ambient (inter-reflection)
term, brighter on upward-facing surfaces. The pixel value is ``albedo * E * exposure``.
The floor uses a precomputed light map that also holds the soft shadows of the
furniture (:func:`floor_lightmap`); the people's soft floor shadows darken it per
frame (:mod:`app.simulation.render`).

Textures (wood planks, plaster walls, fabric) come from a hashed value noise, so they
are deterministic and need no image files.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.simulation.geometry import ray_box

__all__ = ["AMBIENT", "EXPOSURE", "irradiance", "value_noise", "fbm", "floor_albedo",
           "wall_albedo", "material_albedo", "floor_lightmap", "LIGHTMAP_CELL"]

AMBIENT = 0.26
EXPOSURE = 0.74
LIGHTMAP_CELL = 0.04


@njit(cache=True, nogil=True, error_model="numpy")
def _hash(ix, iy, seed):
    h = (ix * 374761393 + iy * 668265263 + seed * 1442695041) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


@njit(cache=True, nogil=True, error_model="numpy")
def value_noise(x, y, seed):
    """Smooth value noise in [0, 1) with unit lattice spacing."""
    fx, fy = math.floor(x), math.floor(y)
    ix, iy = int(fx), int(fy)
    tx, ty = x - fx, y - fy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    a = _hash(ix, iy, seed)
    b = _hash(ix + 1, iy, seed)
    c = _hash(ix, iy + 1, seed)
    d = _hash(ix + 1, iy + 1, seed)
    return (a + (b - a) * tx) * (1.0 - ty) + (c + (d - c) * tx) * ty


@njit(cache=True, nogil=True, error_model="numpy")
def fbm(x, y, seed, octaves):
    """Fractal sum of value noise, in about [0, 1)."""
    s, amp, norm = 0.0, 0.5, 0.0
    for o in range(octaves):
        s += amp * value_noise(x, y, seed + 17 * o)
        norm += amp
        x *= 2.03
        y *= 2.03
        amp *= 0.5
    return s / norm


@njit(cache=True, nogil=True, error_model="numpy")
def irradiance(px, py, pz, nx, ny, nz, lights):
    """Irradiance at a point with unit normal ``n`` from the ceiling panels and ambient."""
    e = AMBIENT * (0.7 + 0.3 * nz)
    for i in range(lights.shape[0]):
        lx, ly, lz = lights[i, 0] - px, lights[i, 1] - py, lights[i, 2] - pz
        d2 = lx * lx + ly * ly + lz * lz
        inv = 1.0 / math.sqrt(d2)
        cos_s = (nx * lx + ny * ly + nz * lz) * inv
        cos_e = lz * inv
        if cos_s > 0.0 and cos_e > 0.0:
            e += lights[i, 3] * cos_s * cos_e / (d2 * 0.55 + 0.25)
    return e


@njit(cache=True, nogil=True, error_model="numpy")
def floor_albedo(x, y, look):
    """The floor of a room's look (:func:`app.simulation.room.room_look`): laminate planks
    (``look[16]`` wide, 1.2 m long along x) with per-plank tone and grain (the default:
    oak, 18 cm), square tiles of side ``look[16]`` with grout lines, or carpet; in the
    look's floor colour ``look[12:15]``."""
    kind = int(look[15])
    width = look[16]
    if kind == 1:   # tiles
        i, j = int(math.floor(x / width)), int(math.floor(y / width))
        fx, fy = x / width - i, y / width - j
        v = 0.93 + 0.1 * _hash(i, j, 23) + 0.03 * value_noise(x * 25.0, y * 25.0, 29)
        if fx < 0.012 or fy < 0.012:
            v *= 0.72
    elif kind == 2:   # carpet
        v = 0.92 + 0.08 * fbm(x * 3.0, y * 3.0, 37, 3) + 0.06 * value_noise(x * 220.0, y * 220.0, 41)
    else:           # planks
        row = int(math.floor(y / width))
        offset = _hash(row, 7, 3) * 1.2
        col = int(math.floor((x + offset) / 1.2))
        tone = 0.82 + 0.3 * _hash(row, col, 11)
        grain = fbm((x + offset) * 1.5, y * 40.0, row * 31 + col, 3)
        fine = value_noise(x * 90.0, y * 300.0, 5)
        v = tone * (0.86 + 0.22 * grain + 0.05 * fine)
        # dark seams between planks
        fy = y / width - row
        fx = (x + offset) / 1.2 - col
        if fy < 0.025 or fx < 0.004:
            v *= 0.55
    return look[12] * v, look[13] * v, look[14] * v


@njit(cache=True, nogil=True, error_model="numpy")
def _window(u, z, u0, u1, z0, z1, r, g, b):
    # aluminium frame, mullions every ~1 m, sky-and-buildings view graded with height
    frame = 0.05
    if u - u0 < frame or u1 - u < frame or z - z0 < frame or z1 - z < frame:
        return 0.78, 0.78, 0.80
    n = max(1, int(round((u1 - u0) / 1.0)))
    pane = (u1 - u0) / n
    k = (u - u0) / pane
    if abs(k - round(k)) * pane < 0.03:
        return 0.78, 0.78, 0.80
    h = (z - z0) / (z1 - z0)
    if h < 0.35 + 0.12 * value_noise(u * 2.0, 0.5, 41):  # buildings across the street
        w = 0.55 + 0.25 * _hash(int(u * 3.0), int(z * 5.0), 2)
        return 0.62 * w, 0.60 * w, 0.58 * w
    return r * (0.92 + 0.12 * h), g * (0.95 + 0.08 * h), b



@njit(cache=True, nogil=True, error_model="numpy")
def _board(u, z, u0, u1, z0, z1):
    if u - u0 < 0.03 or u1 - u < 0.03 or z - z0 < 0.03 or z1 - z < 0.03:
        return 0.70, 0.71, 0.73
    if z - z0 < 0.06 and 0.2 < u - u0 < 0.9:  # marker tray
        return 0.55, 0.56, 0.58
    for j in range(4):
        zc = z1 - 0.17 - 0.17 * j
        length = 0.55 + 0.9 * _hash(j, 3, 77)
        if u0 + 0.12 < u < u0 + 0.12 + length:
            if abs(z - zc - 0.022 * math.sin(u * 41.0 + j)) < 0.0055 and value_noise(u * 7.0, j * 3.1, 9) > 0.33:
                if j == 1:
                    return 0.62, 0.12, 0.10
                return 0.12, 0.20, 0.58
    w = 0.97 + 0.03 * value_noise(u * 3.0, z * 3.0, 13)
    return 0.95 * w, 0.95 * w, 0.94 * w


@njit(cache=True, nogil=True, error_model="numpy")
def _poster(u, z, u0, u1, z0, z1):
    if u - u0 < 0.025 or u1 - u < 0.025 or z - z0 < 0.025 or z1 - z < 0.025:
        return 0.08, 0.08, 0.08
    h = (z - z0) / (z1 - z0)
    s = (u - u0) / (u1 - u0)
    ridge = 0.45 + 0.12 * math.sin(s * 9.0) + 0.08 * math.sin(s * 23.0 + 1.0)
    if h > ridge:
        return 0.45 + 0.3 * h, 0.62 + 0.2 * h, 0.85
    if h > ridge - 0.15:
        return 0.35, 0.38, 0.45
    return 0.25 + 0.1 * s, 0.45, 0.18


@njit(cache=True, nogil=True, error_model="numpy")
def wall_albedo(wall, u, z, height, decor, look):
    """Albedo ``(r, g, b, emissive)`` of a wall point; ``u`` runs along the wall; the
    wall's base colour is ``look[3 wall: 3 wall + 3]``."""
    for i in range(decor.shape[0] - 1, -1, -1):
        d = decor[i]
        if int(d[0]) == wall and d[1] <= u <= d[2] and d[3] <= z <= d[4]:
            kind = int(d[5])
            if kind == 1:
                r, g, b = _window(u, z, d[1], d[2], d[3], d[4], d[6], d[7], d[8])
                return r, g, b, True
            if kind == 2:
                r, g, b = _board(u, z, d[1], d[2], d[3], d[4])
                return r, g, b, False
            if kind == 3:
                r, g, b = _poster(u, z, d[1], d[2], d[3], d[4])
                return r, g, b, False
            w = 0.96 + 0.04 * value_noise(u * 20.0, z * 20.0, 3)
            return d[6] * w, d[7] * w, d[8] * w, False
    if z < 0.08:  # skirting board
        return 0.32 * look[20], 0.30 * look[20], 0.28 * look[20], False
    br, bg, bb = look[3 * wall], look[3 * wall + 1], look[3 * wall + 2]
    blot = fbm(u * 1.1 + wall * 7.0, z * 1.1, 21 + wall, 4)
    fine = value_noise(u * 60.0, z * 60.0, 5 + wall)
    w = 0.90 + 0.16 * blot + 0.03 * fine
    return br * w, bg * w, bb * w, False


@njit(cache=True, nogil=True, error_model="numpy")
def material_albedo(material, px, py, pz, albedo, texture):
    """Albedo of furniture material ``material`` at a point (wood grain, fabric weave)."""
    r, g, b = albedo[material, 0], albedo[material, 1], albedo[material, 2]
    kind = texture[material]
    if kind == 1:
        w = 0.88 + 0.2 * fbm(px * 2.0 + py * 0.3, py * 30.0 + pz * 30.0, 61 + material, 3)
    elif kind == 2:
        w = 0.9 + 0.12 * value_noise(px * 150.0 + pz * 90.0, py * 150.0 + pz * 70.0, 7)
    else:
        w = 1.0
    return r * w, g * w, b * w


@njit(cache=True, nogil=True, error_model="numpy")
def _occluded(px, py, pz, qx, qy, qz, boxes):
    dx, dy, dz = qx - px, qy - py, qz - pz
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / length, dy / length, dz / length
    for i in range(boxes.shape[0]):
        if ray_box(px, py, pz, dx, dy, dz, boxes[i])[0] < length:
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def floor_lightmap(width, depth, cell, lights, boxes):
    """Floor irradiance on a ``cell``-spaced grid (rows y, columns x), with the soft
    shadows of the furniture (each panel sampled at 3 x 3 points) and the ambient
    occlusion of walls and furniture."""
    nx = int(math.ceil(width / cell)) + 1
    ny = int(math.ceil(depth / cell)) + 1
    out = np.empty((ny, nx), dtype=np.float32)
    # fixed ambient probe directions (elevations 25, 55 deg; 6 azimuths each) + zenith
    ndir = 13
    dirs = np.empty((ndir, 3))
    k = 0
    for el in (0.44, 0.96):
        for a in range(6):
            az = a * math.pi / 3.0 + el
            dirs[k, 0] = math.cos(el) * math.cos(az)
            dirs[k, 1] = math.cos(el) * math.sin(az)
            dirs[k, 2] = math.sin(el)
            k += 1
    dirs[12, 0], dirs[12, 1], dirs[12, 2] = 0.0, 0.0, 1.0
    for j in range(ny):
        y = min(j * cell, depth)
        for i in range(nx):
            x = min(i * cell, width)
            z = 0.002
            dwall = min(min(x, width - x), min(y, depth - y))
            ao = 1.0 - 0.32 * math.exp(-dwall / 0.22)
            free = 0
            for d in range(ndir):
                blocked = False
                for b in range(boxes.shape[0]):
                    tb = ray_box(x, y, z, dirs[d, 0], dirs[d, 1], dirs[d, 2], boxes[b])[0]
                    if tb < 1.2:
                        blocked = True
                        break
                if not blocked:
                    free += 1
            e = AMBIENT * ao * (0.35 + 0.65 * free / ndir)
            for l in range(lights.shape[0]):
                lx, ly, lz = lights[l, 0] - x, lights[l, 1] - y, lights[l, 2] - z
                d2 = lx * lx + ly * ly + lz * lz
                cos_s = lz / math.sqrt(d2)
                direct = lights[l, 3] * cos_s * cos_s / (d2 * 0.55 + 0.25)
                half = lights[l, 4] * 0.5
                vis = 0
                for a in range(3):
                    for c in range(3):
                        qx = lights[l, 0] + (a - 1) * half * 0.8
                        qy = lights[l, 1] + (c - 1) * half * 0.8
                        if not _occluded(x, y, z, qx, qy, lights[l, 2], boxes):
                            vis += 1
                e += direct * vis / 9.0
            out[j, i] = e
    return out
