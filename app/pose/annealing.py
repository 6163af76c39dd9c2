"""Annealing machinery shared by the pose filters (thesis §3.1-3.2, §6.3.4, §7.3.2).

* :func:`annealing_exponent`: the exponent ``beta_m`` of a layer chosen so that the
  particle survival rate of Eq. 3.21 equals the desired ``alpha_m``, by regula falsi
  (the Illinois variant, which keeps regula falsi's bracket but does not stall).
* :func:`survival_rate`: Eq. 3.20/3.21, ``alpha(beta) = (sum w^beta)^2 / (N sum w^2beta)``
  (the normalisation ``sum w^beta = 1`` written out).
* :func:`propagate`: ``y + N*(0, diag(sigma^2))``, the truncated Gaussian of §6.3.4:
  a draw outside the joint limits is redrawn (the thesis's rejection sampling); after
  ``tries`` rejections the few left are drawn uniformly inside the part of
  ``[mu - 3 sigma, mu + 3 sigma]`` within the limits, so no state ever leaves them.
* :func:`systematic_resample` (Alg. 2) and :func:`adaptive_resample` (Alg. 4: an
  output set of another size than the input).
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["survival_rate", "annealing_exponent", "propagate", "systematic_resample", "adaptive_resample",
           "normalised_weights", "weighted_mean"]


def survival_rate(log_w: np.ndarray, beta: float) -> float:
    """Particle survival rate ``alpha(beta)`` of weights ``w^beta`` (Eq. 3.21)."""
    a = beta * (np.asarray(log_w, dtype=np.float64) - np.max(log_w))
    w = np.exp(a)
    return float(w.sum() ** 2 / (len(w) * np.sum(w * w)))


def annealing_exponent(log_w: np.ndarray, alpha: float = 0.5, tol: float = 1e-3, max_iter: int = 60) -> float:
    """``beta`` with ``survival_rate(log_w, beta) = alpha`` (Eq. 3.21 by regula falsi).

    ``alpha(beta)`` decreases monotonically from 1 at ``beta = 0``; if even a huge
    ``beta`` keeps more than ``alpha`` (all weights equal) the largest tried is returned.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"survival rate {alpha} must be in (0, 1)")
    log_w = np.asarray(log_w, dtype=np.float64)
    spread = float(np.max(log_w) - np.min(log_w)) if len(log_w) else 0.0
    if not np.isfinite(spread) or spread <= 1e-12:
        return 1.0
    centred = log_w - np.max(log_w)   # survival_rate's, computed once for every trial beta
    n = len(log_w)

    def f(b):
        w = np.exp(b * centred)
        return float(w.sum() ** 2 / (n * np.sum(w * w))) - alpha
    lo, flo = 0.0, 1.0 - alpha
    hi = 1.0 / spread
    fhi = f(hi)
    while fhi > 0:
        lo, flo = hi, fhi
        hi *= 4.0
        fhi = f(hi)
        if hi > 1e9:
            return hi
    side = 0
    b = hi
    for _ in range(max_iter):
        b = (lo * fhi - hi * flo) / (fhi - flo)
        fb = f(b)
        if abs(fb) < tol:
            break
        if fb > 0:
            lo, flo = b, fb
            if side == 1:
                fhi *= 0.5
            side = 1
        else:
            hi, fhi = b, fb
            if side == -1:
                flo *= 0.5
            side = -1
    return float(b)


def normalised_weights(log_w: np.ndarray, beta: float = 1.0) -> np.ndarray:
    a = beta * (np.asarray(log_w, dtype=np.float64) - np.max(log_w))
    w = np.exp(a)
    return w / w.sum()


