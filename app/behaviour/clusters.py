"""Gaussian clusters of the feature space with the number of components chosen by the data
(Caillette, Galata and Howard, CVIU 2007, §4.1: "a variant of the EM algorithm proposed by
Figueiredo and Jain [14]").

The variant implemented is Figueiredo and Jain's own (IEEE PAMI 24(3), 2002, "Unsupervised
learning of finite mixture models", their Fig. 2): component-wise EM (CEM², each
component's weight, mean and covariance updated in turn, the responsibilities recomputed
with it) minimising the minimum-message-length criterion

    L = N/2 sum_m log(n a_m / 12) + k/2 log(n / 12) + k (N + 1) / 2 - log p(Y | theta),

N the parameters of one component (d + d (d + 1) / 2, full covariances), whose M-step
weight ``a_m = max(0, sum_i w_im - N/2) / sum_j max(0, sum_i w_ij - N/2)`` annihilates the
components the data do not support (as in their published code: ``a_m`` from its own
responsibilities, then every weight renormalised, component by component). It starts
from ``k_max`` components on random data points (covariances ``sigma^2 I``, a tenth of
the data's mean variance), runs CEM² to convergence, keeps the mixture of least L,
removes the weakest component and starts again, down to ``k_min``. The one departure: a ridge (``reg`` times the data's mean
variance) on every covariance so that a cluster of a few collinear points stays
invertible (the paper's own guard against singularities is the annihilation alone).

No bus and no scikit-learn: plain numpy, 15 s for the 14 600 16-d vectors of the shipped model.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GaussianClusters", "fit_clusters", "log_gauss", "significant"]

LOG_2PI = np.log(2.0 * np.pi)


def significant(a, digits: int = 7) -> list:
    """``a`` as (nested) lists of floats rounded to ``digits`` significant digits (model files)."""
    return np.vectorize(lambda v: float(f"{v:.{digits}g}"), otypes=[float])(np.asarray(a, float)).tolist()


def log_gauss(X: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``log N(x | mean, cov)`` of every row of ``X`` (n, d)."""
    L = np.linalg.cholesky(cov)
    z = np.linalg.solve(L, (X - mean).T)
    return -0.5 * (np.sum(z * z, axis=0) + X.shape[1] * LOG_2PI) - np.sum(np.log(np.diag(L)))


@dataclass
class GaussianClusters:
    """A Gaussian mixture: ``weights`` (k,), ``means`` (k, d), ``covs`` (k, d, d)."""

    weights: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    message_length: float = float("nan")

    @property
    def k(self) -> int:
        return len(self.weights)

    def log_densities(self, X: np.ndarray) -> np.ndarray:
        """(n, k): ``log N(x_i | mu_m, Sigma_m)``."""
        X = np.atleast_2d(np.asarray(X, float))
        return np.stack([log_gauss(X, m, c) for m, c in zip(self.means, self.covs)], axis=1)

    def label(self, X: np.ndarray) -> np.ndarray:
        """The cluster (n,) each row of ``X`` belongs to (the most probable a posteriori)."""
        return np.argmax(self.log_densities(X) + np.log(self.weights), axis=1)

    def to_dict(self) -> dict:
        """Plain lists, 7 significant digits (a model file of about a hundred kB)."""
        return {"weights": significant(self.weights), "means": significant(self.means),
                "covs": significant(self.covs), "message_length": float(self.message_length)}

    @classmethod
    def from_dict(cls, d: dict) -> "GaussianClusters":
        w = np.asarray(d["weights"], float)
        means = np.asarray(d["means"], float).reshape(len(w), -1)
        covs = np.asarray(d["covs"], float).reshape(len(w), means.shape[1], means.shape[1])
        if not (np.all(np.isfinite(w)) and np.all(w >= 0) and abs(w.sum() - 1) < 1e-6):
            raise ValueError("cluster weights are not a distribution")
        for c in covs:
            np.linalg.cholesky(c)   # positive definite, or LinAlgError
        return cls(w, means, covs, float(d.get("message_length", "nan")))


def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    return np.squeeze(m, axis=axis) + np.log(np.sum(np.exp(a - m), axis=axis))


def fit_clusters(X: np.ndarray, k_max: int = 30, k_min: int = 1, tol: float = 1e-5, reg: float = 1e-3,
                 max_sweeps: int = 500, rng: np.random.Generator | None = None) -> GaussianClusters:
    """Figueiredo and Jain's mixture of the rows of ``X`` (n, d) (module docstring): the
    mixture of least message length over ``k_min..k_max`` components."""
    X = np.asarray(X, float)
    n, d = X.shape
    rng = rng if rng is not None else np.random.default_rng(0)
    k_max = int(min(k_max, n))
    N = d + d * (d + 1) / 2.0
    var = float(np.mean(np.var(X, axis=0))) or 1.0
    ridge = reg * var * np.eye(d)
    means = X[rng.choice(n, k_max, replace=False)].copy()
    covs = np.repeat((0.1 * var * np.eye(d))[None], k_max, axis=0)
    alive = np.ones(k_max, bool)
    a = np.full(k_max, 1.0 / k_max)
    logu = np.full((n, k_max), -np.inf)
    for m in range(k_max):
        logu[:, m] = log_gauss(X, means[m], covs[m])

    def message_length() -> float:
        on = alive & (a > 0)
        loglik = float(np.sum(_logsumexp(logu[:, on] + np.log(a[on]), axis=1)))
        k = int(on.sum())
        return N / 2 * np.sum(np.log(n * a[on] / 12.0)) + k / 2 * np.log(n / 12.0) + k * (N + 1) / 2 - loglik

    best = None
    while alive.sum() >= k_min:
        previous = np.inf
        for _ in range(max_sweeps):
            for m in np.flatnonzero(alive):
                # as Figueiredo and Jain's own code: a_m from its responsibilities, then all renormalised
                joint = logu[:, alive] + np.log(np.maximum(a[alive], 1e-300))
                w = np.exp(logu[:, m] + np.log(max(a[m], 1e-300)) - _logsumexp(joint, axis=1))
                a[m] = max(0.0, w.sum() - N / 2) / n
                a[alive] /= max(a[alive].sum(), 1e-300)
                if a[m] > 0:
                    s = w.sum()
                    means[m] = w @ X / s
                    D = X - means[m]
                    covs[m] = (D * w[:, None]).T @ D / s + ridge
                    logu[:, m] = log_gauss(X, means[m], covs[m])
                else:
                    alive[m] = False
                    logu[:, m] = -np.inf
                if not alive.any():
                    break
            if not alive.any():
                break
            L = message_length()
            if abs(previous - L) < tol * abs(L):
                break
            previous = L
        if not alive.any():
            break
        L = message_length()
        if best is None or L < best.message_length:
            keep = np.flatnonzero(alive)
            best = GaussianClusters(a[keep] / a[keep].sum(), means[keep].copy(), covs[keep].copy(), float(L))
        if alive.sum() <= k_min:
            break
        weakest = np.flatnonzero(alive)[np.argmin(a[alive])]
        alive[weakest] = False
        a[weakest] = 0.0
        logu[:, weakest] = -np.inf
        a[alive] /= a[alive].sum()
    if best is None:
        raise ValueError(f"no mixture: {n} points are too few for {d}-d clusters")
    return best
