"""A mosaic of every camera's view of one frame with the ground-truth skeletons drawn
(``smartroom simulate --preview PNG``): the quickest way to see that the people look
like people from every view and that the ground truth sits on them."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from app.drawing import outlined_text
from app.messages import JOINTS

__all__ = ["BONES", "draw_skeletons", "mosaic", "write_preview"]

#: Skeleton edges between the contract's joints.
BONES = (
    ("pelvis", "neck"), ("neck", "head"),
    ("neck", "l_shoulder"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"),
    ("neck", "r_shoulder"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
    ("pelvis", "l_hip"), ("l_hip", "l_knee"), ("l_knee", "l_ankle"),
    ("pelvis", "r_hip"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
)
_COLOURS = [(0, 220, 255), (255, 120, 0), (60, 230, 60), (230, 60, 230), (60, 60, 255), (255, 255, 60)]


def draw_skeletons(img: np.ndarray, camera, record: dict) -> np.ndarray:
    """Draw the record's skeletons as ``camera`` sees them (distortion included); joints
    no camera sees are drawn hollow, the centroid as a cross."""
    out = img.copy()
    for person in record.get("people", []):
        colour = _COLOURS[(person["id"] - 1) % len(_COLOURS)]
        pts = np.array([person["joints"][n] for n in JOINTS])
        uv, z = camera.project(pts, return_depth=True)
        idx = {n: i for i, n in enumerate(JOINTS)}
        for a, b in BONES:
            pa, pb = uv[idx[a]], uv[idx[b]]
            if z[idx[a]] > 0 and z[idx[b]] > 0 and np.all(np.isfinite([*pa, *pb])):
                cv2.line(out, tuple(int(round(v)) for v in pa), tuple(int(round(v)) for v in pb), colour, 1,
                         cv2.LINE_AA)
        hidden = person.get("visible", {})
        for n, i in idx.items():
            if z[i] > 0 and np.all(np.isfinite(uv[i])):
                cv2.circle(out, (int(round(uv[i, 0])), int(round(uv[i, 1]))), 3, colour,
                           1 if hidden.get(n, True) is False else -1, cv2.LINE_AA)
        c, zc = camera.project(np.array([person["centroid"]]), return_depth=True)
        if zc[0] > 0 and np.all(np.isfinite(c)):
            cv2.drawMarker(out, (int(round(c[0, 0])), int(round(c[0, 1]))), (255, 255, 255), cv2.MARKER_CROSS, 8, 1)
    return out


def mosaic(images: list[np.ndarray], names: list[str], columns: int | None = None) -> np.ndarray:
    """Tile images in a grid with their names written on them; images of other sizes are
    scaled to the widest one's width (aspect kept) and padded to the tallest."""
    n = len(images)
    columns = columns or (2 if n <= 4 else 3)
    rows = math.ceil(n / columns)
    w = max(img.shape[1] for img in images)
    images = [img if img.shape[1] == w else cv2.resize(img, (w, round(img.shape[0] * w / img.shape[1])),
                                                       interpolation=cv2.INTER_AREA) for img in images]
    h = max(img.shape[0] for img in images)
    out = np.zeros((rows * h, columns * w, 3), dtype=np.uint8)
    for k, (img, name) in enumerate(zip(images, names)):
        r, c = divmod(k, columns)
        tile = np.zeros((h, w, 3), dtype=np.uint8)
        tile[:img.shape[0], :img.shape[1]] = img
        outlined_text(tile, name, (8, 22), 0.6, (255, 255, 255), 1, outline=2)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return out


def write_preview(path, simulator, frame: int, skeletons: bool = True) -> Path:
    """Render one frame of a :class:`~app.simulation.simulator.Simulator` and write the
    mosaic of all its cameras (with the skeletons) to a PNG."""
    images, _labels, record = simulator.render(frame)
    tiles = []
    for cam in simulator.calibration.cameras:
        img = images[cam.name]
        tiles.append(draw_skeletons(img, cam, record) if skeletons else img)
    out = mosaic(tiles, [f"{c.name}  frame {frame}" for c in simulator.calibration.cameras])
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), out):
        from app.errors import InputError
        raise InputError(f"{path}: cannot write the preview image (use a .png name)")
    return path
