"""Calibration boards: the ``--board`` specification, detection with OpenCV, and a
renderer of a board seen by a known camera (for tests and for previews).

Specifications:

- ``chessboard:COLSxROWS:SQUARE`` inner corners per row x per column and the square's side
  in metres, e.g. ``chessboard:9x6:0.025`` (``cv2.findChessboardCorners`` +
  ``cv2.cornerSubPix``);
- ``charuco:COLSxROWS:SQUARE:MARKER[:DICT]`` squares per row x per column, square and
  marker sides in metres, ArUco dictionary (default ``DICT_4X4_50``), e.g.
  ``charuco:7x5:0.04:0.03`` (``cv2.aruco.CharucoDetector``). ChArUco corners carry ids, so
  a board seen partly, or from any side, is still matched point for point.

Board coordinates: OpenCV's object points, ``(col * square, row * square, 0)`` for the
inner corner ``row, col`` of a chessboard; a ChArUco board's start at its outer corner
(``((col + 1) * square, (row + 1) * square, 0)``, as ``CharucoBoard.getChessboardCorners``). On the floor the world frame is the board's turned 180 degrees
about its x axis, so that z points up (towards the cameras): see :func:`floor_points`.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.errors import InputError

__all__ = ["Board", "parse_board", "Detection", "detect", "floor_points", "render_view"]


@dataclass(frozen=True)
class Board:
    kind: str  # "chessboard" or "charuco"
    cols: int  # inner corners per row (chessboard) or squares per row (charuco)
    rows: int
    square: float
    marker: float = 0.0
    dictionary: str = "DICT_4X4_50"

    @property
    def corner_grid(self) -> tuple[int, int]:
        """Inner corners per row and per column."""
        return (self.cols, self.rows) if self.kind == "chessboard" else (self.cols - 1, self.rows - 1)

    def object_points(self) -> np.ndarray:
        """All inner corners in board coordinates (N, 3), id order."""
        nx, ny = self.corner_grid
        g = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2).astype(np.float64) * self.square
        if self.kind == "charuco":  # OpenCV's ChArUco origin is the board's outer corner
            g += self.square
        return np.concatenate([g, np.zeros((len(g), 1))], axis=1)

    def charuco(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, d)

    def texture(self, px_per_square: int = 60) -> tuple[np.ndarray, float, float]:
        """A grey image of the printed board with a white margin of one square, and the board
        coordinates (metres) of the texture's top-left pixel centre (offset) and pixel size."""
        s = px_per_square
        if self.kind == "charuco":
            nx, ny = self.cols, self.rows
            img = self.charuco().generateImage(((nx + 2) * s, (ny + 2) * s), marginSize=s, borderBits=1)
            return img, -self.square + self.square / s / 2, self.square / s
        nx, ny = self.cols + 1, self.rows + 1  # squares
        img = np.full(((ny + 2) * s, (nx + 2) * s), 255, np.uint8)
        for r in range(ny):
            for c in range(nx):
                if (r + c) % 2 == 0:
                    img[(r + 1) * s:(r + 2) * s, (c + 1) * s:(c + 2) * s] = 0
        return img, -self.square * 2 + self.square / s / 2, self.square / s


def parse_board(text: str) -> Board:
    parts = str(text).split(":")
    try:
        kind = parts[0].lower()
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square = float(parts[2])
        if kind == "chessboard" and len(parts) == 3:
            board = Board("chessboard", cols, rows, square)
        elif kind == "charuco" and len(parts) in (4, 5):
            board = Board("charuco", cols, rows, square, float(parts[3]),
                          parts[4] if len(parts) == 5 else "DICT_4X4_50")
        else:
            raise ValueError
    except (ValueError, IndexError):
        raise InputError(f"--board {text!r}: expected chessboard:COLSxROWS:SQUARE_M or "
                         "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]") from None
    if min(cols, rows) < 2 or square <= 0 or (kind == "charuco" and not 0 < board.marker < square):
        raise InputError(f"--board {text!r}: needs at least 2x2 corners, square > 0 and 0 < marker < square")
    if kind == "charuco" and not hasattr(cv2.aruco, board.dictionary):
        raise InputError(f"--board {text!r}: unknown ArUco dictionary {board.dictionary}")
    return board


@dataclass
class Detection:
    """Corners found in one image: their ids (index into ``Board.object_points``) and pixels."""

    ids: np.ndarray  # (N,) int
    pixels: np.ndarray  # (N, 2) float64


