"""Caillette's particle filter (CVIU 2007, §3.3, §5): particles propagated by the learnt
behaviour model, weighed by their blobs' relative entropy to the blobs fitted on the
voxels, resampled (SIR); the estimate is the particle of highest weight.

Each particle carries its state (27 DoFs), its joint-angle velocity (per frame) on the
model's principal axes (:class:`app.behaviour.model.Subspace`: the clusters live there;
the part of the angles off the axes stays as it was) and its VLMM state ``q`` (its
cluster the last label of ``q``). Prediction (:meth:`BehaviourFilter.predict`):

- §5.1, Eq. 3: the next cluster ``k'`` is drawn with probability proportional to
  ``N(X_t | mu_k', Sigma_k') gamma(q_t, k')`` over the clusters the VLMM lets follow
  ``q_t`` (``gamma`` above :data:`TRANSITION_FLOOR`: the smoothing's floor is no
  transition);
- §5.2, Eq. 4: staying in the cluster, ``dx_t = dx_{t-1} + lam ddx`` and
  ``x_t = x_{t-1} + dx_t + lam dx`` with ``(dx, ddx) ~ N(0, Sigma_k)`` (drawn through the
  eigen-decomposition's square root, as the paper says); jumping to a new cluster, the
  angles and velocities are drawn from it;
- the six global parameters: Gaussian noise (``global_sigma``), the root also shifted by
  the track's displacement;
- joint limits clip the angles (the paper's bounding values, §3.1).

The VLMM state of every particle goes back to the root on :meth:`recover` (§6.3: a fit
of the blobs too poor to trust), and half the particles are drawn afresh from the
clusters (the paper's "motion prototypes").
"""
from __future__ import annotations

import numpy as np

from app.behaviour.clusters import LOG_2PI
from app.behaviour.model import FEATURE_DOFS, BehaviourModel
from app.pose.model import LIMITS_HI, LIMITS_LO, N_DOF

__all__ = ["BehaviourFilter", "TRANSITION_FLOOR"]

TRANSITION_FLOOR = 0.01
GLOBAL_SIGMA = np.array([0.02, 0.02, 0.015, 0.08, 0.02, 0.02])   # x, y, z (m), yaw, pitch, roll (rad) per frame


