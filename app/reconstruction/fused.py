"""Caillette's fused segmentation and reconstruction (Caillette, Galata and Howard,
CVIU 2007, §6.1 "Hierarchical volumetric reconstruction"; seed ``003_*``).

Instead of a binary mask per camera, each camera gives, per pixel, the Mahalanobis
distance ``d_M(s)`` of its colour to the background model (a full Gaussian in YUV with
a shadowed twin, :class:`app.segmentation.YuvBackground`). Under the background
hypothesis ``d_M`` follows a chi-square distribution with 3 degrees of freedom, and the
sum over ``k`` independent samples one with ``3k``. A voxel (or a coarse cell of the
octree) is classified in each view from the ``k`` pixel samples of its projected area
(Eq. 6):

    if   sum_i d_M(s_i) <= T_k(alpha)       then background
    elif for all i, d_M(s_i) > T_1(alpha)   then foreground
    else                                         edge

with the threshold of Eq. 5, ``T_k(alpha)`` the ``alpha`` quantile of chi-square with
``3k`` degrees of freedom: ``int_0^{T_k} chi2_{3k}(t) dt = alpha`` (the extracted
equation reads so; the paper's alpha = 0.99). A cell is discarded when it is
background in a view (here: in more than ``tolerance`` views, §2.2.4's tolerance),
reconstructed whole when foreground in every view that sees it, and otherwise
subdivided (octants) down to the voxels.

Choices where the paper leaves room, each said here:

* **Samples.** The paper samples ``k = sqrt(A)`` pixels uniformly from a projected area
  of ``A`` pixels (for speed). Here the area is the pixel box of the cell's voxel
  centres (:class:`~.projection.ProjectionTable`) and summed-area tables give the sum
  of ``d_M`` over *all* its pixels at no extra cost, so by default every pixel is a
  sample (``k = A``, ``T_A``): the test is then stronger (a thin arm in a large box no
  longer hides in the chi-square margin, which cost recall on crowd6). The paper's
  count stays selectable (``samples="sqrt"``): the sum over ``k = ceil(sqrt(A))``
  uniform samples is taken at its expectation ``k S_A / A``. The foreground test
  "every sample above ``T_1``" becomes "no pixel of the box at or below ``T_1``" (a
  count from a second summed-area table), which is stricter.
* **Thresholds.** The paper fits a second-order polynomial in ``k`` to ``T_k`` for
  speed; here :func:`chi2_thresholds` tabulates ``T_k`` for every ``k`` once: the
  quantile solved exactly (bisection on the regularised incomplete gamma function) up
  to 96 degrees of freedom, the Wilson-Hilferty cube-root normal approximation beyond
  (relative error below 1e-4 there for alpha <= 0.99, 4e-4 at 0.999).
* **The finest level.** At a voxel the area is its centre pixel (``k = 1``), so Eq. 6
  has no "edge" left: the voxel is foreground in a view where ``d_M > T_1`` (a binary
  mask at the voxel level) and the usual count with ``tolerance`` and ``min_views``
  decides.
* **Colour** is the mean over the views of the colour at the voxel's samples: the
  ``"naive"`` colouring of :mod:`.colouring` is exactly that with one sample per view;
  ``"visibility"`` adds the surface and line-of-sight visibility of the thesis.
"""
from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
from numba import njit

__all__ = ["chi2_threshold", "chi2_thresholds", "classify_cells_fused", "DOF_PER_SAMPLE"]

DOF_PER_SAMPLE = 3   # YUV


