"""Coloured Gaussian blobs on the bones and their fit to the voxels (Caillette, Galata and
Howard, CVIU 2007, §6.2-6.4).

A blob is a 6-d Gaussian (position, colour) attached to one segment of the body model
(:data:`app.pose.model.SEGMENTS`): its spatial mean and covariance are given in the
segment's frame (the paper's offset along the bone and three eigenvalues: here the full
local mean, the offset across the bone included, and the variances along the segment's
three axes), its colour mean and covariance are learnt from the voxels (:func:`learn_blobs`,
§6.2, one blob a segment: the split and merge of multi-coloured clothing is not built).
Any state gives the blobs in the room by forward kinematics (:meth:`BlobModel.world`).

The voxels are summarised by fitting the blobs to them (§6.3, :func:`fit_blobs`): a
k-means with the Mahalanobis distance on position and colour, each voxel to its nearest
blob, each blob's mean and covariance re-estimated from its voxels; the start is the blobs
of one or more candidate states, and the fit whose blobs explain the voxels best (their
log-likelihood) is kept. A particle is weighed by the relative entropy of its blobs to
the fitted ones (§6.4, Eq. 9 with the blob correspondence kept:
:func:`blob_divergences`, a numba kernel, linear in the blobs), weight ``1 / D``.

Colours are in units of :data:`COLOUR_UNIT` (0..1 for 8-bit RGB), positions in metres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from app.pose.model import DOF_AXIS, DOF_SEGMENT, SEG_OFFSET, SEG_PARENT, SEGMENT, BodyModel, fk_segments

__all__ = ["BlobModel", "FittedBlobs", "learn_blobs", "fit_blobs", "blob_divergences", "COLOUR_UNIT", "BONES"]

COLOUR_UNIT = 255.0
#: Each segment's bone (local z from z0 to z1, fractions of the stature) for assigning
#: voxels when the blobs are learnt: the extents of the body model's flesh
#: (:mod:`app.pose.flesh`).
BONES = {"pelvis": (-0.070, 0.045), "torso": (0.045, 0.275), "head": (0.030, 0.155),
         "l_upper_arm": (-0.030, -0.186), "l_forearm": (-0.010, -0.218),
         "r_upper_arm": (-0.030, -0.186), "r_forearm": (-0.010, -0.218),
         "l_thigh": (-0.045, -0.240), "l_shin": (-0.010, -0.246),
         "r_thigh": (-0.045, -0.240), "r_shin": (-0.010, -0.246)}
SEG_OF_BLOB = np.array([SEGMENT[s] for s in BONES], dtype=np.int64)
MIN_VOXELS = 8          # a blob re-estimated from fewer keeps its previous shape
VAR_FLOOR = np.array([1e-4, 1e-4, 1e-4, 4e-4, 4e-4, 4e-4])   # (1 cm)^2 and (0.02 colour)^2


@dataclass
class BlobModel:
    """One person's blobs: ``local_mean`` (B, 3) and ``local_var`` (B, 3) in their
    segment's frame (metres), ``colour_mean`` (B, 3), ``colour_cov`` (B, 3, 3), ``weight``
    (B,) the share of the person's voxels each explains; ``segment`` (B,)."""

    height: float
    segment: np.ndarray
    local_mean: np.ndarray
    local_var: np.ndarray
    colour_mean: np.ndarray
    colour_cov: np.ndarray
    weight: np.ndarray

    def world(self, state) -> tuple[np.ndarray, np.ndarray]:
        """The blobs of ``state`` in the room: means (B, 6) and covariances (B, 6, 6)."""
        R, O = BodyModel(self.height).forward(state)
        B = len(self.segment)
        means, covs = np.zeros((B, 6)), np.zeros((B, 6, 6))
        for b, s in enumerate(self.segment):
            means[b, :3] = O[s] + R[s] @ self.local_mean[b]
            means[b, 3:] = self.colour_mean[b]
            covs[b, :3, :3] = R[s] @ np.diag(self.local_var[b]) @ R[s].T
            covs[b, 3:, 3:] = self.colour_cov[b]
        return means, covs


@dataclass
class FittedBlobs:
    """The blobs fitted to one frame's voxels: ``weight`` (B,), ``mean`` (B, 6), ``cov``
    (B, 6, 6) and the voxels' log-likelihood under them."""

    weight: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    loglik: float


