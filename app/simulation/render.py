"""Ray-cast renderer of the simulated room (numba kernels, single-threaded).

Rendering uses the pipeline's own camera model: every pixel's undistorted world ray is
computed once with :meth:`Camera.pixel_rays` (the exact inverse of
:meth:`Camera.project`), so a world point is rendered at the pixel where
``Camera.project`` puts it, distortion included.

Per camera, once (:class:`CameraView`):
  the empty room is ray-cast into a colour image and a depth image (distance along the
  ray); the floor pixels remember the floor point they show.

Per frame:
  1. the people's soft floor shadows are computed once for all cameras on a floor grid
     (:func:`shadow_map`) and darken the floor pixels (:func:`apply_shadows`);
  2. each body primitive is ray-cast only inside its projected bounding box, depth
     tested against the room (furniture occludes) and the other primitives, shaded
     (Lambert, same lights as the room) and labelled with its person's id;
  3. a slight blur (optics), an illumination flicker (gain) and sensor noise finish
     the image; the video codec adds compression when a recording is written.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from app.simulation.body import (MAT_HEAD, MAT_PELVIS, MAT_SLEEVE, SLOT_BELT, SLOT_HAIR, SLOT_SHIRT, SLOT_SKIN,
                                 SLOT_TROUSERS)
from app.simulation.geometry import CONE, primitive_normal, ray_box, ray_primitive
from app.simulation.room import MATERIAL_ALBEDO, MATERIAL_TEXTURE, Room
from app.simulation.shading import (EXPOSURE, LIGHTMAP_CELL, floor_albedo, floor_lightmap,
                                    irradiance, material_albedo, value_noise, wall_albedo)

__all__ = ["CameraView", "RoomLighting", "depth_people", "shade_people", "shadow_map", "shadow_spheres", "NOISE_SIGMA",
           "RENDERER_VERSION"]

#: Bumped whenever rendered output changes (cache folders carry it).
RENDERER_VERSION = 1
NOISE_SIGMA = 2.2


_SURF_FLOOR, _SURF_CEILING, _SURF_WALL, _SURF_CORRIDOR_FLOOR, _SURF_CORRIDOR, _SURF_BOX = 0, 1, 2, 3, 4, 5


# -- the empty room ------------------------------------------------------------------

@njit(cache=True, nogil=True, error_model="numpy")
def _trace_shell(ox, oy, oz, dx, dy, dz, size, door, corridor):
    """Exit of a ray from the room box (through the doorway into the corridor).

    Returns ``(t, surface, wall, nx, ny, nz)``.
    """
    t, axis, upper = 1e30, -1, False
    for k in range(3):
        o = (ox, oy, oz)[k]
        d = (dx, dy, dz)[k]
        if d > 1e-12:
            tk = (size[k] - o) / d
            if tk < t:
                t, axis, upper = tk, k, True
        elif d < -1e-12:
            tk = -o / d
            if tk < t:
                t, axis, upper = tk, k, False
    if axis == 2:
        if upper:
            return t, _SURF_CEILING, -1, 0.0, 0.0, -1.0
        return t, _SURF_FLOOR, -1, 0.0, 0.0, 1.0
    if axis == 0 and not upper:
        y, z = oy + t * dy, oz + t * dz
        if door[0] <= y <= door[1] and z <= door[2]:
            # through the doorway: exit of the corridor box
            tc, cax = 1e30, -1
            lo = (corridor[0], corridor[2], 0.0)
            hi = (corridor[1], corridor[3], size[2])
            for k in range(3):
                o = (ox, oy, oz)[k]
                d = (dx, dy, dz)[k]
                if k == 0 and d >= 0.0:
                    continue
                if d > 1e-12:
                    tk = (hi[k] - o) / d
                elif d < -1e-12:
                    tk = (lo[k] - o) / d
                else:
                    continue
                if tk < tc:
                    tc, cax = tk, k
            if cax == 2 and dz < 0.0:
                return tc, _SURF_CORRIDOR_FLOOR, -1, 0.0, 0.0, 1.0
            return tc, _SURF_CORRIDOR, cax, 0.0, 0.0, 0.0
        return t, _SURF_WALL, 0, 1.0, 0.0, 0.0
    if axis == 0:
        return t, _SURF_WALL, 1, -1.0, 0.0, 0.0
    if upper:
        return t, _SURF_WALL, 3, 0.0, -1.0, 0.0
    return t, _SURF_WALL, 2, 0.0, 1.0, 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _lightmap_at(lightmap, cell, x, y):
    fx = min(max(x / cell, 0.0), lightmap.shape[1] - 1.001)
    fy = min(max(y / cell, 0.0), lightmap.shape[0] - 1.001)
    i, j = int(fx), int(fy)
    ax, ay = fx - i, fy - j
    return ((lightmap[j, i] * (1 - ax) + lightmap[j, i + 1] * ax) * (1 - ay)
            + (lightmap[j + 1, i] * (1 - ax) + lightmap[j + 1, i + 1] * ax) * ay)


@njit(cache=True, nogil=True, error_model="numpy")
def _ceiling_albedo(x, y, lights):
    for l in range(lights.shape[0]):
        half = lights[l, 4] * 0.5
        ax, ay = abs(x - lights[l, 0]), abs(y - lights[l, 1])
        if ax < half and ay < half:
            if ax > half - 0.025 or ay > half - 0.025:
                return 0.8, 0.8, 0.8, True
            return 1.0, 0.99, 0.95, True
    w = 0.95 + 0.05 * value_noise(x * 1.6, y * 1.6, 91)
    tile = (x / 0.6 - math.floor(x / 0.6) < 0.01) or (y / 0.6 - math.floor(y / 0.6) < 0.01)
    if tile:
        w *= 0.8
    return 0.9 * w, 0.9 * w, 0.88 * w, False


@njit(cache=True, nogil=True, error_model="numpy")
def trace_room(rays, ox, oy, oz, size, door, corridor, boxes, box_bbox, decor, lights, lightmap, cell,
               albedo, texture, look):
    """Ray-cast the empty room: BGR image (uint8), depth (ray distance, float32) and the
    floor point (x, y) of every room-floor pixel (NaN elsewhere). Each furniture box is
    tested only inside its pixel bounding box ``box_bbox[b] = [u0, v0, u1, v1]``.
    ``look``: the room's colours, light colour and exposure
    (:func:`app.simulation.room.room_look`)."""
    h, w = rays.shape[0], rays.shape[1]
    img = np.empty((h, w, 3), dtype=np.uint8)
    depth = np.empty((h, w), dtype=np.float32)
    floor_xy = np.full((h, w, 2), np.nan, dtype=np.float32)
    tt = np.empty((h, w))
    nrm = np.empty((h, w, 3))
    surface = np.empty((h, w), dtype=np.int64)
    wall_of = np.empty((h, w), dtype=np.int64)
    mat = np.full((h, w), -1, dtype=np.int64)
    # the shell (walls, floor, ceiling, corridor)
    for v in range(h):
        for u in range(w):
            dx, dy, dz = np.float64(rays[v, u, 0]), np.float64(rays[v, u, 1]), np.float64(rays[v, u, 2])
            t, surf, wall, nx, ny, nz = _trace_shell(ox, oy, oz, dx, dy, dz, size, door, corridor)
            tt[v, u] = t
            surface[v, u] = surf
            wall_of[v, u] = wall
            nrm[v, u, 0], nrm[v, u, 1], nrm[v, u, 2] = nx, ny, nz
    # the furniture, each box inside its own pixel bounding box
    for b in range(boxes.shape[0]):
        for v in range(box_bbox[b, 1], box_bbox[b, 3] + 1):
            for u in range(box_bbox[b, 0], box_bbox[b, 2] + 1):
                dx, dy, dz = np.float64(rays[v, u, 0]), np.float64(rays[v, u, 1]), np.float64(rays[v, u, 2])
                tb, bnx, bny, bnz = ray_box(ox, oy, oz, dx, dy, dz, boxes[b])
                if tb < tt[v, u]:
                    tt[v, u] = tb
                    nrm[v, u, 0], nrm[v, u, 1], nrm[v, u, 2] = bnx, bny, bnz
                    mat[v, u] = int(boxes[b, 7])
    # shading
    for v in range(h):
        for u in range(w):
            dx, dy, dz = np.float64(rays[v, u, 0]), np.float64(rays[v, u, 1]), np.float64(rays[v, u, 2])
            t = tt[v, u]
            nx, ny, nz = nrm[v, u, 0], nrm[v, u, 1], nrm[v, u, 2]
            surf, wall, m = surface[v, u], wall_of[v, u], mat[v, u]
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            emissive = False
            if m >= 0:
                r, g, bl = material_albedo(m, px, py, pz, albedo, texture)
                e = irradiance(px, py, pz, nx, ny, nz, lights)
            elif surf == _SURF_FLOOR:
                r, g, bl = floor_albedo(px, py, look)
                e = _lightmap_at(lightmap, cell, px, py)
                floor_xy[v, u, 0] = px
                floor_xy[v, u, 1] = py
            elif surf == _SURF_CEILING:
                r, g, bl, emissive = _ceiling_albedo(px, py, lights)
                e = irradiance(px, py, pz, nx, ny, nz, lights)
            elif surf == _SURF_WALL:
                uu = py if wall < 2 else px
                if wall == 0 and door[0] - 0.07 <= py <= door[1] + 0.07 and pz <= door[2] + 0.07:
                    r, g, bl = 0.93, 0.92, 0.89  # door frame
                else:
                    r, g, bl, emissive = wall_albedo(wall, uu, pz, size[2], decor, look)
                e = irradiance(px, py, pz, nx, ny, nz, lights)
                # darker where walls meet the floor, the ceiling and each other
                corner = min(min(px, size[0] - px), min(py, size[1] - py))
                e *= (1.0 - 0.22 * math.exp(-pz / 0.12)) * (1.0 - 0.18 * math.exp(-(size[2] - pz) / 0.15))
                e *= 1.0 - 0.2 * math.exp(-corner / 0.15)
            elif surf == _SURF_CORRIDOR_FLOOR:
                tile = (px / 0.4 - math.floor(px / 0.4) < 0.02) or (py / 0.4 - math.floor(py / 0.4) < 0.02)
                k = 0.7 if tile else 1.0
                r, g, bl = 0.52 * k, 0.51 * k, 0.49 * k
                e = 0.55
            else:
                r, g, bl = 0.74, 0.72, 0.66
                e = 0.5 if wall != 2 else 0.42
            if emissive:
                s = 1.0
            else:   # lit: the lights' colour and the exposure
                s = e * EXPOSURE * look[21]
                r, g, bl = r * look[17], g * look[18], bl * look[19]
            img[v, u, 0] = min(255.0, bl * s * 255.0)
            img[v, u, 1] = min(255.0, g * s * 255.0)
            img[v, u, 2] = min(255.0, r * s * 255.0)
            depth[v, u] = t
    return img, depth, floor_xy


# -- people ----------------------------------------------------------------------------

@njit(cache=True, nogil=True, error_model="numpy")
def _person_albedo(material, person, kind, p, hx, hy, hz, palette, hair, stripes):
    """Albedo of a body point: palette colour, split rules for the head (hair/face) and
    the pelvis (shirt/trousers), stripes on striped shirts."""
    m = material  # becomes the palette slot
    if m == MAT_HEAD or m == MAT_PELVIS:
        # local coordinates of the hit point in the ellipsoid frame, scaled to the unit sphere
        qx, qy, qz = hx - p[0], hy - p[1], hz - p[2]
        lx = (p[3] * qx + p[6] * qy + p[9] * qz) / p[12]
        lz = (p[5] * qx + p[8] * qy + p[11] * qz) / p[14]
        if m == MAT_HEAD:
            front, back = hair[person, 0], hair[person, 1]
            line = front * max(lx, 0.0) + back * max(-lx, 0.0) + 0.25 * (1.0 - abs(lx))
            m = SLOT_HAIR if lz > line else SLOT_SKIN
        elif lz > 0.42:
            m = SLOT_SHIRT
        elif lz > 0.28:
            m = SLOT_BELT
        else:
            m = SLOT_TROUSERS
    elif m == MAT_SLEEVE:
        m = SLOT_SHIRT
    r, g, b = palette[person, m, 0], palette[person, m, 1], palette[person, m, 2]
    if m == SLOT_SHIRT and stripes[person] > 0.0:
        if math.floor(hz / stripes[person]) % 2 == 0:
            r, g, b = r * 0.55 + 0.4, g * 0.55 + 0.4, b * 0.55 + 0.4
    return r, g, b


@njit(cache=True, nogil=True, error_model="numpy")
def depth_people(zbuf, winner, rays, ox, oy, oz, kinds, prims, bbox, seg2d):
    """Depth pass: ray-cast every body primitive inside its pixel bounding box
    ``[u0, v0, u1, v1]`` (inclusive), depth-tested against ``zbuf`` (the room's
    depth: furniture occludes); the nearest primitive's index goes into ``winner``.

    ``seg2d[i] = [ua, va, ub, vb, radius, valid]`` is a conservative image-space
    capsule around the primitive: pixels farther than ``radius`` from the segment are
    skipped without casting a ray."""
    for i in range(prims.shape[0]):
        u0, v0, u1, v1 = bbox[i, 0], bbox[i, 1], bbox[i, 2], bbox[i, 3]
        if u1 < u0 or v1 < v0:
            continue
        p = prims[i]
        kind = kinds[i]
        prune = seg2d[i, 5] > 0.0
        sa_u, sa_v = seg2d[i, 0], seg2d[i, 1]
        sd_u, sd_v = seg2d[i, 2] - sa_u, seg2d[i, 3] - sa_v
        sl2 = sd_u * sd_u + sd_v * sd_v
        rad2 = seg2d[i, 4] * seg2d[i, 4]
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                if prune:
                    qu, qv = u - sa_u, v - sa_v
                    h = 0.0
                    if sl2 > 1e-9:
                        h = min(1.0, max(0.0, (qu * sd_u + qv * sd_v) / sl2))
                    qu -= h * sd_u
                    qv -= h * sd_v
                    if qu * qu + qv * qv > rad2:
                        continue
                t = ray_primitive(ox, oy, oz, np.float64(rays[v, u, 0]), np.float64(rays[v, u, 1]),
                                  np.float64(rays[v, u, 2]), kind, p)
                if t < zbuf[v, u]:
                    zbuf[v, u] = t
                    winner[v, u] = i


@njit(cache=True, nogil=True, error_model="numpy")
def shade_people(img, label, zbuf, winner, area, rays, ox, oy, oz, kinds, prims, owner, material,
                 ids, palette, hair, stripes, lights, look):
    """Shading pass over ``area = [u0, v0, u1, v1]``: every pixel a body won gets its
    person's id in ``label`` and its shaded colour (Lambert, the room's lights in their
    colour ``look[17:20]``, the exposure ``look[21]``, BGR)."""
    for v in range(area[1], area[3] + 1):
        for u in range(area[0], area[2] + 1):
            i = winner[v, u]
            if i < 0:
                continue
            winner[v, u] = -1  # leave the buffer clean for the next frame
            person = owner[i]
            label[v, u] = ids[person]
            p = prims[i]
            kind = kinds[i]
            t = np.float64(zbuf[v, u])
            hx = ox + t * np.float64(rays[v, u, 0])
            hy = oy + t * np.float64(rays[v, u, 1])
            hz = oz + t * np.float64(rays[v, u, 2])
            nx, ny, nz = primitive_normal(kind, p, hx, hy, hz)
            r, g, b = _person_albedo(material[i], person, kind, p, hx, hy, hz, palette, hair, stripes)
            s = irradiance(hx, hy, hz, nx, ny, nz, lights) * EXPOSURE * look[21] * 255.0
            img[v, u, 0] = min(255.0, b * look[19] * s)
            img[v, u, 1] = min(255.0, g * look[18] * s)
            img[v, u, 2] = min(255.0, r * look[17] * s)


@njit(cache=True, nogil=True, error_model="numpy")
def shadow_map(smap, cell, spheres, owner, n_people, lights, lightmap, lm_cell, work):
    """Multiply into ``smap`` (reset to 1 by the caller) the soft floor shadow of each
    person. For every ceiling panel each body sphere casts a soft disc on the floor:
    centred where the line from the light through the sphere's centre meets the floor,
    its radius magnified by ``h_L / (h_L - z)`` and its penumbra widened by the panel
    size times ``z / (h_L - z)`` (an area light). The discs are splatted into
    ``work[0]`` (light left per panel), the light lost is weighted by the panel's
    irradiance; the spheres near the floor add an ambient occlusion (contact shadow),
    ``r^2 cos / d^2`` per sphere, splatted into ``work[2]``."""
    ny, nx = smap.shape
    lit = work[0]
    blocked = work[1]
    amb = work[2]
    for person in range(n_people):
        blocked[:, :] = 0.0
        amb[:, :] = 0.0
        j_lo, j_hi, i_lo, i_hi = ny, -1, nx, -1
        for l in range(lights.shape[0]):
            lx, ly, hl, half = lights[l, 0], lights[l, 1], lights[l, 2], 0.5 * lights[l, 4]
            lit[:, :] = 1.0
            a0, a1, b0, b1 = ny, -1, nx, -1
            for s in range(spheres.shape[0]):
                if owner[s] != person:
                    continue
                cx, cy, cz, r = spheres[s, 0], spheres[s, 1], spheres[s, 2], spheres[s, 3]
                if cz >= hl - 0.05:
                    continue
                mag = hl / (hl - cz)
                fx, fy = lx + (cx - lx) * mag, ly + (cy - ly) * mag
                rf = r * mag
                pw = half * cz / (hl - cz) + 0.01
                strength = min(1.0, (rf / pw) ** 2)
                reach = rf + pw
                j0, j1 = max(0, int((fy - reach) / cell)), min(ny - 1, int((fy + reach) / cell) + 1)
                i0, i1 = max(0, int((fx - reach) / cell)), min(nx - 1, int((fx + reach) / cell) + 1)
                a0, a1, b0, b1 = min(a0, j0), max(a1, j1), min(b0, i0), max(b1, i1)
                for j in range(j0, j1 + 1):
                    dy = j * cell - fy
                    for i in range(i0, i1 + 1):
                        dx = i * cell - fx
                        off = math.sqrt(dx * dx + dy * dy)
                        occ = strength * min(1.0, max(0.0, (rf + pw - off) / (2.0 * pw)))
                        if occ > 0.0:
                            lit[j, i] *= 1.0 - occ
            for j in range(a0, a1 + 1):
                y = j * cell
                for i in range(b0, b1 + 1):
                    if lit[j, i] < 1.0:
                        x = i * cell
                        ddx, ddy = lx - x, ly - y
                        d2 = ddx * ddx + ddy * ddy + hl * hl
                        direct = lights[l, 3] * hl * hl / d2 / (d2 * 0.55 + 0.25)
                        blocked[j, i] += direct * (1.0 - lit[j, i])
            j_lo, j_hi, i_lo, i_hi = min(j_lo, a0), max(j_hi, a1), min(i_lo, b0), max(i_hi, b1)
        for s in range(spheres.shape[0]):
            if owner[s] != person:
                continue
            cx, cy, cz, r = spheres[s, 0], spheres[s, 1], spheres[s, 2], spheres[s, 3]
            if cz > 0.9:
                continue
            reach = 0.7
            dmax = math.sqrt(reach * reach + cz * cz)
            base = r * r * cz / (dmax * dmax * dmax)  # so the term fades to zero at the reach
            j0, j1 = max(0, int((cy - reach) / cell)), min(ny - 1, int((cy + reach) / cell) + 1)
            i0, i1 = max(0, int((cx - reach) / cell)), min(nx - 1, int((cx + reach) / cell) + 1)
            j_lo, j_hi, i_lo, i_hi = min(j_lo, j0), max(j_hi, j1), min(i_lo, i0), max(i_hi, i1)
            for j in range(j0, j1 + 1):
                dy = cy - j * cell
                for i in range(i0, i1 + 1):
                    dx = cx - i * cell
                    d2 = dx * dx + dy * dy + cz * cz
                    if d2 < dmax * dmax:
                        amb[j, i] += r * r / d2 * cz / math.sqrt(d2) - base
        for j in range(j_lo, j_hi + 1):
            for i in range(i_lo, i_hi + 1):
                if blocked[j, i] > 0.0 or amb[j, i] > 0.0:
                    e = _lightmap_at(lightmap, lm_cell, i * cell, j * cell)
                    ambient = 0.6 * e  # light from the whole ceiling and walls (indirect)
                    f = 1.0 - (blocked[j, i] + ambient * min(3.0 * amb[j, i], 0.8)) / e
                    smap[j, i] *= max(0.2, f)


@njit(cache=True, nogil=True, error_model="numpy")
def apply_shadows(img, static, floor_pix, floor_xy, smap, cell):
    """Darken the floor pixels by the shadow map (bilinear)."""
    w = img.shape[1]
    for k in range(floor_pix.shape[0]):
        f = _lightmap_at(smap, cell, floor_xy[k, 0], floor_xy[k, 1])
        if f < 0.998:
            idx = floor_pix[k]
            v, u = idx // w, idx % w
            for c in range(3):
                img[v, u, c] = static[v, u, c] * f


@njit(cache=True, nogil=True, error_model="numpy")
def finish(img, out, gain, noise, offset):
    """Sensor: ``out = clip(img * gain + noise)`` (noise from a pre-drawn bank)."""
    flat_in = img.reshape(-1)
    flat_out = out.reshape(-1)
    n = flat_in.shape[0]
    for k in range(n):
        v = flat_in[k] * gain + noise[offset + k]
        if v < 0.0:
            v = 0.0
        elif v > 255.0:
            v = 255.0
        flat_out[k] = np.uint8(v + 0.5)


def shadow_spheres(kinds: np.ndarray, prims: np.ndarray, owner: np.ndarray):
    """Spheres approximating each body primitive, for shadows: ``(S, 4)`` and owners."""
    out, own = [], []
    for kind, p, o in zip(kinds, prims, owner):
        if kind == CONE:
            a, b, ra, rb = p[0:3], p[3:6], p[6], p[7]
            length = float(np.linalg.norm(b - a))
            n = max(2, int(math.ceil(length / 0.11)) + 1)
            for s in np.linspace(0.0, 1.0, n):
                out.append([*(a + s * (b - a)), ra + s * (rb - ra)])
                own.append(o)
        else:
            out.append([p[0], p[1], p[2], float(np.prod(p[12:15]) ** (1.0 / 3.0))])
            own.append(o)
    return np.array(out, dtype=np.float64).reshape(-1, 4), np.array(own, dtype=np.int64)


# -- one camera ----------------------------------------------------------------------

_LIGHTMAPS: dict = {}


class RoomLighting:
    """The room's lights and floor light map (shared by all cameras of a room)."""

    def __init__(self, room: Room):
        self.room = room
        self.lights = np.ascontiguousarray(room.lights, dtype=np.float64)
        self.cell = LIGHTMAP_CELL
        key = (room.size, self.lights.tobytes(), np.ascontiguousarray(room.boxes).tobytes())
        if key not in _LIGHTMAPS:  # the same room twice in a process: computed once
            _LIGHTMAPS[key] = floor_lightmap(room.size[0], room.size[1], self.cell, self.lights,
                                             np.ascontiguousarray(room.boxes))
        self.lightmap = _LIGHTMAPS[key]
        self.shadow_cell = 0.04
        self.shadow = np.ones_like(self.lightmap)
        self._work = np.zeros((3,) + self.shadow.shape, dtype=np.float32)

    def people_shadows(self, kinds, prims, owner, n_people) -> np.ndarray:
        """The floor shadow map of this frame's people (1 = unshadowed)."""
        self.shadow.fill(1.0)
        if n_people:
            spheres, sowner = shadow_spheres(kinds, prims, owner)
            shadow_map(self.shadow, self.shadow_cell, spheres, sowner, n_people, self.lights,
                       self.lightmap, self.cell, self._work)
        return self.shadow


