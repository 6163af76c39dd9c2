"""The axes an export writes: the world's z-up frame (CONTRACT), or y-up for tools that
expect it (OpenSim, BVH): ``(x, y, z) -> (x, z, -y)``, a rotation of -90 degrees about x,
so the floor stays the floor and the room keeps its handedness."""
from __future__ import annotations

import numpy as np

from app.errors import InputError

__all__ = ["UP_AXES", "to_axes"]

UP_AXES = ("z", "y")
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def to_axes(points: np.ndarray, up: str) -> np.ndarray:
    """World points (..., 3) in the axes of ``up`` ("z": unchanged, "y": y-up)."""
    if up == "z":
        return np.asarray(points, float)
    if up == "y":
        return np.asarray(points, float) @ Y_UP.T
    raise InputError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
