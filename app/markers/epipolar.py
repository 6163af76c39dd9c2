"""Epipolar geometry of a calibrated rig and the generalised symmetric epipolar distance
(thesis §6.4.1.2, Eqs. 6.6-6.7, after [CFCP05b]).

Everything here is in *ideal pixels*: a camera's pixels with its lens distortion removed
(:func:`ideal_pixels`, the pinhole ``K [R|t]`` of Eq. 2.5 alone), where epipolar lines
are straight. The fundamental matrix ``F_ij`` takes an ideal pixel ``p_i`` of view i to
its epipolar line ``l = F_ij p_i`` in view j (HZ04 §9.2.2: ``F = K_j^-T [t]_x R K_i^-1``
with ``R = R_j R_i^T``, ``t = t_j - R t_i``).

Eq. 6.6: ``d_SE(p_i, p_j) = sqrt(d(L(p_i, j), p_j)^2 + d(L(p_j, i), p_i)^2)``.
Eq. 6.7 as extracted reads ``sum_{i=1}^{k-2} sum_{j=i+1}^{k-1}``, which misses the last
view (0-based limits printed as 1-based); reconstructed here as the sum over every pair
of the k views, ``d_SE(p_1..p_k)^2 = sum_{i<j} d_SE(p_i, p_j)^2``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from calibration.camera import undistort_step

__all__ = ["fundamental", "fundamentals", "ideal_pixels", "ideal_project", "line_distance",
           "symmetric_epipolar_distance", "generalised_epipolar_distance"]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def fundamental(cam_i, cam_j) -> np.ndarray:
    """``F_ij`` (3, 3): ideal pixels of view i to epipolar lines in view j."""
    R = cam_j.R @ cam_i.R.T
    t = cam_j.t - R @ cam_i.t
    F = np.linalg.inv(cam_j.K).T @ _skew(t) @ R @ np.linalg.inv(cam_i.K)
    return F / np.linalg.norm(F)


def fundamentals(cameras) -> np.ndarray:
    """``F[i, j]`` (C, C, 3, 3) for every ordered pair of views (zeros on the diagonal)."""
    n = len(cameras)
    F = np.zeros((n, n, 3, 3))
    for i in range(n):
        for j in range(n):
            if i != j:
                F[i, j] = fundamental(cameras[i], cameras[j])
    return F


def ideal_pixels(camera, pixels: np.ndarray) -> np.ndarray:
    """Observed pixels (N, 2) with the camera's lens distortion removed (N, 2): the
    numbers of :meth:`calibration.camera.Camera.undistort_points` (its 20 fixed-point
    steps) mapped back through ``K``, point by point in one kernel (the marker filter does
    this for every camera's detections each frame: 0.23 ms a camera through numpy's
    temporaries, 9 us here)."""
    pixels = np.asarray(pixels, float).reshape(-1, 2)
    if not camera.has_distortion or not len(pixels):
        return pixels.copy()
    out = np.empty_like(pixels)
    _undistort_ideal(np.ascontiguousarray(pixels), np.ascontiguousarray(camera.K, dtype=np.float64),
                     np.ascontiguousarray(camera.dist, dtype=np.float64), 20, out)
    return out


_step = njit(nogil=True)(undistort_step)   # the camera's own step, compiled


@njit(cache=True, nogil=True)
def _undistort_ideal(uv, K, dist, iterations, out):
    """:func:`ideal_pixels`' kernel: the lens model (OpenCV's k1 k2 p1 p2 k3) inverted by
    ``iterations`` fixed-point steps, as ``Camera.undistort_points``, then ``K``."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in range(uv.shape[0]):
        yd = (uv[i, 1] - K[1, 2]) / K[1, 1]
        xd = (uv[i, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        x, y = xd, yd
        for _ in range(iterations):
            x, y = _step(x, y, xd, yd, k1, k2, p1, p2, k3)
        out[i, 0] = K[0, 0] * x + K[0, 1] * y + K[0, 2]
        out[i, 1] = K[1, 1] * y + K[1, 2]


def ideal_project(camera, points: np.ndarray) -> np.ndarray:
    """World points (..., 3) to ideal pixels (..., 2) (NaN behind the camera)."""
    p = np.asarray(points, float)
    pc = p @ camera.R.T + camera.t
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(pc[..., 2] > 1e-9, pc[..., 2], np.nan)
        xn, yn = pc[..., 0] / z, pc[..., 1] / z
    K = camera.K
    return np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], axis=-1)


def line_distance(line: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance of points (..., 2) to lines (..., 3) ``a x + b y + c = 0``."""
    return np.abs(line[..., 0] * p[..., 0] + line[..., 1] * p[..., 1] + line[..., 2]) / np.hypot(line[..., 0],
                                                                                                 line[..., 1])


def symmetric_epipolar_distance(p_i: np.ndarray, p_j: np.ndarray, F_ij: np.ndarray) -> np.ndarray:
    """Eq. 6.6 for points (..., 2) of views i and j (``F_ij`` from :func:`fundamental`)."""
    hi = np.concatenate([p_i, np.ones(p_i.shape[:-1] + (1,))], axis=-1)
    hj = np.concatenate([p_j, np.ones(p_j.shape[:-1] + (1,))], axis=-1)
    line_in_j = hi @ F_ij.T            # L(p_i, j) = F_ij p_i
    line_in_i = hj @ F_ij              # L(p_j, i) = F_ij^T p_j
    return np.hypot(line_distance(line_in_j, p_j), line_distance(line_in_i, p_i))


def generalised_epipolar_distance(points: np.ndarray, views, F: np.ndarray) -> float:
    """Eq. 6.7 (every pair, module docstring): ``points`` (k, 2) seen in ``views`` (k,)
    (indices into ``F`` of :func:`fundamentals`); NaN below two points."""
    k = len(points)
    if k < 2:
        return float("nan")
    total = 0.0
    for a in range(k - 1):
        for b in range(a + 1, k):
            total += float(symmetric_epipolar_distance(points[a], points[b], F[views[a], views[b]])) ** 2
    return float(np.sqrt(total))
