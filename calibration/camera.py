"""Pinhole camera with OpenCV lens distortion (thesis §2.2.2, Eqs. 2.1-2.8).

The thesis models projection as ``x = K [R|t] X`` (Eq. 2.5) followed by a radial
distortion ``L(r) = 1 + k1 r^2 + k2 r^4`` (Eqs. 2.7-2.8). We use OpenCV's model, a
superset of it: radial ``k1, k2, k3`` and tangential ``p1, p2`` terms applied to the
normalised image coordinates, so calibrations from OpenCV (and from the thesis, with
``p1 = p2 = k3 = 0``) are used unchanged. Coordinates: world metres, z up;
``x_cam = R x_world + t``; pixels with the origin at the top-left pixel's centre.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Camera", "undistort_step"]


def undistort_step(x, y, xd, yd, k1, k2, p1, p2, k3):
    """One fixed-point step inverting the lens model (OpenCV's k1 k2 p1 p2 k3) at the
    distorted normalised point ``(xd, yd)`` from the guess ``(x, y)``: arrays or scalars
    (:meth:`Camera.undistort_points`; compiled as is in numba kernels such as
    :func:`app.markers.epipolar.ideal_pixels`', so both give the same numbers)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return (xd - dx) / radial, (yd - dy) / radial


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: intrinsics ``K``, distortion ``dist`` and pose ``R``, ``t``."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        dist = np.zeros(5)
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        dist[: min(5, d.size)] = d[:5]
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    # -- geometry -----------------------------------------------------------------
    @property
    def centre(self) -> np.ndarray:
        """Optical centre in world coordinates, ``C = -R^T t``."""
        return -self.R.T @ self.t

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) to camera coordinates (..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.R.T + self.t

    def distort(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply the lens model to normalised coordinates (OpenCV order k1 k2 p1 p2 k3)."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        return xd, yd

    def project(self, points: np.ndarray, return_depth: bool = False):
        """Project world points (N, 3) to pixels (N, 2), Eq. 2.5 with distortion.

        Points behind the camera get NaN pixels. With ``return_depth`` the camera-frame
        depth ``z_cam`` (N,) is returned too.
        """
        pc = self.to_camera(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(z > 1e-9, 1.0 / z, np.nan)
        xd, yd = self.distort(pc[:, 0] * inv, pc[:, 1] * inv)
        K = self.K
        uv = np.empty((pc.shape[0], 2))
        uv[:, 0] = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        uv[:, 1] = K[1, 1] * yd + K[1, 2]
        return (uv, z) if return_depth else uv

    def undistort_points(self, pixels: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels (N, 2) to undistorted normalised coordinates (N, 2).

        Inverts the lens model by fixed-point iteration (as ``cv2.undistortPoints``).
        """
        uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        K = self.K
        yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
        xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        if not self.has_distortion:
            return np.stack([xd, yd], axis=1)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            x, y = undistort_step(x, y, xd, yd, k1, k2, p1, p2, k3)
        return np.stack([x, y], axis=1)

    def pixel_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit ray directions in world coordinates (N, 3) through pixels (N, 2)."""
        xy = self.undistort_points(pixels)
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1) @ self.R  # R^T d
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def sees(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean (N,): the point is in front of the camera and projects inside the image."""
        uv, z = self.project(points, return_depth=True)
        with np.errstate(invalid="ignore"):
            return (
                (z > 1e-6)
                & (uv[:, 0] >= -0.5 - margin)
                & (uv[:, 0] < self.width - 0.5 + margin)
                & (uv[:, 1] >= -0.5 - margin)
                & (uv[:, 1] < self.height - 0.5 + margin)
            )

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera imaging at another resolution (e.g. a downscaled mask).

        Pixel centres map as ``u' = (u + 0.5) * width / self.width - 0.5``, so the
        intrinsics scale about the image corner, not the principal point.
        """
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(self.name, int(width), int(height), K, self.dist.copy(), self.R.copy(), self.t.copy())

    # -- construction -------------------------------------------------------------
    @classmethod
    def look_at(
        cls,
        name: str,
        position,
        target,
        width: int = 640,
        height: int = 480,
        hfov_deg: float = 70.0,
        dist=(0.0, 0.0, 0.0, 0.0, 0.0),
        up=(0.0, 0.0, 1.0),
    ) -> "Camera":
        """A camera at ``position`` looking at ``target`` (world z up, image y down)."""
        c = np.asarray(position, dtype=np.float64)
        forward = np.asarray(target, dtype=np.float64) - c
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(up, dtype=np.float64))
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])  # rows: camera x, y, z axes in world
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2.0)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(name=name, width=width, height=height, K=K, dist=np.asarray(dist), R=R, t=-R @ c)

    def to_dict(self) -> dict:
        """The camera as the contract's ``calibration.yaml`` entry."""
        return {
            "name": self.name,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }
