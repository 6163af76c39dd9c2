"""Synthetic scenes with exact silhouettes, for the reconstruction's tests and benchmark.

A person is a union of spheres (chains of spheres along the limbs, two columns for the
torso, one for the head), so "is this point inside the body" and "which sphere does this
pixel's ray hit first" are exact. Each sphere belongs to a body part and the colour of a
hit point depends on the part and on whether it lies in front of or behind the person's
frontal plane (a shirt with a red front and a blue back shows the voxel-colouring bias
of thesis §2.2.4 / Fig. 2.4). Rays are cast through every pixel with
:meth:`Camera.pixel_rays`, so the masks include the lens distortion.

This module is independent of the simulator (``app.simulation``), which makes the
realistic scenes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from calibration import Calibration, Camera

__all__ = ["Body", "person", "Scene", "room_calibration", "meeting_scene", "inside"]

# parts
HEAD, TORSO, L_ARM, R_ARM, L_LEG, R_LEG = range(6)


@dataclass
class Body:
    """Spheres (M, 4) ``x y z r``, their part (M,), the person's ground position and facing."""

    spheres: np.ndarray
    parts: np.ndarray
    centre: np.ndarray
    facing: np.ndarray
    front: np.ndarray = field(default_factory=lambda: np.zeros((6, 3), np.uint8))   # BGR per part
    back: np.ndarray = field(default_factory=lambda: np.zeros((6, 3), np.uint8))


def _chain(a, b, r, step=0.5):
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / (r * step))) + 1)
    t = np.linspace(0, 1, n)[:, None]
    p = a + t * (b - a)
    return np.concatenate([p, np.full((n, 1), r)], axis=1)


def person(x: float, y: float, facing_deg: float = 0.0, height: float = 1.75, arm_swing: float = 0.0,
           arm_raise: float = 0.0, front_bgr=(30, 30, 220), back_bgr=(220, 40, 30)) -> Body:
    """A standing person at ``(x, y)`` facing ``facing_deg`` (0: +x), ``height`` m tall.

    ``arm_swing`` (m) moves the hands forward/backward (left/right opposite), ``arm_raise``
    (m) lifts the right hand sideways. The torso is ``front_bgr`` in front, ``back_bgr``
    behind (BGR); head, arms and legs have their own colours.
    """
    k = height / 1.75
    f = np.array([np.cos(np.radians(facing_deg)), np.sin(np.radians(facing_deg)), 0.0])
    lat = np.array([-f[1], f[0], 0.0])          # the person's left
    base = np.array([x, y, 0.0])
    up = np.array([0, 0, 1.0])

    def at(fwd, left, z):
        return base + fwd * f + left * lat + z * k * up

    spheres, parts = [], []

    def add(chain, part):
        spheres.append(chain)
        parts.append(np.full(len(chain), part))

    add(_chain(at(0, 0, 1.60), at(0, 0, 1.64), 0.105 * k), HEAD)
    for side in (-1, 1):
        add(_chain(at(0, 0.07 * side, 0.98), at(0, 0.08 * side, 1.40), 0.125 * k), TORSO)
    add(_chain(at(0, 0, 1.40), at(0, 0, 1.50), 0.06 * k), TORSO)         # neck
    for side, part in ((1, L_ARM), (-1, R_ARM)):
        swing = arm_swing * side
        lift = arm_raise if part == R_ARM else 0.0
        shoulder = at(0, 0.22 * side, 1.40)
        elbow = at(0.5 * swing, (0.25 + 0.5 * lift) * side, 1.12 + 0.4 * lift)
        hand = at(swing, (0.27 + lift) * side, 0.86 + 0.5 * lift)
        add(np.concatenate([_chain(shoulder, elbow, 0.05 * k), _chain(elbow, hand, 0.045 * k)]), part)
    for side, part in ((1, L_LEG), (-1, R_LEG)):
        add(np.concatenate([_chain(at(0, 0.09 * side, 0.92), at(0, 0.10 * side, 0.50), 0.075 * k),
                            _chain(at(0, 0.10 * side, 0.50), at(0.03, 0.10 * side, 0.07), 0.055 * k)]), part)
    front = np.array([[150, 180, 230], front_bgr, [140, 170, 220], [140, 170, 220], [90, 60, 40], [90, 60, 40]],
                     np.uint8)
    back = np.array([[40, 50, 60], back_bgr, [140, 170, 220], [140, 170, 220], [90, 60, 40], [90, 60, 40]],
                    np.uint8)
    return Body(np.concatenate(spheres), np.concatenate(parts).astype(np.int64), base, f, front, back)


