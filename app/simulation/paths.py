"""Collision-free walking paths on the floor plan (A* on a clearance grid, then smoothed).

The floor plan is a grid (5 cm cells) over the room and the corridor behind its door;
furniture footprints and walls are obstacles. A distance transform gives each free
cell its clearance (distance to the nearest obstacle); a walker of radius ``r`` may use
the cells with clearance >= ``r``. A* finds the shortest 8-connected path (with a
small cost for passing close to obstacles), string pulling removes the grid's zigzag
and the corners are rounded with quadratic Bezier fillets where the clearance allows.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from app.simulation.room import Room

__all__ = ["FloorPlan", "PathError", "TIGHT_RADIUS"]


#: Clearance needed to step into a tight spot (half the depth of a body, front to back).
TIGHT_RADIUS = 0.2


class PathError(RuntimeError):
    """No path exists between two points for the requested clearance."""


class FloorPlan:
    """Clearance map of a room's floor (the corridor included)."""

    def __init__(self, room: Room, cell: float = 0.05):
        self.room = room
        self.cell = cell
        cx0, _, cy0, cy1 = room.corridor
        self.x0 = min(0.0, cx0)
        self.y0 = min(0.0, cy0)
        x1 = room.size[0]
        y1 = max(room.size[1], cy1)
        self.nx = int(math.ceil((x1 - self.x0) / cell))
        self.ny = int(math.ceil((y1 - self.y0) / cell))
        xs = self.x0 + (np.arange(self.nx) + 0.5) * cell
        ys = self.y0 + (np.arange(self.ny) + 0.5) * cell
        X, Y = np.meshgrid(xs, ys)
        free = (X > 0.0) & (X < room.size[0]) & (Y > 0.0) & (Y < room.size[1])
        free |= (X > cx0) & (X < 0.0) & (Y > cy0) & (Y < cy1)
        d0, d1, _ = room.door
        free |= (X > -0.2) & (X < 0.2) & (Y > d0) & (Y < d1)  # the doorway through the wall
        for b in room.boxes:
            c, s = math.cos(b[6]), math.sin(b[6])
            lx = c * (X - b[0]) + s * (Y - b[1])
            ly = -s * (X - b[0]) + c * (Y - b[1])
            free &= ~((np.abs(lx) <= b[3]) & (np.abs(ly) <= b[4]))
        self.free = free
        self.base_clearance = self._clearance(free)
        self.clearance = self.base_clearance

    def _clearance(self, free: np.ndarray) -> np.ndarray:
        img = np.pad(free.astype(np.uint8), 1)  # the grid's border is an obstacle
        d = cv2.distanceTransform(img, cv2.DIST_L2, 5)[1:-1, 1:-1]
        return d.astype(np.float64) * self.cell

    def with_obstacles(self, discs) -> "FloorPlan":
        """A copy with extra round obstacles ``[(x, y, radius), ...]`` (e.g. people who
        stand still)."""
        other = object.__new__(FloorPlan)
        other.__dict__.update(self.__dict__)
        if discs:
            xs = self.x0 + (np.arange(self.nx) + 0.5) * self.cell
            ys = self.y0 + (np.arange(self.ny) + 0.5) * self.cell
            X, Y = np.meshgrid(xs, ys)
            free = self.free.copy()
            for x, y, r in discs:
                free &= (X - x) ** 2 + (Y - y) ** 2 > r * r
            other.free = free
            other.clearance = self._clearance(free)
        return other

    # -- queries ------------------------------------------------------------------
    def cell_of(self, xy) -> tuple[int, int]:
        i = int((xy[0] - self.x0) / self.cell)
        j = int((xy[1] - self.y0) / self.cell)
        return min(max(j, 0), self.ny - 1), min(max(i, 0), self.nx - 1)

    def centre(self, j: int, i: int) -> np.ndarray:
        return np.array([self.x0 + (i + 0.5) * self.cell, self.y0 + (j + 0.5) * self.cell])

    def clearance_at(self, xy) -> float:
        """Clearance (m) at a point, bilinear."""
        fx = (xy[0] - self.x0) / self.cell - 0.5
        fy = (xy[1] - self.y0) / self.cell - 0.5
        i = min(max(int(math.floor(fx)), 0), self.nx - 2)
        j = min(max(int(math.floor(fy)), 0), self.ny - 2)
        ax, ay = min(max(fx - i, 0.0), 1.0), min(max(fy - j, 0.0), 1.0)
        c = self.clearance
        return float((c[j, i] * (1 - ax) + c[j, i + 1] * ax) * (1 - ay)
                     + (c[j + 1, i] * (1 - ax) + c[j + 1, i + 1] * ax) * ay)

    def base_clearance_at(self, xy) -> float:
        """Clearance (m) from furniture and walls only (no extra obstacles)."""
        return float(_clearance_at(self.base_clearance, self.x0, self.y0, self.cell, float(xy[0]), float(xy[1])))

    def segment_clear(self, a, b, radius: float) -> bool:
        """True when every point of the segment has clearance >= ``radius``."""
        return _segment_clear(self.clearance, self.x0, self.y0, self.cell, float(a[0]), float(a[1]),
                              float(b[0]), float(b[1]), float(radius))

    def nearest_free(self, xy, radius: float) -> np.ndarray:
        """The centre of the closest cell with clearance >= ``radius``."""
        ok = self.clearance >= radius
        if not ok.any():
            raise PathError(f"no free cell with clearance {radius:.2f} m")
        js, is_ = np.nonzero(ok)
        cx = self.x0 + (is_ + 0.5) * self.cell
        cy = self.y0 + (js + 0.5) * self.cell
        k = int(np.argmin((cx - xy[0]) ** 2 + (cy - xy[1]) ** 2))
        return np.array([cx[k], cy[k]])

    # -- planning -----------------------------------------------------------------
    def plan(self, start, goal, radius: float, prefer: float = 0.25) -> np.ndarray:
        """A smoothed collision-free path ``(N, 2)`` from ``start`` to ``goal`` for a
        walker of ``radius``. A start in a tight spot (by a chair) joins the free space
        at the nearest free cell with a straight segment; a goal too tight to stand in is
        replaced by the nearest free point (see :data:`TIGHT_RADIUS` for deliberate
        tight moves, made by the caller with straight segments)."""
        start = np.asarray(start, dtype=float)
        goal = np.asarray(goal, dtype=float)
        if self.clearance_at(goal) >= radius and self.segment_clear(start, goal, radius):
            return _resample(np.array([start, goal]), 0.02)
        s_free = start if self.clearance_at(start) >= radius else self.nearest_free(start, radius)
        if self.clearance_at(goal) < radius:
            goal = self.nearest_free(goal, radius)  # too tight to stand there: stop next to it
        g_free = goal
        cells = self._astar(self.cell_of(s_free), self.cell_of(g_free), radius, prefer)
        pts = [start] + [self.centre(j, i) for j, i in cells] + [goal]
        pts = _dedupe(np.array(pts))
        pts = self._string_pull(pts, radius)
        pts = self._round_corners(pts, radius)
        return _resample(pts, 0.02)

    def _astar(self, s, g, radius, prefer):
        ok = self.clearance >= radius - 1e-9
        ok[s] = ok[g] = True
        extra = np.maximum(0.0, prefer - (self.clearance - radius)) * 2.0  # keep away from obstacles
        cells = _astar_grid(ok, extra, s[0], s[1], g[0], g[1], self.cell)
        if len(cells) == 0:
            raise PathError("no path between the points for this clearance")
        return [(int(j), int(i)) for j, i in cells]

    def _string_pull(self, pts, radius):
        out = [pts[0]]
        k = 0
        n = len(pts)
        while k < n - 1:
            nxt = k + 1
            for m in range(n - 1, k + 1, -1):
                if self.segment_clear(pts[k], pts[m], radius):
                    nxt = m
                    break
            out.append(pts[nxt])
            k = nxt
        return np.array(out)

    def _round_corners(self, pts, radius, fillet: float = 0.45):
        if len(pts) < 3:
            return pts
        out = [pts[0]]
        for k in range(1, len(pts) - 1):
            a, c, b = out[-1], pts[k], pts[k + 1]
            la, lb = np.linalg.norm(c - a), np.linalg.norm(b - c)
            rho = min(fillet, 0.45 * la, 0.45 * lb)
            if rho < 0.03:
                out.append(c)
                continue
            p0 = c + (a - c) / la * rho
            p2 = c + (b - c) / lb * rho
            curve = [(1 - s) ** 2 * p0 + 2 * (1 - s) * s * c + s * s * p2 for s in np.linspace(0, 1, 9)]
            if all(self.clearance_at(q) >= radius for q in curve):
                out.extend(curve)
            else:
                out.append(c)
        out.append(pts[-1])
        return _dedupe(np.array(out))


