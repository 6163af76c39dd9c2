"""Small recordings written with OpenCV for tests that need a recording folder fast
(the simulator makes the realistic ones)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.recording import RecordingWriter
from calibration import Calibration, Camera


def tiny_calibration(n_cameras: int = 2, width: int = 160, height: int = 120, fps: float = 25.0) -> Calibration:
    """Cameras around a 4 x 4 x 2.5 m room, looking at its centre."""
    cams = []
    for i in range(n_cameras):
        a = 2 * np.pi * i / n_cameras + np.pi / 4
        pos = [2 + 2.8 * np.cos(a), 2 + 2.8 * np.sin(a), 2.4]
        cams.append(Camera.look_at(f"cam{i}", pos, [2, 2, 0.9], width, height, hfov_deg=75,
                                   dist=[-0.08, 0.01, 0, 0, 0]))
    return Calibration(fps, np.zeros(3), np.array([4.0, 4.0, 2.5]), tuple(cams))


def write_tiny_recording(path, frames: int = 60, n_cameras: int = 2, width: int = 160, height: int = 120,
                         fps: float = 25.0, background: bool = True) -> Path:
    """A textured background and a bright box moving across the view of every camera."""
    calib = tiny_calibration(n_cameras, width, height, fps)
    rng = np.random.default_rng(1)
    bgs = {}
    for c in calib.cameras:
        noise = rng.integers(60, 120, (height // 8 + 1, width // 8 + 1, 3), dtype=np.uint8)
        bgs[c.name] = cv2.resize(noise, (width, height), interpolation=cv2.INTER_LINEAR)
    with RecordingWriter(path, calib, codec="MJPG") as w:
        if background:
            for name, bg in bgs.items():
                w.write_background(name, bg)
        for i in range(frames):
            images = {}
            for c in calib.cameras:
                img = bgs[c.name].copy()
                x = int((i / max(1, frames - 1)) * (width - width // 4))
                cv2.rectangle(img, (x, height // 3), (x + width // 6, height - 10), (40, 200, 240), -1)
                images[c.name] = img
            w.write(images)
    return Path(path)
