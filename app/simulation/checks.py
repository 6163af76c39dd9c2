"""Geometric checks of simulated scenes: do bodies pass through furniture or through
one another? (Used by the tests; handy when writing new scenes.)

Bodies are sampled on their surfaces (round cones: rings along the axis plus the two
end caps; ellipsoids: a Fibonacci sphere mapped onto them); a body point inside a
furniture box or inside another person's primitive is an intersection.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.simulation.geometry import CONE, inside_primitive, point_in_box

__all__ = ["surface_points", "points_in_boxes", "points_in_primitives", "scene_intersections"]


@njit(cache=True, nogil=True)
def _counts(kinds, rows, spacing):
    counts = np.zeros((rows.shape[0], 3), dtype=np.int64)  # rings, points per ring, cap points
    for m in range(rows.shape[0]):
        p = rows[m]
        if kinds[m] == CONE:
            L = math.sqrt((p[3] - p[0]) ** 2 + (p[4] - p[1]) ** 2 + (p[5] - p[2]) ** 2)
            rmax = max(p[6], p[7])
            counts[m, 0] = max(2, int(L / spacing) + 1)
            counts[m, 1] = max(8, int(2 * math.pi * rmax / spacing))
            counts[m, 2] = max(12, int(4 * math.pi * rmax * rmax / spacing ** 2))
        else:
            area = 4 * math.pi * (p[12] * p[13] * p[14]) ** (2.0 / 3.0)
            counts[m, 2] = max(20, int(area / spacing ** 2))
    return counts


@njit(cache=True, nogil=True)
def _fill(kinds, rows, counts, out):
    golden = math.pi * (1.0 + math.sqrt(5.0))
    k = 0
    for m in range(rows.shape[0]):
        p = rows[m]
        if kinds[m] == CONE:
            ax, ay, az = p[0], p[1], p[2]
            wx, wy, wz = p[3] - ax, p[4] - ay, p[5] - az
            L = math.sqrt(wx * wx + wy * wy + wz * wz)
            if L > 1e-9:
                wx, wy, wz = wx / L, wy / L, wz / L
            else:
                wx, wy, wz = 0.0, 0.0, 1.0
            # u: perpendicular to w
            if abs(wx) < 0.9:
                ux, uy, uz = 0.0, wz, -wy      # w x (1, 0, 0)
            else:
                ux, uy, uz = -wz, 0.0, wx      # w x (0, 1, 0)
            n = math.sqrt(ux * ux + uy * uy + uz * uz)
            ux, uy, uz = ux / n, uy / n, uz / n
            vx, vy, vz = wy * uz - wz * uy, wz * ux - wx * uz, wx * uy - wy * ux
            nt, nphi, ncap = counts[m, 0], counts[m, 1], counts[m, 2]
            for i in range(nt):
                t = i / (nt - 1)
                r = p[6] + (p[7] - p[6]) * t
                cx, cy, cz = ax + t * L * wx, ay + t * L * wy, az + t * L * wz
                for j in range(nphi):
                    phi = 2 * math.pi * j / nphi
                    c, s = math.cos(phi), math.sin(phi)
                    out[k, 0] = cx + r * (c * ux + s * vx)
                    out[k, 1] = cy + r * (c * uy + s * vy)
                    out[k, 2] = cz + r * (c * uz + s * vz)
                    k += 1
            for end in range(2):
                cx, cy, cz, r = p[3 * end], p[3 * end + 1], p[3 * end + 2], p[6 + end]
                for i in range(ncap):
                    z = 1.0 - 2.0 * (i + 0.5) / ncap
                    rho = math.sqrt(max(0.0, 1.0 - z * z))
                    th = golden * (i + 0.5)
                    out[k, 0] = cx + r * rho * math.cos(th)
                    out[k, 1] = cy + r * rho * math.sin(th)
                    out[k, 2] = cz + r * z
                    k += 1
        else:
            n = counts[m, 2]
            for i in range(n):
                z = 1.0 - 2.0 * (i + 0.5) / n
                rho = math.sqrt(max(0.0, 1.0 - z * z))
                th = golden * (i + 0.5)
                lx, ly, lz = rho * math.cos(th) * p[12], rho * math.sin(th) * p[13], z * p[14]
                out[k, 0] = p[0] + p[3] * lx + p[4] * ly + p[5] * lz
                out[k, 1] = p[1] + p[6] * lx + p[7] * ly + p[8] * lz
                out[k, 2] = p[2] + p[9] * lx + p[10] * ly + p[11] * lz
                k += 1
    return k


def surface_points(kinds: np.ndarray, rows: np.ndarray, spacing: float = 0.015) -> np.ndarray:
    """Points ``(N, 3)`` on the surfaces of the primitives, about ``spacing`` apart."""
    kinds = np.ascontiguousarray(kinds, dtype=np.int64)
    rows = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, rows.shape[-1] if rows.ndim > 1 else 16)
    counts = _counts(kinds, rows, float(spacing))
    total = int((counts[:, 0] * counts[:, 1] + np.where(kinds == CONE, 2, 1) * counts[:, 2]).sum())
    out = np.empty((total, 3))
    n = _fill(kinds, rows, counts, out)
    return out[:n]


@njit(cache=True, nogil=True)
def _count_in_boxes(points, boxes, margin):
    n = 0
    for i in range(points.shape[0]):
        for b in range(boxes.shape[0]):
            if point_in_box(points[i, 0], points[i, 1], points[i, 2], boxes[b], margin):
                n += 1
                break
    return n


@njit(cache=True, nogil=True)
def _count_in_prims(points, kinds, rows, margin):
    n = 0
    for i in range(points.shape[0]):
        for m in range(rows.shape[0]):
            if inside_primitive(points[i, 0], points[i, 1], points[i, 2], kinds[m], rows[m], margin):
                n += 1
                break
    return n


def _box_bounds(boxes: np.ndarray):
    c, s = np.abs(np.cos(boxes[:, 6])), np.abs(np.sin(boxes[:, 6]))
    ex = c * boxes[:, 3] + s * boxes[:, 4]
    ey = s * boxes[:, 3] + c * boxes[:, 4]
    half = np.stack([ex, ey, boxes[:, 5]], axis=1)
    return boxes[:, :3] - half, boxes[:, :3] + half


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, margin: float = 0.0) -> int:
    """How many points lie inside a furniture box (grown by ``margin``)."""
    if len(points) == 0 or len(boxes) == 0:
        return 0
    lo, hi = _box_bounds(boxes)
    near = np.all((hi + margin >= points.min(axis=0)) & (lo - margin <= points.max(axis=0)), axis=1)
    if not near.any():
        return 0
    return int(_count_in_boxes(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(boxes[near]),
                               margin))


def points_in_primitives(points: np.ndarray, kinds: np.ndarray, rows: np.ndarray, margin: float = 0.0) -> int:
    """How many points lie inside one of the primitives (grown by ``margin``)."""
    if len(kinds) == 0 or len(points) == 0:
        return 0
    from app.simulation.geometry import primitive_bounds
    b = np.empty(6)
    lo, hi = np.empty((len(kinds), 3)), np.empty((len(kinds), 3))
    for m in range(len(kinds)):
        primitive_bounds(int(kinds[m]), rows[m], b)
        lo[m], hi[m] = b[:3] - margin, b[3:] + margin
    plo, phi = points.min(axis=0), points.max(axis=0)
    near = np.all((hi >= plo) & (lo <= phi), axis=1)
    if not near.any():
        return 0
    glo, ghi = lo[near].min(axis=0), hi[near].max(axis=0)
    inside = np.all((points >= glo) & (points <= ghi), axis=1)
    if not inside.any():
        return 0
    return int(_count_in_prims(np.ascontiguousarray(points[inside], dtype=np.float64),
                               np.ascontiguousarray(kinds[near]), np.ascontiguousarray(rows[near]), margin))


def scene_intersections(simulator, step_s: float = 0.2, spacing: float = 0.02, margin: float = 0.0,
                        limits: bool = True):
    """Scan a simulator's scene every ``step_s`` seconds; returns a list of problems
    (strings): a person in furniture, two people intersecting, a joint angle outside
    the human limits. Empty when all is well."""
    from app.simulation.body import DOFS, LIMITS_HI, LIMITS_LO

    problems = []
    boxes = np.ascontiguousarray(simulator.room.boxes)
    n = simulator.frame_count()
    step = max(1, int(round(step_s * simulator.fps)))
    for i in range(0, n, step):
        people = simulator.people(i)
        pts = [surface_points(p["kinds"], p["rows"], spacing) for p in people]
        for p, q in zip(people, pts):
            k = points_in_boxes(q, boxes, margin)
            if k:
                problems.append(f"frame {i}: person {p['id']} has {k} surface points inside furniture")
            if limits:
                a = p["pose"].angles
                bad = np.nonzero((a < LIMITS_LO - 1e-9) | (a > LIMITS_HI + 1e-9))[0]
                if len(bad):
                    problems.append(f"frame {i}: person {p['id']} joint {DOFS[bad[0]]} = {a[bad[0]]:.3f} "
                                    f"outside its limits")
        for x in range(len(people)):
            for y in range(x + 1, len(people)):
                a, b = people[x], people[y]
                if np.linalg.norm(a["centroid"][:2] - b["centroid"][:2]) > 2.2:
                    continue
                k = points_in_primitives(pts[x], b["kinds"], b["rows"], margin)
                if k:
                    problems.append(f"frame {i}: persons {a['id']} and {b['id']} intersect ({k} points)")
    return problems
