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

from app.markers.likelihood import exclusive_picks
from app.pose.model import LIMITS_HI, LIMITS_LO, N_DOF, joints_subset, segments_needed

__all__ = ["polish"]

EPS = 1e-4              # finite-difference step (m for the root, rad for the angles)
DAMPING = 1e-3          # Levenberg's damping, times the normal matrix's mean diagonal
_ALL = np.arange(15, dtype=np.int64)
_NEED = segments_needed(_ALL)


def _pairs(X, scorer):
    """Per view, the landmarks with a detection within ``rho`` of their projection and
    that detection: ``[(view, landmarks (k,), detections (k, 2))]``; with the scorer's
    exclusive picks, a detection is the pick of one landmark (:func:`exclusive_picks`)."""
    C = len(scorer.cameras)
    pick = np.full((len(X), C), -1, np.int64)
    pick_d2 = np.zeros((len(X), C))
    for n in range(C):
        det = scorer.det[scorer.start[n]:scorer.start[n + 1]]
        if not len(det):
            continue
        uv = _project(X[None], scorer, n)[0]
        d = np.linalg.norm(uv[:, None, :] - det[None], axis=2)
        d[~np.isfinite(d)] = np.inf
        q = np.argmin(d, axis=1)
        dq = d[np.arange(len(X)), q]
        ok = dq < scorer.rho
        pick[ok, n] = scorer.start[n] + q[ok]
        pick_d2[:, n] = dq * dq
    if scorer.exclusive:
        exclusive_picks(pick, pick_d2)
    out = []
    for n in range(C):
        m = np.flatnonzero(pick[:, n] >= 0)
        if len(m):
            out.append((n, m, scorer.det[pick[m, n]]))
    return out


def _project(X, scorer, n):
    """Ideal pixels (P, M, 2) of points (P, M, 3) in view ``n`` (NaN behind it)."""
    pc = X @ scorer.R[n].T + scorer.t[n]
    z = np.where(pc[..., 2] > 1e-6, pc[..., 2], np.nan)
    K = scorer.K[n]
    xn, yn = pc[..., 0] / z, pc[..., 1] / z
    return np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], axis=-1)


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
    probes = np.empty((N_DOF + 1, N_DOF))
    for r in range(max(int(rounds), 1)):
        pairs = _pairs(joints_subset(x[None], height, _ALL, _NEED)[0], scorer)
        if sum(len(m) for _, m, _ in pairs) < min_pairs:
            if r == 0:
                return state
            break
        x = _steps(x, pairs, scorer, height, iterations, scale, probes, lo, hi)
    before, after = scorer.log_weights(np.stack([state, x]))
    return x if after >= before else state


def _steps(x, pairs, scorer, height, iterations, scale, probes, lo, hi):
    """``x`` after up to ``iterations`` damped Gauss-Newton steps on ``pairs``."""
    for _ in range(iterations):
        probes[:] = x
        probes[1:] += EPS * np.eye(N_DOF)
        X = joints_subset(probes, height, _ALL, _NEED)                           # (28, 15, 3)
        res = np.concatenate([(_project(X[:, m], scorer, n) - det[None]).reshape(N_DOF + 1, -1)
                              for n, m, det in pairs], axis=1)                     # (28, 2 k)
        if not np.all(np.isfinite(res)):
            break
        r0 = res[0]
        J = (res[1:] - r0) / EPS                                                   # (27, 2 k)
        e = np.hypot(r0[0::2], r0[1::2])
        w = np.repeat(1.0 / np.sqrt(1.0 + (e / scale) ** 2), 2)                    # soft L1, per pair
        A = (J * w) @ J.T
        A[np.diag_indices_from(A)] += DAMPING * float(np.mean(np.diag(A))) + 1e-12
        step = np.linalg.solve(A, -(J * w) @ r0)
        x = np.clip(x + step, lo, hi)
        if float(np.abs(step).max()) < 1e-4:
            break
    return x