@njit(cache=True, nogil=True)
def _inside(points, spheres, out):
    for n in range(points.shape[0]):
        hit = False
        for m in range(spheres.shape[0]):
            dx = points[n, 0] - spheres[m, 0]
            dy = points[n, 1] - spheres[m, 1]
            dz = points[n, 2] - spheres[m, 2]
            if dx * dx + dy * dy + dz * dz <= spheres[m, 3] * spheres[m, 3]:
                hit = True
                break
        out[n] = hit


def inside(points: np.ndarray, bodies: list[Body]) -> np.ndarray:
    """Boolean (N,): the points lie inside some body."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(pts), dtype=np.bool_)
    for b in bodies:
        tmp = np.empty(len(pts), dtype=np.bool_)
        _inside(pts, b.spheres, tmp)
        out |= tmp
    return out


@njit(cache=True, nogil=True)
def _nearest(points, spheres, out_idx, out_dist):
    for n in range(points.shape[0]):
        best = np.inf
        arg = -1
        for m in range(spheres.shape[0]):
            dx = points[n, 0] - spheres[m, 0]
            dy = points[n, 1] - spheres[m, 1]
            dz = points[n, 2] - spheres[m, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz) - spheres[m, 3]
            if d < best:
                best = d
                arg = m
        out_idx[n] = arg
        out_dist[n] = best


@njit(cache=True, nogil=True)
def _cast(origin, dirs, spheres, body_of, bounds, out_t, out_sphere):
    """Nearest sphere hit by each ray (t, sphere index; -1 when none)."""
    nb = bounds.shape[0]
    for n in range(dirs.shape[0]):
        dx, dy, dz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
        best = out_t[n]
        hit = out_sphere[n]
        for b in range(nb):
            # bounding sphere of body b: skip it when the ray misses
            ox = origin[0] - bounds[b, 0]
            oy = origin[1] - bounds[b, 1]
            oz = origin[2] - bounds[b, 2]
            bb = ox * dx + oy * dy + oz * dz
            cc = ox * ox + oy * oy + oz * oz - bounds[b, 3] * bounds[b, 3]
            if bb * bb - cc < 0:
                continue
            for m in range(int(bounds[b, 4]), int(bounds[b, 5])):
                ox = origin[0] - spheres[m, 0]
                oy = origin[1] - spheres[m, 1]
                oz = origin[2] - spheres[m, 2]
                bb = ox * dx + oy * dy + oz * dz
                cc = ox * ox + oy * oy + oz * oz - spheres[m, 3] * spheres[m, 3]
                disc = bb * bb - cc
                if disc < 0:
                    continue
                t = -bb - np.sqrt(disc)
                if 0 < t < best:
                    best = t
                    hit = m
        out_t[n] = best
        out_sphere[n] = hit


class Scene:
    """Bodies in a room, rendered exactly into any camera: masks and BGR images."""

    def __init__(self, bodies: list[Body], background_bgr=(128, 128, 128)):
        self.bodies = list(bodies)
        self.background = np.asarray(background_bgr, np.uint8)
        self.spheres = np.concatenate([b.spheres for b in self.bodies])
        self.body_of = np.concatenate([np.full(len(b.spheres), i) for i, b in enumerate(self.bodies)])
        self.part_of = np.concatenate([b.parts for b in self.bodies])
        bounds = []
        start = 0
        for b in self.bodies:
            c = b.spheres[:, :3].mean(axis=0)
            r = float(np.max(np.linalg.norm(b.spheres[:, :3] - c, axis=1) + b.spheres[:, 3]))
            bounds.append([*c, r, start, start + len(b.spheres)])
            start += len(b.spheres)
        self.bounds = np.asarray(bounds, dtype=np.float64)

    _rays: dict = {}

    @classmethod
    def _pixel_rays(cls, cam: Camera) -> np.ndarray:
        key = (cam.name, cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), cam.R.tobytes(), cam.t.tobytes())
        rays = cls._rays.get(key)
        if rays is None:
            u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
            rays = np.ascontiguousarray(cam.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1)))
            if len(cls._rays) > 64:
                cls._rays.clear()
            cls._rays[key] = rays
        return rays

    def render(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Mask (h, w) bool and BGR image (h, w, 3) uint8 of the scene seen by ``cam``."""
        rays = self._pixel_rays(cam)
        n = len(rays)
        t = np.full(n, np.inf)
        sph = np.full(n, -1, dtype=np.int64)
        origin = np.asarray(cam.centre, dtype=np.float64)
        _cast(origin, rays, self.spheres, self.body_of, self.bounds, t, sph)
        hit = sph >= 0
        img = np.empty((n, 3), np.uint8)
        img[:] = self.background
        hs = sph[hit]
        points = origin + t[hit, None] * rays[hit]
        body = self.body_of[hs]
        part = self.part_of[hs]
        centres = np.stack([b.centre for b in self.bodies])[body]
        facing = np.stack([b.facing for b in self.bodies])[body]
        in_front = np.einsum("ij,ij->i", (points - centres)[:, :2], facing[:, :2]) >= 0
        fronts = np.stack([b.front for b in self.bodies])
        backs = np.stack([b.back for b in self.bodies])
        img[hit] = np.where(in_front[:, None], fronts[body, part], backs[body, part])
        return hit.reshape(cam.height, cam.width), img.reshape(cam.height, cam.width, 3)

    def frame(self, cameras: list[Camera]) -> tuple[dict, dict]:
        """Masks and images of every camera, keyed by camera name."""
        masks, images = {}, {}
        for c in cameras:
            masks[c.name], images[c.name] = self.render(c)
        return masks, images

    def inside(self, points: np.ndarray) -> np.ndarray:
        return inside(points, self.bodies)

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each point the sphere whose surface is nearest (signed distance, < 0 inside):
        ``(sphere index (N,), signed distance (N,))``."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        idx = np.empty(len(p), dtype=np.int64)
        dist = np.empty(len(p))
        _nearest(p, self.spheres, idx, dist)
        return idx, dist

    def part_at(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) body and part of the sphere containing (or nearest to the surface of)
        each point."""
        m, _ = self.nearest(points)
        return np.stack([self.body_of[m], self.part_of[m]], axis=1)


def room_calibration(n_cameras: int = 5, width: int = 640, height: int = 480, room=(5.0, 4.0, 2.5),
                     fps: float = 25.0, hfov_deg: float = 80.0, dist=(-0.12, 0.03, 0.0, 0.0, 0.0)) -> Calibration:
    """``n_cameras`` cameras high on the walls of a ``room`` (x, y, z metres) looking at its
    middle, with barrel distortion (a smart room like the thesis's CHIL room)."""
    rx, ry, rz = room
    cams = []
    for i in range(n_cameras):
        a = 2 * np.pi * i / n_cameras + 0.3
        pos = [rx / 2 + 0.48 * rx * np.cos(a), ry / 2 + 0.48 * ry * np.sin(a), rz - 0.15]
        cams.append(Camera.look_at(f"cam{i}", pos, [rx / 2, ry / 2, 0.8], width, height, hfov_deg=hfov_deg,
                                   dist=list(dist)))
    return Calibration(fps, np.zeros(3), np.array(room, dtype=np.float64), tuple(cams))


def meeting_scene(t: float = 0.0, room=(5.0, 4.0, 2.5)) -> Scene:
    """Three people in a room at time ``t`` (s): two walking slowly, one gesturing."""
    rx, ry, _ = room
    p1 = person(1.4 + 0.5 * np.sin(0.4 * t), 1.3, facing_deg=20, arm_swing=0.2 * np.sin(3 * t))
    p2 = person(3.5, 2.6 + 0.4 * np.sin(0.5 * t + 1), facing_deg=200, height=1.65,
                arm_raise=0.25 + 0.2 * np.sin(2 * t), front_bgr=(40, 200, 40), back_bgr=(200, 200, 40))
    p3 = person(2.4 + 0.3 * np.cos(0.3 * t), 3.0 - 0.2 * t % 1.0, facing_deg=-80, height=1.82,
                arm_swing=0.15 * np.sin(2.5 * t), front_bgr=(200, 60, 200), back_bgr=(20, 120, 240))
    return Scene([p1, p2, p3])
