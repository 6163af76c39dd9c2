"""The relative entropy of Gaussian blob mixtures (Caillette, Galata and Howard, CVIU 2007,
§6.4, Eqs. 7-10): how a particle's blobs ``F = sum_i a_i f_i`` are weighed against the blobs
fitted to the voxels, ``G = sum_j b_j g_j``.

Eq. 10 as printed, ``1/2 (ln |S_f|/|S_g| - d + tr(S_f^-1 S_g) + (m_g - m_f)^T S_f^-1 (m_g - m_f))``,
is the divergence the other way round, D_KL(g||f): the roles of f and g are swapped against
its own left-hand side (``int f ln f/g``). :func:`gaussian_kl` is the left-hand side,

    D_KL(f||g) = 1/2 (ln |S_g|/|S_f| - d + tr(S_g^-1 S_f) + (m_g - m_f)^T S_g^-1 (m_g - m_f)),

checked against a Monte-Carlo estimate in the tests. Eq. 8 (Goldberger's approximation for
mixtures whose components do not overlap) is :func:`mixture_kl`; Eq. 9, the same with the
correspondence ``f_i <-> g_pi(i)`` kept, is :func:`matched_kl` (linear in the blobs).
"""
from __future__ import annotations

import numpy as np

__all__ = ["gaussian_kl", "mixture_kl", "matched_kl"]


def gaussian_kl(mean_f, cov_f, mean_g, cov_g) -> np.ndarray:
    """D_KL(f||g) of Gaussians ``f = N(mean_f, cov_f)``, ``g = N(mean_g, cov_g)`` (d-dim;
    leading axes broadcast)."""
    mean_f, mean_g = np.asarray(mean_f, float), np.asarray(mean_g, float)
    cov_f, cov_g = np.asarray(cov_f, float), np.asarray(cov_g, float)
    d = mean_f.shape[-1]
    Lg = np.linalg.cholesky(cov_g)
    _, logdet_f = np.linalg.slogdet(cov_f)
    logdet_g = 2.0 * np.sum(np.log(np.diagonal(Lg, axis1=-2, axis2=-1)), axis=-1)
    inv_g = np.linalg.inv(cov_g)
    diff = (mean_g - mean_f)[..., None]
    maha = np.squeeze(np.swapaxes(diff, -1, -2) @ inv_g @ diff, axis=(-2, -1))
    trace = np.trace(inv_g @ cov_f, axis1=-2, axis2=-1)
    return 0.5 * (logdet_g - logdet_f - d + trace + maha)


def mixture_kl(weights_f, means_f, covs_f, weights_g, means_g, covs_g) -> float:
    """Eq. 8: ``sum_i a_i min_j (D_KL(f_i||g_j) + ln(a_i / b_j))``."""
    a, b = np.asarray(weights_f, float), np.asarray(weights_g, float)
    D = gaussian_kl(np.asarray(means_f)[:, None], np.asarray(covs_f)[:, None],
                    np.asarray(means_g)[None], np.asarray(covs_g)[None])        # (n_f, n_g)
    return float(np.sum(a * np.min(D + np.log(a[:, None] / b[None]), axis=1)))


def matched_kl(weights_f, means_f, covs_f, weights_g, means_g, covs_g) -> float:
    """Eq. 9: ``sum_i a_i (D_KL(f_i||g_i) + ln(a_i / b_i))``, blob i of F against blob i of G."""
    a, b = np.asarray(weights_f, float), np.asarray(weights_g, float)
    return float(np.sum(a * (gaussian_kl(means_f, covs_f, means_g, covs_g) + np.log(a / b))))
