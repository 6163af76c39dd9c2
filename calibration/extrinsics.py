"""Extrinsic calibration: each camera's pose (R, t) in the world, from a board lying on the
floor (which then defines the world: origin at the board, z up; see
:func:`calibration.boards.floor_points`) or from known 3D points with their pixels.

Per camera: ``cv2.solvePnP`` (IPPE for a planar board, iterative otherwise) and
``cv2.solvePnPRefineLM``. When the board is shown in further places seen by several
cameras (``views`` beyond the floor view), :func:`refine_jointly` adjusts all camera poses
and the board's extra poses together, minimising every reprojection error at once
(``scipy.optimize.least_squares``), the floor view fixing the world.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from app.errors import InputError
from calibration.camera import Camera

__all__ = ["PoseResult", "solve_pose", "refine_jointly", "reprojection_rms"]


@dataclass
class PoseResult:
    camera: Camera
    rms: float  # px
    points: int


def reprojection_rms(camera: Camera, world: np.ndarray, pixels: np.ndarray) -> float:
    uv = camera.project(world)
    return float(np.sqrt(np.mean(np.sum((uv - pixels) ** 2, axis=1))))


def solve_pose(camera: Camera, world, pixels, what: str = "") -> PoseResult:
    """The pose of a camera with known intrinsics from world points and their pixels."""
    world = np.asarray(world, dtype=np.float64).reshape(-1, 3)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(world) < 4 or len(world) != len(pixels):
        raise InputError(f"{what or camera.name}: needs at least 4 world points with their pixels, got "
                         f"{len(world)} points and {len(pixels)} pixels")
    planar = np.ptp(world[:, 2]) < 1e-9
    flag = cv2.SOLVEPNP_IPPE if planar else (cv2.SOLVEPNP_ITERATIVE if len(world) >= 6 else cv2.SOLVEPNP_SQPNP)
    ok, rvec, tvec = cv2.solvePnP(world, pixels, camera.K, camera.dist, flags=flag)
    if not ok:
        raise InputError(f"{what or camera.name}: no camera pose fits the points")
    rvec, tvec = cv2.solvePnPRefineLM(world, pixels, camera.K, camera.dist, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    cam = Camera(camera.name, camera.width, camera.height, camera.K, camera.dist, R, tvec.ravel())
    if planar and cam.centre[2] < 0:
        raise InputError(f"{what or camera.name}: the camera comes out below the floor; the board's corners "
                         "were matched mirrored (use a ChArUco board, or a chessboard with odd x even corners)")
    return PoseResult(cam, reprojection_rms(cam, world, pixels), len(world))


def _rt(x):
    return cv2.Rodrigues(x[:3].reshape(3, 1))[0], x[3:6]


def refine_jointly(cameras: list[Camera], observations, board_points: np.ndarray) -> list[PoseResult]:
    """Adjust camera poses and extra board poses together.

    ``observations``: ``(camera index, view index, corner ids, pixels)``; view 0 is the board
    on the floor (its world points are ``board_points[ids]``, fixed); view k > 0 is the
    board somewhere else, its pose unknown and shared by the cameras that saw it.
    ``cameras`` carry their first poses (from :func:`solve_pose` on view 0)."""
    n_cam = len(cameras)
    views = sorted({v for _, v, _, _ in observations if v > 0})
    vindex = {v: i for i, v in enumerate(views)}
    # first guess of each extra view's pose: from the first camera that saw it
    x0 = []
    for c in cameras:
        x0 += [*cv2.Rodrigues(c.R)[0].ravel(), *c.t]
    for v in views:
        ci, ids, px = next((ci, ids, px) for ci, vv, ids, px in observations if vv == v)
        cam = cameras[ci]
        ok, rvec, tvec = cv2.solvePnP(board_points[ids], px, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
        Rc, tc = cv2.Rodrigues(rvec)[0], tvec.ravel()
        # board in camera: x_c = Rc p + tc; world: x_w = R^T (x_c - t)
        Rw, tw = cam.R.T @ Rc, cam.R.T @ (tc - cam.t)
        x0 += [*cv2.Rodrigues(Rw)[0].ravel(), *tw]
    x0 = np.asarray(x0, dtype=np.float64)

    def residuals(x):
        out = []
        for ci, v, ids, px in observations:
            Rc, tc = _rt(x[6 * ci:6 * ci + 6])
            pts = board_points[ids]
            if v > 0:
                j = 6 * (n_cam + vindex[v])
                Rw, tw = _rt(x[j:j + 6])
                pts = pts @ Rw.T + tw
            cam = cameras[ci]
            proj, _ = cv2.projectPoints(pts, cv2.Rodrigues(Rc)[0], tc, cam.K, cam.dist)
            out.append((proj.reshape(-1, 2) - px).ravel())
        return np.concatenate(out)

    sol = least_squares(residuals, x0, method="trf", x_scale="jac")
    results = []
    for ci, c in enumerate(cameras):
        R, t = _rt(sol.x[6 * ci:6 * ci + 6])
        cam = Camera(c.name, c.width, c.height, c.K, c.dist, R, t)
        mine = [(v, ids, px) for cc, v, ids, px in observations if cc == ci]
        errs, n = [], 0
        for v, ids, px in mine:
            pts = board_points[ids]
            if v > 0:
                j = 6 * (n_cam + vindex[v])
                Rw, tw = _rt(sol.x[j:j + 6])
                pts = pts @ Rw.T + tw
            errs.append(np.sum((cam.project(pts) - px) ** 2, axis=1))
            n += len(ids)
        results.append(PoseResult(cam, float(np.sqrt(np.mean(np.concatenate(errs)))), n))
    return results