def _gamma_p(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function P(a, x) (series for x < a + 1,
    continued fraction otherwise; Numerical Recipes §6.2)."""
    if x <= 0:
        return 0.0
    lg = math.lgamma(a)
    if x < a + 1:
        term = total = 1.0 / a
        n = a
        for _ in range(10000):
            n += 1
            term *= x / n
            total += term
            if abs(term) < abs(total) * 1e-15:
                break
        return total * math.exp(-x + a * math.log(x) - lg)
    b = x + 1 - a
    c = 1e300
    d = 1 / b
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b += 2
        d = an * d + b
        d = 1e-300 if abs(d) < 1e-300 else d
        c = b + an / c
        c = 1e-300 if abs(c) < 1e-300 else c
        d = 1 / d
        delta = d * c
        h *= delta
        if abs(delta - 1) < 1e-15:
            break
    return 1.0 - math.exp(-x + a * math.log(x) - lg) * h


#: up to this many degrees of freedom the quantile is solved exactly
EXACT_DOF = 96


def chi2_threshold(alpha: float, k: int, dof: int = DOF_PER_SAMPLE) -> float:
    """``T_k(alpha)`` of Eq. 5: the ``alpha`` quantile of chi-square with ``dof * k``
    degrees of freedom: exact (bisection on P(nu/2, x/2)) up to :data:`EXACT_DOF`
    degrees of freedom, Wilson-Hilferty beyond (relative error below 1e-4 there for
    alpha <= 0.99)."""
    if not 0.0 < alpha < 1.0 or k < 1:
        raise ValueError("chi2_threshold needs 0 < alpha < 1 and k >= 1")
    nu = dof * k
    z = NormalDist().inv_cdf(alpha)
    c = 2.0 / (9.0 * nu)
    approx = nu * max(1e-6, 1.0 - c + z * math.sqrt(c)) ** 3
    if nu > EXACT_DOF:
        return approx
    lo, hi = 0.0, max(2.0 * approx, nu + 50.0)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if _gamma_p(nu / 2.0, mid / 2.0) < alpha:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def chi2_thresholds(alpha: float, k_max: int, dof: int = DOF_PER_SAMPLE) -> np.ndarray:
    """``T[k] = T_k(alpha)`` for ``k = 0 .. k_max`` (``T[0] = 0``), float64."""
    out = np.zeros(k_max + 1)
    for k in range(1, k_max + 1):
        out[k] = chi2_threshold(alpha, k, dof)
    return out


@njit(cache=True, nogil=True)
def classify_cells_fused(cells, boxes, cams, dsat, csat, sat_offset, sat_stride, thresholds, tolerance, min_views,
                         expand, out_edge, out_full, sqrt_samples=False):
    """Eq. 6 per view and the octree rule per cell, for ``cells`` at one box level.

    ``dsat`` (float64) and ``csat`` (int32): the summed-area tables of each camera's
    distance map and of its pixels at or below ``T_1`` (background-like), both at
    ``sat_offset[c]`` with row stride ``sat_stride[c]``. ``thresholds[k] = T_k``.
    Background in more than ``tolerance`` views (or fewer than ``min_views`` views not
    background): dropped; foreground in every view that sees the cell whole, at least
    ``min_views`` of them, and no view that sees only part of it: ``out_full``;
    otherwise edge (children to ``out_edge`` with ``expand``). Returns ``(n_edge, n_full)``.
    """
    n_edge = 0
    n_full = 0
    n_cams = cams.shape[0]
    k_max = thresholds.shape[0] - 1
    for ci in range(cells.shape[0]):
        cell = cells[ci]
        background = 0
        foreground = 0
        other = 0        # edge views, and views that see only part of the cell
        for a in range(n_cams):
            c = cams[a]
            status = boxes[cell, c, 4]
            if status == 0:
                continue
            u0 = np.int64(boxes[cell, c, 0])
            v0 = np.int64(boxes[cell, c, 1])
            u1 = np.int64(boxes[cell, c, 2]) + 1
            v1 = np.int64(boxes[cell, c, 3]) + 1
            base = sat_offset[c]
            st = sat_stride[c]
            area = (u1 - u0) * (v1 - v0)
            total = (dsat[base + v1 * st + u1] - dsat[base + v0 * st + u1]
                     - dsat[base + v1 * st + u0] + dsat[base + v0 * st + u0])
            quiet = (csat[base + v1 * st + u1] - csat[base + v0 * st + u1]
                     - csat[base + v1 * st + u0] + csat[base + v0 * st + u0])
            if sqrt_samples:     # the paper's k = sqrt(A) samples, their sum at its expectation
                k = np.int64(math.ceil(math.sqrt(area)))
                total = total * k / area
            else:                # every pixel of the box a sample
                k = area
            if k > k_max:
                k = k_max
            if status == 2 and total <= thresholds[k]:
                background += 1            # Eq. 6: background (only for a view that sees all of it)
                if background > tolerance:
                    break
            elif quiet == 0 and status == 2:
                foreground += 1            # Eq. 6: every sample above T_1
            else:
                other += 1
        if background > tolerance or foreground + other < min_views:
            continue
        if foreground >= min_views and other == 0 and background == 0:
            out_full[n_full] = cell
            n_full += 1
        elif expand:
            for o in range(8):
                out_edge[n_edge] = cell * 8 + o
                n_edge += 1
        else:
            out_edge[n_edge] = cell
            n_edge += 1
    return n_edge, n_full