def _points(centres, colours) -> np.ndarray:
    return np.concatenate([np.asarray(centres, float), np.asarray(colours, float) / COLOUR_UNIT], axis=1)


def learn_blobs(height: float, state, centres, colours) -> BlobModel:
    """The blobs of a person whose pose is ``state``, from their voxels (centres (N, 3),
    colours (N, 3) 8-bit RGB): each voxel to the bone it is nearest (relative to the
    flesh's thickness there), each blob the mean and variances of its voxels in its
    segment's frame and the mean and covariance of their colours (§6.2)."""
    R, O = BodyModel(height).forward(state)
    X = np.asarray(centres, float)
    C = np.asarray(colours, float) / COLOUR_UNIT
    local = np.einsum("sji,nsj->nsi", R[SEG_OF_BLOB], X[:, None, :] - O[SEG_OF_BLOB][None])   # (N, B, 3)
    z0 = np.array([min(v) for v in BONES.values()]) * height
    z1 = np.array([max(v) for v in BONES.values()]) * height
    along = np.clip(local[..., 2], z0, z1)
    dist = np.sqrt(local[..., 0] ** 2 + local[..., 1] ** 2 + (local[..., 2] - along) ** 2)
    owner = np.argmin(dist, axis=1)
    B = len(SEG_OF_BLOB)
    lm, lv = np.zeros((B, 3)), np.zeros((B, 3))
    cm, cc = np.zeros((B, 3)), np.zeros((B, 3, 3))
    w = np.zeros(B)
    for b in range(B):
        mine = owner == b
        n = int(mine.sum())
        w[b] = n
        if n >= MIN_VOXELS:
            pts = local[mine, b]
            lm[b], lv[b] = pts.mean(axis=0), pts.var(axis=0) + VAR_FLOOR[:3]
            cm[b], cc[b] = C[mine].mean(axis=0), np.cov(C[mine].T) + np.diag(VAR_FLOOR[3:])
        else:   # a part the voxels do not show: a thin blob along its bone, grey
            lm[b] = (0.0, 0.0, 0.5 * (z0[b] + z1[b]))
            lv[b] = (0.03 ** 2, 0.03 ** 2, ((z1[b] - z0[b]) / 3.5) ** 2)
            cm[b], cc[b] = 0.5, np.eye(3) * 0.05
            w[b] = max(n, 1)
    return BlobModel(float(height), SEG_OF_BLOB.copy(), lm, lv, cm, cc, w / w.sum())


@njit(cache=True, nogil=True, inline="always")
def _mahalanobis(P, n, mean, inv, b):
    """(p_n - mu_b)^T inv_b (p_n - mu_b) of 6-d points and blobs."""
    q = 0.0
    for i in range(6):
        row = 0.0
        for j in range(6):
            row += inv[b, i, j] * (P[n, j] - mean[b, j])
        q += (P[n, i] - mean[b, i]) * row
    return q


@njit(cache=True, nogil=True)
def _assign(P, mean, inv, owner):
    """Each voxel to the blob of least Mahalanobis distance (§6.3)."""
    for n in range(P.shape[0]):
        best, arg = np.inf, 0
        for b in range(mean.shape[0]):
            q = _mahalanobis(P, n, mean, inv, b)
            if q < best:
                best, arg = q, b
        owner[n] = arg


@njit(cache=True, nogil=True)
def _moments(P, owner, B, min_voxels, var_floor, mean, cov, count):
    """Each blob's mean and covariance (plus the floor) from its voxels, where it has at
    least ``min_voxels`` (the others keep theirs); ``count`` the voxels of each."""
    N = P.shape[0]
    s1 = np.zeros((B, 6))
    s2 = np.zeros((B, 6, 6))
    count[:] = 0
    for n in range(N):
        b = owner[n]
        count[b] += 1
        for i in range(6):
            s1[b, i] += P[n, i]
            for j in range(6):
                s2[b, i, j] += P[n, i] * P[n, j]
    for b in range(B):
        c = count[b]
        if c < min_voxels:
            continue
        for i in range(6):
            mean[b, i] = s1[b, i] / c
        for i in range(6):
            for j in range(6):   # np.cov's unbiased estimate
                cov[b, i, j] = (s2[b, i, j] - c * mean[b, i] * mean[b, j]) / (c - 1)
            cov[b, i, i] += var_floor[i]