def detect(board: Board, image: np.ndarray, min_corners: int = 6) -> Detection | None:
    """The board's inner corners in an image (BGR or grey), or None when not found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if board.kind == "chessboard":
        ok, corners = cv2.findChessboardCorners(gray, board.corner_grid,
                                                cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4))
        px = corners.reshape(-1, 2).astype(np.float64)
        return Detection(np.arange(len(px)), _first_corner_black(board, gray, px))
    detector = cv2.aruco.CharucoDetector(board.charuco())
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    return Detection(ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float64))


def _first_corner_black(board: Board, gray: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Order the corners as printed: seen from the printed side, row 0 to row 1 turns
    clockwise from the first row's direction (the board's z axis points away from the
    camera), and the square outside corner 0 is black.

    ``findChessboardCorners`` lists the corners row by row as they appear in the image,
    which may be the board mirrored or turned half a turn. The printed side faces the
    camera, which settles the mirror image. With an odd number of squares one way and an even number the other (e.g. 9x6
    inner corners, 10x7 squares) the two outer corner squares differ in colour, which
    settles the order; with equal parities a half-turned board looks the same, and the
    order is left as found (use a ChArUco board for extrinsics then)."""
    nx, ny = board.corner_grid
    right, down = px[1] - px[0], px[nx] - px[0]
    if right[0] * down[1] - right[1] * down[0] < 0:  # mirrored: reverse each row
        px = px.reshape(ny, nx, 2)[:, ::-1].reshape(-1, 2).copy()
    if (nx + ny) % 2 == 0:
        return px
    c0, right, down = px[0], px[1] - px[0], px[nx] - px[0]

    def grey(p):
        x, y = int(round(p[0])), int(round(p[1]))
        if not (0 <= x < gray.shape[1] and 0 <= y < gray.shape[0]):
            return None
        return float(gray[y, x])

    outside, inside = grey(c0 - 0.5 * (right + down)), grey(c0 + 0.5 * (right + down))
    if outside is not None and inside is not None and outside > inside:
        return px[::-1].copy()
    return px


def floor_points(board: Board, ids=None) -> np.ndarray:
    """World coordinates of the board's corners when the board lies on the floor and
    defines the world: origin at corner 0, x along the first row of corners, z up, so
    ``(x, y, z)_world = (x, -y, -z)_board`` (a half turn about the board's x axis)."""
    p = board.object_points() if ids is None else board.object_points()[np.asarray(ids)]
    return p * np.array([1.0, -1.0, -1.0])


FLOOR_POSE = (np.diag([1.0, -1.0, -1.0]), np.zeros(3))


def render_view(board: Board, camera, board_to_world=FLOOR_POSE, px_per_square: int = 60,
                background: int = 128, supersample: int = 2) -> np.ndarray:
    """The grey image ``camera`` takes of the board whose pose in the world is
    ``x_world = Rb x_board + tb`` (lens distortion included): each pixel's ray is cut
    with the board's plane and the printed board is sampled there (``cv2.remap``). The
    printed side is the one the board's z axis points away from (OpenCV's convention);
    from behind, the board is not seen. The default pose is the floor's (see
    :func:`floor_points`)."""
    if supersample > 1:  # render larger and average blocks of pixels: no aliased edges
        big = render_view(board, camera.scaled(camera.width * supersample, camera.height * supersample),
                          board_to_world, px_per_square * supersample, background, 1)
        return cv2.resize(big, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    Rb, tb = (np.asarray(a, dtype=np.float64) for a in board_to_world)
    tex, origin, pitch = board.texture(px_per_square)
    out = np.full((camera.height, camera.width), background, np.uint8)
    # only the pixels inside the board's outline can see it: project the outline densely
    th, tw = tex.shape
    e = np.linspace(0.0, 1.0, 40)
    ox, oy = origin + np.r_[e * tw, np.full(40, tw), e * tw, np.zeros(40)] * pitch, \
        origin + np.r_[np.zeros(40), e * th, np.full(40, th), e * th] * pitch
    outline = np.stack([ox, oy, np.zeros_like(ox)], axis=1) @ Rb.T + tb
    uv = camera.project(outline)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) == 0:
        return out
    x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 2, 0)
    x1, y1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 3, [camera.width, camera.height])
    if x1 <= x0 or y1 <= y0:
        return out
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(pix, camera.K, camera.dist, None, None,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)).reshape(-1, 2)
    # the rays in board coordinates: d_board = Rb^T R^T (x, y, 1); the centre likewise
    c = Rb.T @ (camera.centre - tb)
    A = Rb.T @ camera.R.T
    d = xy @ A[:, :2].T + A[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -c[2] / d[:, 2]
    bad = ~(s > 0) | (c[2] > 0)  # the printed side faces -z (board z points away from the camera)
    mx = ((c[0] + s * d[:, 0] - origin) / pitch).astype(np.float32)
    my = ((c[1] + s * d[:, 1] - origin) / pitch).astype(np.float32)
    mx[bad], my[bad] = -1e6, -1e6
    out[y0:y1, x0:x1] = cv2.remap(tex, mx.reshape(u.shape), my.reshape(u.shape), cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return out