class BehaviourFilter:
    """``particles`` particles of one person; ``lam`` the attenuation of Eq. 4."""

    def __init__(self, model: BehaviourModel, particles: int = 200, lam: float = 0.5,
                 global_sigma=GLOBAL_SIGMA, rng: np.random.Generator | None = None):
        self.model = model
        self.n = int(particles)
        self.lam = float(lam)
        self.global_sigma = np.asarray(global_sigma, float)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        c = model.clusters
        self.d = model.dims
        self.sub = model.subspace
        vals, vecs = np.linalg.eigh(c.covs)
        self.sqrt_cov = vecs * np.sqrt(np.maximum(vals, 0.0))[:, None, :]      # V sqrt(D): V sqrt(D) V^T z ~ same law
        chol = np.linalg.cholesky(c.covs)
        self.whiten = np.linalg.inv(chol)             # L^-1: |L^-1 (x - mu)|^2 the Mahalanobis distance
        self.log_norm = -np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1) - 0.5 * (2 * self.d) * LOG_2PI
        self._tau: dict[tuple, tuple] = {}            # (q, k) -> tau(q, k), memoised
        self.states = np.zeros((self.n, N_DOF))
        self.velocity = np.zeros((self.n, self.d))
        self.vlmm_state: list[tuple] = [()] * self.n
        self.cluster = np.zeros(self.n, np.int64)
        self.estimate: np.ndarray | None = None

    def _features(self) -> np.ndarray:
        return np.concatenate([self.sub.reduce(self.states[:, FEATURE_DOFS]), self.velocity], axis=1)

    def reset(self, state) -> None:
        """Every particle at ``state``, at rest, its VLMM state the root."""
        self.states = np.tile(np.asarray(state, float), (self.n, 1))
        self.velocity = np.zeros((self.n, self.d))
        X = self._features()
        self.cluster = self.model.clusters.label(X)
        self.vlmm_state = [self.model.vlmm.next_state((), int(k)) for k in self.cluster]
        self.estimate = np.asarray(state, float).copy()

    def recover(self, spread: float = 0.5) -> None:
        """§6.3: forget the VLMM states and spread a share ``spread`` of the particles over
        the motion prototypes: their angles and velocities drawn from a cluster picked by
        its weight (the global parameters kept: the track still holds the body)."""
        self.vlmm_state = [()] * self.n
        m = int(round(spread * self.n))
        if m <= 0:
            return
        c, rng = self.model.clusters, self.rng
        who = rng.choice(self.n, m, replace=False)
        k = np.minimum(np.searchsorted(np.cumsum(c.weights) / c.weights.sum(), rng.random(m)), c.k - 1)
        drawn = c.means[k] + self._cluster_noise(k, rng.standard_normal((m, 2 * self.d)))
        x, v = drawn[:, :self.d], drawn[:, self.d:]
        states = self.states[who].copy()
        states[:, FEATURE_DOFS] = self.sub.mean + x @ self.sub.basis.T
        self.states[who] = np.clip(states, LIMITS_LO, LIMITS_HI)
        self.velocity[who] = v
        self.cluster[who] = k

    def _cluster_noise(self, clusters: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Standard normal draws ``z`` (n, 2D) made draws of the clusters' covariances (each
        row by its cluster's square root, one matrix product per cluster)."""
        noise = np.empty_like(z)
        for k in np.unique(clusters):
            mine = clusters == k
            noise[mine] = z[mine] @ self.sqrt_cov[k].T
        return noise

    def support(self) -> dict[int, float]:
        """Share of the particles in each cluster (the blob fit's starts, §6.3)."""
        ks, counts = np.unique(self.cluster, return_counts=True)
        return {int(k): c / self.n for k, c in zip(ks, counts)}

    def predict(self, shift_xy=(0.0, 0.0)) -> None:
        """§5: every particle one frame on (module docstring)."""
        c, vlmm, rng = self.model.clusters, self.model.vlmm, self.rng
        X = self._features()
        new_cluster = self.cluster.copy()
        groups: dict[tuple, list[int]] = {}
        for p, q in enumerate(self.vlmm_state):
            groups.setdefault(q, []).append(p)
        logdens: dict[int, np.ndarray] = {}
        for q, members in groups.items():
            members = np.asarray(members)
            gamma = vlmm.gamma(q)
            cand = np.flatnonzero(gamma > TRANSITION_FLOOR)
            if not len(cand):
                cand = np.arange(c.k)
            lp = np.empty((len(members), len(cand)))
            for j, k in enumerate(cand):
                if k not in logdens:   # log N(X | mu_k, Sigma_k) of every particle, once a frame
                    z = (X - c.means[k]) @ self.whiten[k].T
                    logdens[k] = self.log_norm[k] - 0.5 * np.einsum("ij,ij->i", z, z)
                lp[:, j] = logdens[k][members] + np.log(gamma[k])
            lp -= lp.max(axis=1, keepdims=True)
            pr = np.exp(lp)
            pr /= pr.sum(axis=1, keepdims=True)
            u = rng.random(len(members))
            pick = np.minimum((pr.cumsum(axis=1) < u[:, None]).sum(axis=1), len(cand) - 1)
            new_cluster[members] = cand[pick]
        noise = self._cluster_noise(new_cluster, rng.standard_normal((self.n, 2 * self.d)))
        angles = self.states[:, FEATURE_DOFS]
        x = X[:, :self.d]
        off_axes = angles - self.sub.mean - x @ self.sub.basis.T
        stay = new_cluster == self.cluster
        v = np.where(stay[:, None], self.velocity + self.lam * noise[:, self.d:], 0.0)
        x_new = np.where(stay[:, None], x + v + self.lam * noise[:, :self.d], 0.0)
        jump = ~stay
        if jump.any():   # drawn from the new cluster
            drawn = c.means[new_cluster[jump]] + noise[jump]
            x_new[jump], v[jump] = drawn[:, :self.d], drawn[:, self.d:]
        states = self.states.copy()
        states[:, FEATURE_DOFS] = self.sub.mean + x_new @ self.sub.basis.T + off_axes
        states[:, :6] += rng.standard_normal((self.n, 6)) * self.global_sigma
        states[:, 0] += shift_xy[0]
        states[:, 1] += shift_xy[1]
        clipped = np.clip(states, LIMITS_LO, LIMITS_HI)
        # a joint limit stops the motion
        self.velocity = v + self.sub.reduce_change(clipped[:, FEATURE_DOFS] - states[:, FEATURE_DOFS])
        self.states = clipped
        self.vlmm_state = [self._next(q, int(k)) for q, k in zip(self.vlmm_state, new_cluster)]
        self.cluster = new_cluster

    def _next(self, q: tuple, k: int) -> tuple:
        """The VLMM's ``tau(q, k)``, memoised (a few dozen distinct pairs a frame)."""
        out = self._tau.get((q, k))
        if out is None:
            out = self._tau[(q, k)] = self.model.vlmm.next_state(q, k)
        return out

    def update(self, log_weights: np.ndarray) -> np.ndarray:
        """Weigh, take the best particle as the estimate, resample (SIR, systematic)."""
        lw = np.asarray(log_weights, float)
        best = int(np.argmax(lw))
        self.estimate = self.states[best].copy()
        self.resample(lw)
        return self.estimate

    def resample(self, log_weights: np.ndarray) -> None:
        """Systematic resampling by ``log_weights``, each particle's velocity, cluster and
        VLMM state with it."""
        lw = np.asarray(log_weights, float)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        positions = (self.rng.random() + np.arange(self.n)) / self.n
        idx = np.minimum(np.searchsorted(np.cumsum(w), positions), self.n - 1)
        self.states, self.velocity = self.states[idx], self.velocity[idx]
        self.cluster = self.cluster[idx]
        self.vlmm_state = [self.vlmm_state[i] for i in idx]
