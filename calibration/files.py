"""Small input files of the calibration tools: known 3D points and their pixels."""
from __future__ import annotations

import numpy as np

from app.errors import InputError
from app.files import read_yaml

__all__ = ["read_points"]


def read_points(path) -> tuple[dict, dict]:
    """``world: {NAME: [x, y, z]}`` (metres) and ``pixels: {CAM: {NAME: [u, v]}}``."""
    doc = read_yaml(path, "points file")
    if not isinstance(doc, dict) or not isinstance(doc.get("world"), dict) or not isinstance(doc.get("pixels"), dict):
        raise InputError(f"{path}: expected world: {{NAME: [x, y, z]}} and pixels: {{CAM: {{NAME: [u, v]}}}}")
    world = {}
    for n, v in doc["world"].items():
        a = np.asarray(v, dtype=np.float64) if isinstance(v, list) else np.zeros(0)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise InputError(f"{path}: world.{n}: must be [x, y, z] in metres")
        world[str(n)] = a
    pixels = {}
    for cam, seen in doc["pixels"].items():
        if not isinstance(seen, dict):
            raise InputError(f"{path}: pixels.{cam}: must map point names to [u, v]")
        pixels[str(cam)] = {}
        for n, v in seen.items():
            a = np.asarray(v, dtype=np.float64) if isinstance(v, list) else np.zeros(0)
            if a.shape != (2,) or not np.all(np.isfinite(a)):
                raise InputError(f"{path}: pixels.{cam}.{n}: must be [u, v] in pixels")
            if str(n) not in world:
                raise InputError(f"{path}: pixels.{cam}.{n}: no world point {n}")
            pixels[str(cam)][str(n)] = a
    return world, pixels
