"""Draw what a calibration says onto a camera's image: the room box, the world axes and
the floor grid, so a person sees at once whether the calibration fits the images
(``smartroom calibrate check --recording``)."""
from __future__ import annotations

import cv2
import numpy as np

from app.drawing import outlined_text
from calibration.camera import Camera

__all__ = ["draw_calibration", "contact_sheet", "floor_coverage"]

ROOM = (0, 255, 255)  # BGR yellow
GRID = (200, 200, 200)
AXES = ((0, 0, 255), (0, 200, 0), (255, 0, 0))  # x red, y green, z blue


def _polyline(img, camera: Camera, a, b, colour, thickness=1, steps=60):
    """A straight world segment drawn as the lens bends it; parts behind the camera skipped."""
    pts = np.linspace(a, b, steps)
    uv, z = camera.project(pts, return_depth=True)
    ok = (z > 0.05) & np.all(np.isfinite(uv), axis=1) & (np.abs(uv) < 1e5).all(axis=1)
    run = []
    for good, p in zip(ok, uv):
        if good:
            run.append(p)
        elif run:
            _draw_run(img, run, colour, thickness)
            run = []
    if run:
        _draw_run(img, run, colour, thickness)


def _draw_run(img, run, colour, thickness):
    if len(run) >= 2:
        pts = np.round(np.array(run) * 4).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, colour, thickness, cv2.LINE_AA, shift=2)


def draw_calibration(camera: Camera, image: np.ndarray | None, room_min, room_max, grid: float = 0.5,
                     lines: list[str] | None = None) -> np.ndarray:
    """``image`` (BGR, the camera's size; grey when None) with the floor grid, the room box,
    the world axes (1 m; x red, y green, z blue) and text ``lines`` drawn on it."""
    if image is None:
        img = np.full((camera.height, camera.width, 3), 64, np.uint8)
    else:
        img = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    lo, hi = np.asarray(room_min, float), np.asarray(room_max, float)
    thick = max(1, round(max(camera.width, camera.height) / 640))
    for x in np.arange(np.ceil(lo[0] / grid) * grid, hi[0] + 1e-9, grid):
        _polyline(img, camera, [x, lo[1], 0.0], [x, hi[1], 0.0], GRID, 1)
    for y in np.arange(np.ceil(lo[1] / grid) * grid, hi[1] + 1e-9, grid):
        _polyline(img, camera, [lo[0], y, 0.0], [hi[0], y, 0.0], GRID, 1)
    corners = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    for i in range(8):
        for j in range(i + 1, 8):
            if bin(i ^ j).count("1") == 1:
                _polyline(img, camera, corners[i], corners[j], ROOM, thick + 1)
    for axis, colour in enumerate(AXES):
        end = np.zeros(3)
        end[axis] = 1.0
        _polyline(img, camera, np.zeros(3), end, colour, thick + 2)
    scale = max(0.3, 0.45 * max(camera.width, camera.height) / 640)
    step = int(30 * scale) + 4
    y = step
    for text in [camera.name] + list(lines or []):
        outlined_text(img, text, (6 + thick, y), scale, (255, 255, 255), thick, outline=thick + 1)
        y += step
    return img


SHEET_TILE_HEIGHT = 720   # HD cameras are judged at 1280x720 each in the sheet (2560x1440 for four)


def contact_sheet(images: list[np.ndarray], tile_height: int | None = None, columns: int | None = None) -> np.ndarray:
    """Images (any sizes, portrait or landscape) scaled to one height and tiled in a grid;
    the height is the images' own, up to :data:`SHEET_TILE_HEIGHT` (big enough to judge
    whether the room's lines fall on its edges)."""
    if tile_height is None:
        tile_height = min(SHEET_TILE_HEIGHT, max(im.shape[0] for im in images))
    tiles = [cv2.resize(im, (max(1, round(im.shape[1] * tile_height / im.shape[0])), tile_height),
                        interpolation=cv2.INTER_AREA) for im in images]
    cols = columns or int(np.ceil(np.sqrt(len(tiles))))
    rows = [tiles[i:i + cols] for i in range(0, len(tiles), cols)]
    width = max(sum(t.shape[1] for t in r) for r in rows)
    sheet = np.zeros((tile_height * len(rows), width, 3), np.uint8)
    for r, row in enumerate(rows):
        x = 0
        for t in row:
            sheet[r * tile_height:(r + 1) * tile_height, x:x + t.shape[1]] = t
            x += t.shape[1]
    return sheet


def floor_coverage(camera: Camera, room_min, room_max, step: float = 0.1) -> float:
    """Share of the room's floor the camera sees."""
    xs = np.arange(room_min[0] + step / 2, room_max[0], step)
    ys = np.arange(room_min[1] + step / 2, room_max[1], step)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, room_min[2])], axis=1)
    return float(camera.sees(pts).mean()) if len(pts) else 0.0
