"""One person's pose by Caillette, Galata and Howard's method (CVIU 2007): the behaviour
model's particle filter (:mod:`.filter`) weighed through Gaussian blobs (:mod:`.blobs`).

Each frame (§5-6): the particles are propagated; the blobs are fitted to the person's
voxels from the blobs of the previous estimate and of the mean poses of the clusters that
hold at least ``support`` of the particles (at most ``starts`` of them; §6.3), the best
fit kept as the frame's evidence; each particle's weight is ``1 / D_KL(F || G)`` (Eq. 9;
§6.4: "proportional to the inverse of the relative entropy"), the best particle is the
estimate, the set is resampled. A fit whose voxels' mean log-likelihood falls ``lost``
standard deviations below its mean over the frames since the start is a tracking failure
(the paper: "a poor fit", no threshold given): the VLMM states are
reset and half the particles spread over the clusters (§6.3,
:meth:`~app.behaviour.filter.BehaviourFilter.recover`).

The voxels are those the reconstruction coloured (its surface voxels, as the paper's
§6.2; the inside of a hull is black and would make blobs of its own). The blobs' shapes
and colours are learnt from the voxels at the starting pose
(:func:`app.behaviour.blobs.learn_blobs`): the paper learns them "during the first frames"
without saying from which poses; here the caller gives the pose (the pose worker: its
first frames posed by SHBM-APF, ``pose.behaviour_start``).
"""
from __future__ import annotations

import numpy as np

from app.behaviour.blobs import BlobModel, blob_divergences, fit_blobs, learn_blobs, voxel_logliks
from app.behaviour.filter import BehaviourFilter
from app.behaviour.model import FEATURE_DOFS, BehaviourModel
from app.pose.annealing import annealing_exponent, propagate
from app.pose.model import LIMITS_HI, LIMITS_LO, SIGMA0

__all__ = ["BehaviourTracker", "EVALUATIONS"]

EVALUATIONS = ("kl", "voxels", "model")


class BehaviourTracker:
    """``evaluation``: ``kl`` (the paper's: the blobs fitted to the voxels, each particle
    weighed by its blobs' relative entropy to them) or ``voxels`` (ours: each particle's
    blobs scored directly by the voxels' likelihood under them, at most ``voxels`` of
    them drawn a frame, the mean log-likelihood times ``temperature``; no fit) or ``model``
    (ours: the caller's likelihood, :meth:`step`'s ``score``; the pose worker's is the
    thesis's voxel likelihood with its additions, the one SHBM-APF weighs with).
    ``rng``: a seed or a generator (the pose worker's, so that its snapshot holds it)."""

    def __init__(self, model: BehaviourModel, height: float, particles: int = 200, lam: float = 0.5,
                 support: float = 0.1, starts: int = 3, iterations: int = 4, lost: float = 3.0, rng=0,
                 evaluation: str = "kl", temperature: float = 20.0, voxels: int = 300,
                 survival: float = 0.5, layers: int = 1, refine: float = 0.5):
        if evaluation not in EVALUATIONS:
            raise ValueError(f"evaluation {evaluation!r} is not one of {', '.join(EVALUATIONS)}")
        self.model = model
        self.height = float(height)
        self.filter = BehaviourFilter(model, particles, lam, rng=np.random.default_rng(rng))
        self.support, self.starts, self.iterations, self.lost = float(support), int(starts), int(iterations), lost
        self.blobs: BlobModel | None = None
        # the fit qualities of the frames not lost: count, mean and summed squared deviation
        # (Welford), so that a person tracked for days costs what one tracked a minute does
        self.fits = (0, 0.0, 0.0)
        self.recoveries = 0
        self.lost_now = False     # the last step found the tracker lost
        self.last_position = None
        self.evaluation, self.temperature, self.voxels = evaluation, float(temperature), int(voxels)
        self.survival = float(survival)
        self.layers, self.refine = int(layers), float(refine)

    @staticmethod
    def coloured(centres, colours):
        """The voxels the reconstruction coloured (its surface, §6.2: the inside stays
        black), or every voxel, grey, when it coloured fewer than 30."""
        centres = np.asarray(centres, float).reshape(-1, 3)
        if colours is not None and len(colours) == len(centres):
            colours = np.asarray(colours, float)
            seen = colours.any(axis=1)
            if seen.sum() >= 30:
                return centres[seen], colours[seen]
        return centres, np.full((len(centres), 3), 128.0)

    def start(self, state, centres, colours, position=None) -> None:
        """Learn the blobs from the voxels at ``state`` and put every particle there."""
        centres, colours = self.coloured(centres, colours)
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

    def step(self, centres, colours, position=None, score=None) -> np.ndarray:
        """One frame of the person's voxels (centres (N, 3), colours (N, 3) RGB): the state.
        ``score(states) -> log-likelihoods`` (the ``model`` evaluation: the caller's
        likelihood of the states, e.g. the thesis's voxel likelihood), its weights tempered
        to a survival rate of ``survival`` (Eq. 3.21 of the thesis)."""
        shift = (0.0, 0.0)
        if position is not None and self.last_position is not None:
            shift = tuple(np.asarray(position, float)[:2] - self.last_position[:2])
        if position is not None:
            self.last_position = np.asarray(position, float).copy()
        self.filter.predict(shift)
        if self.evaluation == "model":
            if score is None:
                raise ValueError("the model evaluation needs the caller's score")
            ll = np.asarray(score(self.filter.states), float)
            quality, lw = float(ll.max()), annealing_exponent(ll, self.survival) * ll
            f = self.filter
            for m in range(1, self.layers):   # ours: annealing layers about the prediction (Eq. 3.22)
                f.resample(lw)
                sigma = SIGMA0 * self.refine * np.sqrt(self.survival ** m)
                f.states = propagate(f.states, sigma, LIMITS_LO, LIMITS_HI, f.rng)
                ll = np.asarray(score(f.states), float)
                lw = annealing_exponent(ll, self.survival) * ll
        elif self.evaluation == "voxels":
            centres, colours = self.coloured(centres, colours)
            idx = np.arange(len(centres))
            if len(idx) > self.voxels:
                idx = self.filter.rng.choice(len(centres), self.voxels, replace=False)
            ll = voxel_logliks(self.blobs, self.filter.states, centres[idx], colours[idx])
            quality, lw = float(ll.max()), self.temperature * ll
        else:
            centres, colours = self.coloured(centres, colours)
            fitted = fit_blobs(self.blobs, self._fit_starts(), centres, colours, self.iterations)
            quality = fitted.loglik / max(len(centres), 1)
            d = blob_divergences(self.blobs, fitted, self.filter.states)
            lw = -np.log(np.maximum(d, 1e-3))   # w = 1 / D
        estimate = self.filter.update(lw)
        n, mean, m2 = self.fits
        self.lost_now = n >= 5 and quality < mean - self.lost * max(np.sqrt(m2 / n), 1e-6)
        if self.lost_now:
            self.filter.recover()   # §6.3: a poor fit, the tracker is lost: next frame's particles spread
            self.recoveries += 1
        else:
            delta = quality - mean
            mean += delta / (n + 1)
            self.fits = (n + 1, mean, m2 + delta * (quality - mean))
        return estimate

    def restart(self, state, position=None) -> None:
        """Every particle at ``state`` again (the blobs and the fits' statistics kept): the
        caller found the person by other means after a failure."""
        self.filter.reset(state)
        self.last_position = None if position is None else np.asarray(position, float).copy()