class CameraView:
    """One camera looking at a room: precomputed pixel rays and the empty room image."""

    def __init__(self, camera, room: Room, lighting: RoomLighting):
        self.camera = camera
        self.room = room
        self.lighting = lighting
        h, w = camera.height, camera.width
        v, u = np.mgrid[0:h, 0:w]
        pix = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        self.rays = np.ascontiguousarray(camera.pixel_rays(pix).reshape(h, w, 3).astype(np.float32))
        self.origin = camera.centre.astype(np.float64)
        ox, oy, oz = (float(c) for c in self.origin)
        self.r_fold = _fold_radius(camera.dist)
        boxes = np.ascontiguousarray(room.boxes)
        c, s = np.abs(np.cos(boxes[:, 6])), np.abs(np.sin(boxes[:, 6]))
        half = np.stack([c * boxes[:, 3] + s * boxes[:, 4], s * boxes[:, 3] + c * boxes[:, 4], boxes[:, 5]], axis=1)
        box_bbox = self._project_bounds(boxes[:, :3] - half, boxes[:, :3] + half)
        self.static, depth, floor_xy = trace_room(
            self.rays, ox, oy, oz, np.array(room.size, dtype=np.float64),
            np.array(room.door, dtype=np.float64), np.array(room.corridor, dtype=np.float64),
            boxes, box_bbox, np.ascontiguousarray(room.decor), lighting.lights,
            lighting.lightmap, lighting.cell, MATERIAL_ALBEDO, MATERIAL_TEXTURE,
            np.ascontiguousarray(room.look, dtype=np.float64))
        self.depth = depth
        floor = ~np.isnan(floor_xy[:, :, 0])
        self.floor_pix = np.flatnonzero(floor.ravel()).astype(np.int64)
        self.floor_xy = np.ascontiguousarray(floor_xy.reshape(-1, 2)[self.floor_pix])
        self._look = np.ascontiguousarray(room.look, dtype=np.float64)
        self._img = np.empty_like(self.static)
        self._zbuf = np.empty_like(self.depth)
        self._winner = np.full(self.depth.shape, -1, dtype=np.int32)

    @property
    def background(self) -> np.ndarray:
        """The empty room as this camera sees it (BGR uint8, no noise)."""
        return self.static.copy()

    def image_capsules(self, kinds: np.ndarray, prims: np.ndarray) -> np.ndarray:
        """A conservative image-space capsule around each primitive (see
        :func:`raster_people`): the projected axis (cone) or centre (ellipsoid) and a
        radius ``f r (1 + r_n^2) / z + 2`` px, which bounds the perspective image of a
        sphere of radius ``r`` at normalised radius ``r_n`` (barrel distortion only
        shrinks it); invalid (no pruning) when a point is near or behind the camera."""
        m = prims.shape[0]
        ends = np.empty((m, 2, 3))
        rad = np.empty(m)
        cone = kinds == CONE
        ends[:, 0] = prims[:, 0:3]
        ends[:, 1] = np.where(cone[:, None], prims[:, 3:6], prims[:, 0:3])
        rad[:] = np.where(cone, np.maximum(prims[:, 6], prims[:, 7]), prims[:, 12:15].max(axis=1))
        cam = self.camera
        pc = ends.reshape(-1, 3) @ cam.R.T + cam.t
        z = pc[:, 2]
        ok = z > 0.2
        zs = np.where(ok, z, 1.0)
        xn, yn = pc[:, 0] / zs, pc[:, 1] / zs
        rn2 = xn * xn + yn * yn
        ok &= rn2 < (0.9 * self.r_fold) ** 2
        xd, yd = cam.distort(xn, yn)
        K = cam.K
        uv = np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1).reshape(m, 2, 2)
        f = max(K[0, 0], K[1, 1])
        rpx = (f * np.repeat(rad, 2) * (1.0 + rn2) / zs).reshape(m, 2).max(axis=1) + 2.0
        out = np.empty((m, 6))
        out[:, 0:2] = uv[:, 0]
        out[:, 2:4] = uv[:, 1]
        out[:, 4] = rpx
        out[:, 5] = ok.reshape(m, 2).all(axis=1)
        return out

    def bounding_boxes(self, kinds: np.ndarray, prims: np.ndarray) -> np.ndarray:
        """Pixel bounding box ``[u0, v0, u1, v1]`` of each primitive (``u1 < u0``: not seen)."""
        m = prims.shape[0]
        lo = np.empty((m, 3))
        hi = np.empty((m, 3))
        for i in range(m):
            k, p = kinds[i], prims[i]
            if k == CONE:
                lo[i] = np.minimum(p[0:3] - p[6], p[3:6] - p[7])
                hi[i] = np.maximum(p[0:3] + p[6], p[3:6] + p[7])
            else:
                R = p[3:12].reshape(3, 3)
                e = np.sqrt(((R * p[12:15]) ** 2).sum(axis=1))
                lo[i], hi[i] = p[0:3] - e, p[0:3] + e
        return self._project_bounds(lo, hi)

    def _project_bounds(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Pixel bounding boxes of world boxes ``[lo, hi]``: the 27 points of each box's
        lattice are projected; a 2 px margin covers the slight bulge of edges under lens
        distortion. A box reaching behind the camera or past the distortion's fold gets
        the whole image."""
        m = lo.shape[0]
        f = np.array([0.0, 0.5, 1.0])
        fx, fy, fz = np.meshgrid(f, f, f, indexing="ij")
        lattice = np.stack([fx.ravel(), fy.ravel(), fz.ravel()], axis=1)  # (27, 3)
        pts = lo[:, None, :] + lattice[None, :, :] * (hi - lo)[:, None, :]
        cam = self.camera
        pc = pts.reshape(-1, 3) @ cam.R.T + cam.t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn, yn = pc[:, 0] / z, pc[:, 1] / z
        r = np.sqrt(xn * xn + yn * yn)
        bad = (z <= 0.05) | ~(r < 0.95 * self.r_fold)
        xd, yd = cam.distort(np.where(bad, 0.0, xn), np.where(bad, 0.0, yn))
        K = cam.K
        uu = (K[0, 0] * xd + K[0, 1] * yd + K[0, 2]).reshape(m, 27)
        vv = (K[1, 1] * yd + K[1, 2]).reshape(m, 27)
        bad = bad.reshape(m, 27).any(axis=1)
        out = np.empty((m, 4), dtype=np.int64)
        out[:, 0] = np.floor(uu.min(axis=1)) - 2
        out[:, 1] = np.floor(vv.min(axis=1)) - 2
        out[:, 2] = np.ceil(uu.max(axis=1)) + 2
        out[:, 3] = np.ceil(vv.max(axis=1)) + 2
        out[bad] = (0, 0, cam.width - 1, cam.height - 1)
        out[:, 0] = np.maximum(out[:, 0], 0)
        out[:, 1] = np.maximum(out[:, 1], 0)
        out[:, 2] = np.minimum(out[:, 2], cam.width - 1)
        out[:, 3] = np.minimum(out[:, 3], cam.height - 1)
        return out

    def render(self, bodies, shadow: np.ndarray | None, *, gain: float = 1.0, noise=None,
               noise_offset: int = 0, blur: bool = True):
        """One frame: ``(bgr image, int16 label image)``; ``bodies`` a
        :class:`~app.simulation.body.FrameBodies`."""
        img = self._img
        np.copyto(img, self.static)
        zbuf = self._zbuf
        np.copyto(zbuf, self.depth)
        label = np.full(self.depth.shape, -1, dtype=np.int16)
        if shadow is not None and len(bodies.ids):
            apply_shadows(img, self.static, self.floor_pix, self.floor_xy, shadow,
                          self.lighting.shadow_cell)
        if len(bodies.kinds):
            bbox = self.bounding_boxes(bodies.kinds, bodies.prims)
            seg2d = self.image_capsules(bodies.kinds, bodies.prims)
            ox, oy, oz = (float(c) for c in self.origin)
            depth_people(zbuf, self._winner, self.rays, ox, oy, oz, bodies.kinds, bodies.prims, bbox, seg2d)
            seen = bbox[:, 2] >= bbox[:, 0]
            if seen.any():
                area = np.array([bbox[seen, 0].min(), bbox[seen, 1].min(), bbox[seen, 2].max(),
                                 bbox[seen, 3].max()], dtype=np.int64)
                shade_people(img, label, zbuf, self._winner, area, self.rays, ox, oy, oz, bodies.kinds,
                             bodies.prims, bodies.owner, bodies.material, bodies.ids, bodies.palette,
                             bodies.hair, bodies.stripes, self.lighting.lights, self._look)
        out = np.empty_like(img)
        src = cv2.GaussianBlur(img, (3, 3), 0.55) if blur else img
        if noise is None:
            np.copyto(out, src)
            if gain != 1.0:
                out[:] = np.clip(src * gain + 0.5, 0, 255).astype(np.uint8)
        else:
            finish(src, out, float(gain), noise, int(noise_offset))
        return out, label


def _fold_radius(dist) -> float:
    """Undistorted radius where the radial model folds back (d r_d / d r = 0)."""
    k1, k2, _, _, k3 = (float(d) for d in dist)
    r = np.linspace(0.0, 6.0, 6001)
    deriv = 1.0 + 3.0 * k1 * r ** 2 + 5.0 * k2 * r ** 4 + 7.0 * k3 * r ** 6
    bad = np.nonzero(deriv <= 0.0)[0]
    return float(r[bad[0]]) if len(bad) else 6.0