@njit(cache=True, nogil=True)
def _mixture_loglik(P, mean, inv, log_norm):
    """The voxels' log-likelihood under the mixture (``log_norm``: each blob's log weight
    less half its log-determinant and 3 ln 2 pi)."""
    N, B = P.shape[0], mean.shape[0]
    L = np.empty(B)
    total = 0.0
    for n in range(N):
        top = -np.inf
        for b in range(B):
            L[b] = log_norm[b] - 0.5 * _mahalanobis(P, n, mean, inv, b)
            if L[b] > top:
                top = L[b]
        acc = 0.0
        for b in range(B):
            acc += math.exp(L[b] - top)
        total += top + math.log(acc)
    return total


def fit_blobs(model: BlobModel, starts, centres, colours, iterations: int = 6) -> FittedBlobs:
    """The blobs fitted to the voxels by the Mahalanobis k-means of §6.3 from the blobs of
    each state of ``starts``; the fit of the highest log-likelihood of the voxels."""
    P = np.ascontiguousarray(_points(centres, colours))
    B = len(model.segment)
    owner = np.zeros(len(P), np.int64)
    count = np.zeros(B, np.int64)
    best = None
    for state in np.atleast_2d(starts):
        mean, cov = model.world(state)
        weight = model.weight.copy()
        for _ in range(iterations):
            _assign(P, mean, np.linalg.inv(cov), owner)
            _moments(P, owner, B, MIN_VOXELS, VAR_FLOOR, mean, cov, count)
            weight = np.maximum(count, 1) / np.maximum(count, 1).sum()
        sign, logdet = np.linalg.slogdet(cov)
        ll = _mixture_loglik(P, mean, np.linalg.inv(cov),
                             np.log(np.maximum(weight, 1e-12)) - 0.5 * logdet - 3.0 * math.log(2 * math.pi))
        if best is None or ll > best.loglik:
            best = FittedBlobs(weight, mean.copy(), cov.copy(), float(ll))
    return best


@njit(cache=True, nogil=True)
def _divergences(states, height, seg_parent, seg_offset, dof_segment, dof_axis, blob_seg, local_mean, local_var,
                 colour_mean, colour_cov, alpha, g_mean, g_inv, g_logdet, beta, out):
    """Eq. 9 for each state: sum_b alpha_b (D_KL(f_b || g_b) + ln(alpha_b / beta_b))."""
    P = states.shape[0]
    B = blob_seg.shape[0]
    R = np.empty((seg_parent.shape[0], 3, 3))
    O = np.empty((seg_parent.shape[0], 3))
    logdet_f = np.empty(B)
    trace_c = np.empty(B)
    for b in range(B):
        logdet_f[b] = math.log(local_var[b, 0] * local_var[b, 1] * local_var[b, 2]) + \
            math.log(np.linalg.det(colour_cov[b]))
        t = 0.0
        for i in range(3):
            for j in range(3):
                t += g_inv[b, 3 + i, 3 + j] * colour_cov[b, j, i]
        trace_c[b] = t
    mu = np.empty(6)
    for p in range(P):
        fk_segments(states[p], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O)
        total = 0.0
        for b in range(B):
            s = blob_seg[b]
            for i in range(3):
                mu[i] = O[s, i] + R[s, i, 0] * local_mean[b, 0] + R[s, i, 1] * local_mean[b, 1] + \
                    R[s, i, 2] * local_mean[b, 2]
                mu[3 + i] = colour_mean[b, i]
            # tr(G^-1 S_f): the spatial block is sum_k var_k r_k^T G^-1 r_k (r_k the segment's axes)
            tr = trace_c[b]
            for k in range(3):
                q = 0.0
                for i in range(3):
                    for j in range(3):
                        q += R[s, i, k] * g_inv[b, i, j] * R[s, j, k]
                tr += local_var[b, k] * q
            maha = 0.0
            for i in range(6):
                di = g_mean[b, i] - mu[i]
                for j in range(6):
                    maha += di * g_inv[b, i, j] * (g_mean[b, j] - mu[j])
            kl = 0.5 * (g_logdet[b] - logdet_f[b] - 6.0 + tr + maha)
            total += alpha[b] * (kl + math.log(alpha[b] / beta[b]))
        out[p] = total


