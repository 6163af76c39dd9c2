"""Intrinsic calibration from views of a board (Zhang's method as OpenCV implements it,
``cv2.calibrateCamera``): K, the distortion ``k1 k2 p1 p2 k3`` and the RMS reprojection
error, from image files or from frames sampled from a video."""
from __future__ import annotations

import glob
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.errors import InputError
from calibration.boards import Board, detect

__all__ = ["IntrinsicResult", "calibrate_intrinsics", "images_from_glob", "frames_from_video", "RMS_WARNING_PX"]

RMS_WARNING_PX = 1.0


@dataclass
class IntrinsicResult:
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    rms: float
    views_used: int
    views_total: int
    per_view_rms: list[float] = field(default_factory=list)
    used: list[str] = field(default_factory=list)

    @property
    def warning(self) -> str | None:
        if self.rms > RMS_WARNING_PX:
            return (f"RMS reprojection error {self.rms:.2f} px is above {RMS_WARNING_PX:g} px: check the board "
                    "specification (corners, square size), blurred views, or a lens the 5-term model does not fit")
        return None


def images_from_glob(pattern: str):
    """``(name, image)`` for every image matching a glob pattern, sorted by name."""
    files = sorted(glob.glob(pattern))
    if not files:
        raise InputError(f"--images {pattern!r}: no file matches")
    for f in files:
        img = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"{f}: cannot be read as an image")
        yield Path(f).name, img


def frames_from_video(path, every: int = 0, max_frames: int = 60):
    """``(name, frame)`` sampled evenly from a video: every ``every``-th frame, or
    ``max_frames`` frames spread over the whole video when ``every`` is 0."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"{path}: cannot be opened as a video")
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        step = every or max(1, n // max(1, max_frames))
        i = 0
        while True:
            ok = cap.grab()
            if not ok:
                break
            if i % step == 0:
                ok, img = cap.retrieve()
                if ok:
                    yield f"frame {i}", cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            i += 1
    finally:
        cap.release()


def calibrate_intrinsics(views, board: Board, fix_k3: bool = False, source: str = "images") -> IntrinsicResult:
    """Calibrate one camera from ``(name, image)`` views of the board."""
    obj, img, names, size, total = [], [], [], None, 0
    for name, image in views:
        total += 1
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise InputError(f"{name}: {w}x{h}, but the first view is {size[0]}x{size[1]}")
        d = detect(board, image)
        if d is None or len(d.ids) < 6:
            continue
        obj.append(board.object_points()[d.ids].astype(np.float32))
        img.append(d.pixels.astype(np.float32).reshape(-1, 1, 2))
        names.append(name)
    if size is None:
        raise InputError(f"{source}: no image")
    if len(obj) < 3:
        raise InputError(f"{source}: the board was found in {len(obj)} of {total} views; at least 3 are needed "
                         "(check --board: inner corners COLSxROWS and the square size)")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    per_view = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - i) ** 2, axis=2)))))
    d5 = np.zeros(5)
    d5[: min(5, dist.size)] = dist.ravel()[:5]
    return IntrinsicResult(size[0], size[1], K, d5, float(rms), len(obj), total, per_view, names)
