"""One person's pose by Caillette, Galata and Howard's method (CVIU 2007): the behaviour
model's particle filter (:mod:`.filter`) weighed through Gaussian blobs (:mod:`.blobs`).

Each frame (§5-6): the particles are propagated; the blobs are fitted to the person's
voxels from the blobs of the previous estimate and of the mean poses of the clusters that
hold at least ``support`` of the particles (at most ``starts`` of them; §6.3), the best
fit kept as the frame's evidence; each particle's weight is ``1 / D_KL(F || G)`` (Eq. 9;
§6.4: "proportional to the inverse of the relative entropy"), the best particle is the
estimate, the set is resampled. A fit whose voxels' mean log-likelihood falls ``lost``
below the mean of the frames since the start is a tracking failure: the VLMM states are
reset (§6.3).

The blobs' shapes and colours are learnt from the voxels at the starting pose
(:func:`app.behaviour.blobs.learn_blobs`): the paper learns them "during the first frames"
without saying from which poses; here the caller gives the pose (the pose worker: its
first frames posed by SHBM-APF).
"""
from __future__ import annotations

import numpy as np

from app.behaviour.blobs import BlobModel, blob_divergences, fit_blobs, learn_blobs
from app.behaviour.filter import BehaviourFilter
from app.behaviour.model import FEATURE_DOFS, BehaviourModel

__all__ = ["BehaviourTracker"]


class BehaviourTracker:
    def __init__(self, model: BehaviourModel, height: float, particles: int = 200, lam: float = 0.5,
                 support: float = 0.1, starts: int = 3, iterations: int = 4, lost: float = 1.5, seed: int = 0,
                 sharpness: float = 0.0):
        self.model = model
        self.height = float(height)
        self.filter = BehaviourFilter(model, particles, lam, rng=np.random.default_rng(seed))
        self.support, self.starts, self.iterations, self.lost = float(support), int(starts), int(iterations), lost
        self.blobs: BlobModel | None = None
        self.fits: list[float] = []
        self.recoveries = 0
        self.sharpness = float(sharpness)   # 0: w = 1 / D (the paper); > 0: w = exp(-sharpness D) (ours)
        self.last_position = None

    def start(self, state, centres, colours, position=None) -> None:
        """Learn the blobs from the voxels at ``state`` and put every particle there."""
        self.blobs = learn_blobs(self.height, state, centres, colours)
        self.filter.reset(state)
        self.last_position = None if position is None else np.asarray(position, float).copy()

    def _fit_starts(self) -> np.ndarray:
        est = self.filter.estimate
        starts = [est]
        supported = sorted(((s, k) for k, s in self.filter.support().items() if s >= self.support), reverse=True)
        for _, k in supported[:self.starts]:
            st = est.copy()
            sub = self.model.subspace
            st[FEATURE_DOFS] = sub.mean + sub.basis @ self.model.clusters.means[k][:self.model.dims]
            starts.append(st)
        return np.array(starts)

    def step(self, centres, colours, position=None) -> np.ndarray:
        """One frame of the person's voxels (centres (N, 3), colours (N, 3) RGB): the state."""
        shift = (0.0, 0.0)
        if position is not None and self.last_position is not None:
            shift = tuple(np.asarray(position, float)[:2] - self.last_position[:2])
        if position is not None:
            self.last_position = np.asarray(position, float).copy()
        self.filter.predict(shift)
        fitted = fit_blobs(self.blobs, self._fit_starts(), centres, colours, self.iterations)
        per_voxel = fitted.loglik / max(len(centres), 1)
        if len(self.fits) >= 5 and per_voxel < np.mean(self.fits) - self.lost:
            self.filter.recover()   # §6.3: a poor fit, the tracker is lost
            self.recoveries += 1
        else:
            self.fits.append(per_voxel)
        d = blob_divergences(self.blobs, fitted, self.filter.states)
        lw = -self.sharpness * d if self.sharpness > 0 else -np.log(np.maximum(d, 1e-3))
        return self.filter.update(lw)