@njit(cache=True, nogil=True)
def _propagate_rows(mu, sigma, lo, hi, rng, tries, out, bad_i, bad_j):
    """:func:`propagate` for a per-DoF ``sigma (D,)`` in one numba loop: the same draws
    from the same generator in the same order (numba's ``Generator`` shares the bit
    generator's state and its normal and uniform algorithms with numpy's), so the
    results are identical to the numpy version below."""
    P, D = mu.shape
    n = 0
    for i in range(P):
        for j in range(D):
            v = mu[i, j] + rng.standard_normal() * sigma[j]
            out[i, j] = v
            if v < lo[j] or v > hi[j]:
                bad_i[n], bad_j[n] = i, j
                n += 1
    for _ in range(tries):
        if n == 0:
            return
        kept = 0
        for t in range(n):
            i, j = bad_i[t], bad_j[t]
            v = mu[i, j] + rng.standard_normal() * sigma[j]
            out[i, j] = v
            if v < lo[j] or v > hi[j]:
                bad_i[kept], bad_j[kept] = i, j
                kept += 1
        n = kept
    for t in range(n):
        i, j = bad_i[t], bad_j[t]
        a = min(max(mu[i, j] - 3 * sigma[j], lo[j]), hi[j])
        b = min(max(mu[i, j] + 3 * sigma[j], lo[j]), hi[j])
        out[i, j] = a + rng.random() * (b - a)


def propagate(states: np.ndarray, sigma: np.ndarray, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator,
              tries: int = 8) -> np.ndarray:
    """Every state diffused by ``N*(0, diag(sigma^2))`` truncated to ``[lo, hi]`` (§6.3.4)."""
    mu = np.asarray(states, dtype=np.float64)
    if mu.ndim == 2 and np.ndim(sigma) == 1 and np.ndim(lo) == 1 and np.ndim(hi) == 1 \
            and isinstance(rng, np.random.Generator) and len(mu):
        out = np.empty(mu.shape)
        bad_i, bad_j = np.empty(mu.size, np.int64), np.empty(mu.size, np.int64)
        _propagate_rows(np.ascontiguousarray(mu), np.ascontiguousarray(sigma, dtype=np.float64),
                        np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                        rng, int(tries), out, bad_i, bad_j)
        return out
    return _propagate_numpy(mu, sigma, lo, hi, rng, tries)


def _propagate_numpy(mu, sigma, lo, hi, rng, tries=8):
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), mu.shape)
    out = mu + rng.standard_normal(mu.shape) * sigma
    lo_b, hi_b = np.broadcast_to(lo, mu.shape), np.broadcast_to(hi, mu.shape)
    # the rejected entries' indices in C order, the order of a boolean mask: only they
    # are redrawn and tested again (the same draws as masking the whole array)
    bad = np.nonzero((out < lo_b) | (out > hi_b))
    for _ in range(tries):
        n = len(bad[0])
        if not n:
            return out
        redraw = mu[bad] + rng.standard_normal(n) * sigma[bad]
        out[bad] = redraw
        still = (redraw < lo_b[bad]) | (redraw > hi_b[bad])
        bad = tuple(i[still] for i in bad)
    n = len(bad[0])
    if n:
        lo_r, hi_r = lo_b[bad], hi_b[bad]
        a = np.clip(mu[bad] - 3 * sigma[bad], lo_r, hi_r)
        b = np.clip(mu[bad] + 3 * sigma[bad], lo_r, hi_r)
        out[bad] = a + rng.random(n) * (b - a)
    return out


def systematic_resample(weights: np.ndarray, rng: np.random.Generator, n_out: int | None = None) -> np.ndarray:
    """Indices drawn by systematic resampling (Alg. 2), ``n_out`` of them (default: as
    many as the weights, Alg. 4 otherwise)."""
    w = np.asarray(weights, dtype=np.float64)
    n = len(w) if n_out is None else int(n_out)
    c = np.cumsum(w)
    c[-1] = 1.0
    u = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(c, u, side="left"), len(w) - 1)


def adaptive_resample(weights: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """Systematic adaptive resampling (Alg. 4, Fig. 7.9(b)): the input sorted by weight
    (heaviest first), then ``n_out`` indices drawn systematically."""
    order = np.argsort(-np.asarray(weights))
    return order[systematic_resample(np.asarray(weights)[order], rng, n_out)]


def weighted_mean(states: np.ndarray, weights: np.ndarray, circular=(3,)) -> np.ndarray:
    """Weighted mean of states (Eq. 3.19), circular for the angles in ``circular`` (yaw)."""
    m = weights @ states
    for c in circular:
        m[c] = np.arctan2(weights @ np.sin(states[:, c]), weights @ np.cos(states[:, c]))
    return m
