"""The same camera seen through another image: turned by quarter turns, rescaled, or
cropped (for videos whose size differs from the calibration's; which one a video needs is
decided in :mod:`calibration.fitting`).

Pixel convention as in :mod:`calibration.camera`: the origin at the top-left pixel's
centre. A clockwise quarter turn maps pixel ``(u, v)`` of a ``W x H`` image to
``(H - 1 - v, u)`` of the ``H x W`` image; the camera axes turn with it
(``x' = -y, y' = x``), so ``fx' = fy, cx' = H - 1 - cy, fy' = fx, cy' = cx`` and the
tangential terms become ``p1' = p2, p2' = -p1`` (the radial ones do not change).
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Camera

__all__ = ["turned", "cropped", "rescaled"]

_QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _turn_once(c: Camera) -> Camera:
    K = c.K
    K2 = np.array([[K[1, 1], 0.0, c.height - 1 - K[1, 2]], [0.0, K[0, 0], K[0, 2]], [0.0, 0.0, 1.0]])
    k1, k2, p1, p2, k3 = c.dist
    return Camera(c.name, c.height, c.width, K2, np.array([k1, k2, p2, -p1, k3]), _QUARTER @ c.R, _QUARTER @ c.t)


def turned(camera: Camera, degrees_clockwise: int) -> Camera:
    """The camera whose image is this one's turned clockwise by 0, 90, 180 or 270 degrees."""
    d = int(degrees_clockwise) % 360
    if d % 90:
        raise ValueError(f"rotation {degrees_clockwise} is not a multiple of 90 degrees")
    c = camera
    for _ in range(d // 90):
        c = _turn_once(c)
    return c


def cropped(camera: Camera, left: int, top: int, width: int, height: int) -> Camera:
    """The camera seeing the ``width x height`` window whose top-left pixel is (left, top)
    (negative offsets or a larger window mean padding)."""
    K = camera.K.copy()
    K[0, 2] -= left
    K[1, 2] -= top
    return Camera(camera.name, int(width), int(height), K, camera.dist.copy(), camera.R.copy(), camera.t.copy())


def rescaled(camera: Camera, width: int, height: int) -> Camera:
    """The camera imaging the same field at ``width x height`` (see :meth:`Camera.scaled`)."""
    return camera.scaled(width, height)
