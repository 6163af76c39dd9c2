"""Marker-based motion capture of one person: the annealed particle filter (§3.2,
:class:`app.pose.filters.APF`) over the body model's 27-DoF state, weighted by the
marker likelihood of §6.4.1.2 (:class:`app.markers.likelihood.MarkerScorer`). The
thesis's best setting (§6.6.1, Fig. 6.13): L = 3 layers of N_pL = 700 particles.

:func:`fit_state` poses the body model on 3D joints by least squares (the start of a
track: the true joints on simulated clips, triangulated markers in a room).
"""
from __future__ import annotations

import numpy as np

from app.markers.likelihood import MarkerScorer
from app.pose.filters import APF
from app.pose.model import LIMITS_HI, LIMITS_LO, BodyModel, neutral_state

__all__ = ["MarkerTracker", "fit_state"]


def fit_state(height: float, joints: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """The state (27,) of a body model of ``height`` whose joints best match ``joints`` (15, 3)."""
    from scipy.optimize import least_squares

    model = BodyModel(height)
    joints = np.asarray(joints, float)
    if start is None:
        pelvis = joints[0]
        across = joints[12] - joints[9]          # r_hip - l_hip
        yaw = float(np.arctan2(across[1], across[0])) - np.pi / 2   # the model faces +x at yaw 0
        start = neutral_state(height, (pelvis[0], pelvis[1], pelvis[2]), yaw)
    lo = np.where(np.isfinite(LIMITS_LO), LIMITS_LO, -1e3)
    hi = np.where(np.isfinite(LIMITS_HI), LIMITS_HI, 1e3)
    x0 = np.clip(start, lo + 1e-6, hi - 1e-6)
    best = None
    for turn in (0.0, np.pi):                    # the yaw guess may face the wrong way
        x = x0.copy()
        x[3] += turn
        x = np.clip(x, lo + 1e-6, hi - 1e-6)
        r = least_squares(lambda s: (model.joints(s) - joints).ravel(), x, bounds=(lo, hi))
        if best is None or r.cost < best.cost:
            best = r
    return best.x


class MarkerTracker:
    """One person's pose from frames of marker detections (per camera (Q_n, 2) pixels)."""

    def __init__(self, cameras, height: float, particles: int = 700, layers: int = 3, rho: float = 20.0,
                 sigma: float = 1.0, cost: str = "thesis", alpha: float = 0.5, seed: int = 0):
        self.model = BodyModel(height)
        self.scorer = MarkerScorer(cameras, height, rho=rho, sigma=sigma, cost=cost)
        self.filter = APF(particles=particles, layers=layers, alpha=alpha, rng=np.random.default_rng(seed))
        self.state: np.ndarray | None = None

    def start(self, state: np.ndarray) -> None:
        self.state = np.asarray(state, float).copy()
        self.filter.reset(self.state, spread=0.25 * self.filter.sigma0)

    def step(self, detections) -> np.ndarray:
        """One frame: the estimated state (27,)."""
        if self.state is None:
            raise RuntimeError("MarkerTracker.start() first")
        self.scorer.set_detections(detections)
        self.state = self.filter.step(self.scorer)
        return self.state

    def joints(self) -> np.ndarray:
        return self.model.joints(self.state)