def blob_divergences(model: BlobModel, fitted: FittedBlobs, states: np.ndarray) -> np.ndarray:
    """D_KL(F || G) (Eq. 9) of each state's blobs F against the fitted blobs G, (P,)."""
    states = np.ascontiguousarray(np.atleast_2d(states), dtype=np.float64)
    out = np.empty(len(states))
    inv = np.linalg.inv(fitted.cov)
    logdet = np.linalg.slogdet(fitted.cov)[1]
    _divergences(states, model.height, SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS, model.segment,
                 model.local_mean, model.local_var, model.colour_mean, model.colour_cov,
                 np.maximum(model.weight, 1e-6), fitted.mean, inv, logdet, np.maximum(fitted.weight, 1e-6), out)
    return out


@njit(cache=True, nogil=True)
def _voxel_logliks(states, height, seg_parent, seg_offset, dof_segment, dof_axis, blob_seg, local_mean, inv_var,
                   spatial_norm, colour_term, points, floor, out):
    """Mean over the voxels of log(max(sum_b w_b N(p | blob b of the state), floor)) for each state."""
    P = states.shape[0]
    B = blob_seg.shape[0]
    M = points.shape[0]
    R = np.empty((seg_parent.shape[0], 3, 3))
    O = np.empty((seg_parent.shape[0], 3))
    centre = np.empty((B, 3))
    axes = np.empty((B, 3, 3))
    lfloor = math.log(floor)
    ls = np.empty(B)
    for p in range(P):
        fk_segments(states[p], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O)
        for b in range(B):
            s = blob_seg[b]
            for i in range(3):
                centre[b, i] = O[s, i] + R[s, i, 0] * local_mean[b, 0] + R[s, i, 1] * local_mean[b, 1] + \
                    R[s, i, 2] * local_mean[b, 2]
                for j in range(3):
                    axes[b, i, j] = R[s, i, j]
        total = 0.0
        for m in range(M):
            best = lfloor
            acc = 0.0
            for b in range(B):
                dx = points[m, 0] - centre[b, 0]
                dy = points[m, 1] - centre[b, 1]
                dz = points[m, 2] - centre[b, 2]
                q = 0.0
                for k in range(3):
                    u = axes[b, 0, k] * dx + axes[b, 1, k] * dy + axes[b, 2, k] * dz
                    q += u * u * inv_var[b, k]
                ls[b] = colour_term[m, b] + spatial_norm[b] - 0.5 * q
                if ls[b] > best:
                    best = ls[b]
            acc = math.exp(lfloor - best)
            for b in range(B):
                ls[b] = math.exp(ls[b] - best)
                acc += ls[b]
            total += best + math.log(acc)
        out[p] = total / max(M, 1)


def voxel_logliks(model: BlobModel, states: np.ndarray, centres, colours, floor: float = 1e-3) -> np.ndarray:
    """The voxels' mean log-likelihood under each state's blobs (P,): the mixture of the
    blobs posed by the state (weights the shares the blobs were learnt with), each voxel's
    likelihood floored at ``floor`` (a voxel no blob explains, the hull's excess, costs a
    bounded amount)."""
    states = np.ascontiguousarray(np.atleast_2d(states), dtype=np.float64)
    P = _points(centres, colours)
    out = np.empty(len(states))
    w = np.maximum(model.weight, 1e-6)
    cinv = np.linalg.inv(model.colour_cov)
    dc = P[:, None, 3:] - model.colour_mean[None]
    colour_term = (-0.5 * np.einsum("nbi,bij,nbj->nb", dc, cinv, dc) - 0.5 * np.linalg.slogdet(model.colour_cov)[1]
                   + np.log(w))
    spatial_norm = -0.5 * np.log(np.prod(model.local_var, axis=1)) - 3.0 * math.log(2 * math.pi)
    _voxel_logliks(states, model.height, SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS, model.segment,
                   model.local_mean, 1.0 / model.local_var, spatial_norm, np.ascontiguousarray(colour_term),
                   np.ascontiguousarray(P[:, :3]), float(floor), out)
    return out