def _dedupe(pts: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    keep = [0]
    for k in range(1, len(pts)):
        if np.linalg.norm(pts[k] - pts[keep[-1]]) > eps:
            keep.append(k)
    return pts[keep]


def _resample(pts: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` metres along a polyline (ends kept)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    if total < 1e-9:
        return pts[:1].copy()
    n = max(2, int(math.ceil(total / step)) + 1)
    q = np.linspace(0.0, total, n)
    return np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], axis=1)


@njit(cache=True, nogil=True)
def _astar_grid(ok, extra, sj, si, gj, gi, cell):
    """8-connected A* on a boolean grid with a per-cell extra cost factor; returns the
    ``(K, 2)`` cells (row, column) from start to goal, empty when unreachable."""
    ny, nx = ok.shape
    n = ny * nx
    dist = np.full(n, 1e18)
    came = np.full(n, -1, dtype=np.int64)
    closed = np.zeros(n, dtype=np.bool_)
    heap_f = np.empty(8 * n + 8)
    heap_i = np.empty(8 * n + 8, dtype=np.int64)
    size = 0
    s = sj * nx + si
    g = gj * nx + gi
    dist[s] = 0.0
    heap_f[0], heap_i[0], size = 0.0, s, 1
    dj = (-1, -1, -1, 0, 0, 1, 1, 1)
    di = (-1, 0, 1, -1, 1, -1, 0, 1)
    found = False
    while size > 0:
        cur = heap_i[0]
        # pop the root of the binary heap
        size -= 1
        lf, li = heap_f[size], heap_i[size]
        k = 0
        while True:
            c = 2 * k + 1
            if c >= size:
                break
            if c + 1 < size and heap_f[c + 1] < heap_f[c]:
                c += 1
            if heap_f[c] >= lf:
                break
            heap_f[k], heap_i[k] = heap_f[c], heap_i[c]
            k = c
        if size > 0:
            heap_f[k], heap_i[k] = lf, li
        if cur == g:
            found = True
            break
        if closed[cur]:
            continue
        closed[cur] = True
        cj, ci = cur // nx, cur % nx
        for m in range(8):
            j, i = cj + dj[m], ci + di[m]
            if j < 0 or i < 0 or j >= ny or i >= nx or not ok[j, i]:
                continue
            nxt = j * nx + i
            if closed[nxt]:
                continue
            step = (1.4142135623730951 if dj[m] != 0 and di[m] != 0 else 1.0) * cell
            nd = dist[cur] + step * (1.0 + extra[j, i])
            if nd < dist[nxt]:
                dist[nxt] = nd
                came[nxt] = cur
                h = math.sqrt((i - gi) ** 2 + (j - gj) ** 2) * cell
                # push
                k = size
                size += 1
                f = nd + h
                while k > 0:
                    p = (k - 1) // 2
                    if heap_f[p] <= f:
                        break
                    heap_f[k], heap_i[k] = heap_f[p], heap_i[p]
                    k = p
                heap_f[k], heap_i[k] = f, nxt
    if not found:
        return np.zeros((0, 2), dtype=np.int64)
    count = 1
    c = g
    while c != s:
        c = came[c]
        count += 1
    out = np.empty((count, 2), dtype=np.int64)
    c = g
    for k in range(count - 1, -1, -1):
        out[k, 0], out[k, 1] = c // nx, c % nx
        if k > 0:
            c = came[c]
    return out


@njit(cache=True, nogil=True)
def _clearance_at(c, x0, y0, cell, x, y):
    ny, nx = c.shape
    fx = (x - x0) / cell - 0.5
    fy = (y - y0) / cell - 0.5
    i = min(max(int(math.floor(fx)), 0), nx - 2)
    j = min(max(int(math.floor(fy)), 0), ny - 2)
    ax = min(max(fx - i, 0.0), 1.0)
    ay = min(max(fy - j, 0.0), 1.0)
    return ((c[j, i] * (1 - ax) + c[j, i + 1] * ax) * (1 - ay)
            + (c[j + 1, i] * (1 - ax) + c[j + 1, i + 1] * ax) * ay)


@njit(cache=True, nogil=True)
def _segment_clear(c, x0, y0, cell, ax, ay, bx, by, radius):
    length = math.sqrt((bx - ax) ** 2 + (by - ay) ** 2)
    n = max(2, int(length / (0.5 * cell)) + 1)
    for k in range(n):
        s = k / (n - 1)
        if _clearance_at(c, x0, y0, cell, ax + s * (bx - ax), ay + s * (by - ay)) < radius:
            return False
    return True
