"""Naive tracking (thesis §4.3.1, Eq. 4.4-4.7): the new centroid of a target is the
centroid of the voxels inside its region of influence, an ellipsoid of axes
``(alpha s_x, alpha s_y, beta z)`` centred at the previous estimate (Eq. 4.2 with the
enlargements of §4.3.1: alpha = 1.5, beta = 1.2), after removing the voxels shared with
any other target's region (the exclusion of Eq. 4.7).
"""
from __future__ import annotations

import numpy as np

from app.tracking.scene import SceneFrame

__all__ = ["NaiveTarget"]


class NaiveTarget:
    """One target of the naive tracker (state: its centroid)."""

    name = "naive"

    def __init__(self, position, scene: SceneFrame, rng: np.random.Generator, params):
        self.x = np.asarray(position, dtype=np.float64).copy()
        self.p = params

    def region(self, scene: SceneFrame) -> np.ndarray:
        """``Y_t^k`` (Eq. 4.4): list positions of the voxels in the enlarged ellipsoid."""
        p = self.p
        rxy = p.alpha * p.sx
        cand = scene.near_xy(self.x, rxy)
        if cand.size == 0:
            return cand
        d = scene.centres_at(cand) - self.x
        rz = max(p.beta * self.x[2], scene.voxel_size)
        inside = (d[:, 0] ** 2 + d[:, 1] ** 2) / rxy ** 2 + (d[:, 2] / rz) ** 2 <= 1.0
        return cand[inside]

    @classmethod
    def step_all(cls, targets: list["NaiveTarget"], scene: SceneFrame) -> None:
        regions = [t.region(scene) for t in targets]
        counts = np.zeros(scene.n, dtype=np.int32)
        for r in regions:
            counts[r] += 1
        for t, r in zip(targets, regions):
            own = r[counts[r] == 1]           # Eq. 4.7: drop what another region also holds
            if own.size:
                t.x = scene.centres_at(own).mean(axis=0)   # Eq. 4.5
