"""The annealed filter's estimate polished on the markers it found (beyond the thesis;
issue 28).

Three layers of 700 particles (the thesis's setting, §6.6.1) place a 27-DoF body to a few
centimetres: the particles are spread over the whole body, and no one of them lies on
every marker at once. What they leave is a local fit: each landmark of the estimate has,
in each view, the detection nearest to its projection within ``rho`` (Eq. 6.5, the
likelihood's own pick, exclusive where the scorer's picks are), and a few Gauss-Newton
steps on the reprojection error of those pairs, with a robust (soft L1) weight per pair
so that a wrong pick pulls little, settle the body on them. Then the landmarks pick
their detections again from where the steps left the body, and the next round of steps
follows (``rounds``: a landmark a centimetre or two nearer its marker may find it within
``rho`` where the filter's estimate did not). The Jacobian is taken by finite
differences of the whole state at once (:func:`app.pose.model.joints_subset` of 28
states), so a step costs about one particle layer's 28 evaluations, not a layer's 700.
The polished state is kept only where the filter's own likelihood (Eq. 6.10 with our
terms and priors) rates it at least as well as the estimate.

Pure: states, detections and cameras in, a state out; no bus.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.markers.likelihood import exclusive_picks, nearest_detection, project_ideal
from app.pose.model import (AVERAGE, DOF_AXIS, DOF_SEGMENT, JOINT_SEG, LIMITS_HI, LIMITS_LO, SEG_PARENT,
                            fk_probed, joints_subset, segments_needed)

__all__ = ["polish"]

EPS = 1e-4              # finite-difference step (m for the root, rad for the angles)
DAMPING = 1e-3          # Levenberg's damping, times the normal matrix's mean diagonal
_ALL = np.arange(15, dtype=np.int64)
_NEED = segments_needed(_ALL)


def _pairs(X, scorer):
    """Per view, the landmarks with a detection within ``rho`` of their projection and
    that detection, flat: ``views (k,), landmarks (k,), detections (k, 2)`` view by view;
    with the scorer's exclusive picks, a detection is the pick of one landmark
    (:func:`exclusive_picks`)."""
    return _picks(np.ascontiguousarray(X, dtype=np.float64), scorer.K, scorer.R, scorer.t, scorer.det, scorer.start,
                  float(scorer.rho), bool(scorer.exclusive))


@njit(cache=True, nogil=True)
def _picks(X, K, R, t, det, start, rho, exclusive):
    """:func:`_pairs`' kernel: each landmark's nearest detection per view (the first at a
    tie), kept within ``rho``."""
    M = X.shape[0]
    C = K.shape[0]
    pick = np.full((M, C), -1, np.int64)
    pick_d2 = np.zeros((M, C))
    for n in range(C):
        if start[n] == start[n + 1]:
            continue
        for m in range(M):
            u, v = project_ideal(K[n], R[n], t[n], X[m, 0], X[m, 1], X[m, 2], 1e-6)
            best, bq = nearest_detection(det, start[n], start[n + 1], u, v)
            if best < rho:
                pick[m, n] = bq
            pick_d2[m, n] = best * best
    if exclusive:
        exclusive_picks(pick, pick_d2)
    k = 0
    for n in range(C):
        for m in range(M):
            if pick[m, n] >= 0:
                k += 1
    views = np.empty(k, np.int64)
    landmarks = np.empty(k, np.int64)
    dets = np.empty((k, 2))
    k = 0
    for n in range(C):
        for m in range(M):
            if pick[m, n] >= 0:
                views[k] = n
                landmarks[k] = m
                dets[k] = det[pick[m, n]]
                k += 1
    return views, landmarks, dets


def polish(state: np.ndarray, scorer, iterations: int = 5, scale: float = 3.0, min_pairs: int = 12,
           rounds: int = 1) -> np.ndarray:
    """``state`` (27,) after ``rounds`` of up to ``iterations`` robust Gauss-Newton steps
    each on the reprojection error of its landmarks' detections (soft L1 of ``scale`` px;
    each round picks the detections again from where the last one left the body), or
    ``state`` itself where that is not rated better by ``scorer`` (a
    :class:`~app.markers.likelihood.MarkerScorer` with this frame's detections)."""
    state = np.asarray(state, dtype=np.float64)
    if iterations <= 0:
        return state
    height = scorer.height
    lo, hi = LIMITS_LO + 1e-9, LIMITS_HI - 1e-9
    x = state.copy()
    for r in range(max(int(rounds), 1)):
        views, landmarks, dets = _pairs(joints_subset(x[None], height, _ALL, _NEED)[0], scorer)
        if len(views) < min_pairs:
            if r == 0:
                return state
            break
        x = _steps(x, views, landmarks, dets, scorer.K, scorer.R, scorer.t, float(height), SEG_PARENT,
                   AVERAGE.seg_offset, DOF_SEGMENT, DOF_AXIS, JOINT_SEG, AVERAGE.joint_local, _ALL, _NEED,
                   int(iterations), float(scale), lo, hi)
    before, after = scorer.log_weights(np.stack([state, x]))
    return x if after >= before else state


@njit(cache=True, nogil=True)
def _steps(x, views, landmarks, dets, K, R, t, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg,
           joint_local, joints, need, iterations, scale, lo, hi):
    """``x`` after up to ``iterations`` damped Gauss-Newton steps on the pairs
    (``views``, ``landmarks``, ``dets``): the Jacobian of the reprojection residuals by
    forward differences of :data:`EPS` over the whole state, each pair weighted by the
    soft L1 of ``scale`` px, Levenberg's damping, the step clipped to ``lo``, ``hi``."""
    D = x.shape[0]
    k = views.shape[0]
    x = x.copy()
    every = np.arange(D)                 # the Jacobian over the whole state
    probes = np.empty((D + 1, D))
    X = np.empty((D + 1, joints.shape[0], 3))
    res = np.empty((D + 1, 2 * k))
    J = np.empty((D, 2 * k))
    w = np.empty(2 * k)
    for _ in range(iterations):
        fk_probed(x, every, EPS, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg, joint_local,
                  joints, need, probes, X)
        finite = True
        for p in range(D + 1):
            for i in range(k):
                n, m = views[i], landmarks[i]
                u, v = project_ideal(K[n], R[n], t[n], X[p, m, 0], X[p, m, 1], X[p, m, 2], 1e-6)
                res[p, 2 * i] = u - dets[i, 0]
                res[p, 2 * i + 1] = v - dets[i, 1]
                finite = finite and np.isfinite(u) and np.isfinite(v)
        if not finite:
            break
        for i in range(k):
            e = np.hypot(res[0, 2 * i], res[0, 2 * i + 1])
            w[2 * i] = w[2 * i + 1] = 1.0 / np.sqrt(1.0 + (e / scale) ** 2)     # soft L1, per pair
        for d in range(D):
            for c in range(2 * k):
                J[d, c] = (res[d + 1, c] - res[0, c]) / EPS
        Jw = J * w
        A = Jw @ J.T
        diag = 0.0
        for d in range(D):
            diag += A[d, d]
        for d in range(D):
            A[d, d] += DAMPING * (diag / D) + 1e-12
        step = np.linalg.solve(A, -(Jw @ res[0]))
        biggest = 0.0
        for d in range(D):
            x[d] = min(max(x[d] + step[d], lo[d]), hi[d])
            biggest = max(biggest, abs(step[d]))
        if biggest < 1e-4:
            break
    return x
