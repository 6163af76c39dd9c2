"""Scores and likelihood of a pose against the voxels (thesis §6.5.1.1-6.5.1.2).

Per body part ``Y`` of the fleshed model moved to a particle's pose ``V_y^HBM``:

* outside ``rho_Out`` (Eq. 6.13): fraction of the part's voxels outside the analysed room;
* double occupancy ``rho_DO`` (Eq. 6.14): fraction in a model voxel that another part
  also fills (inter-penetration; counted on a scratch grid at the model's spacing);
* occupancy ``rho_Occ`` (Eq. 6.15): fraction on an occupied data voxel; the likelihood
  uses ``rho_Empty = 1 - rho_Occ``;
* surface ``rho_Surf`` (Eq. 6.16): mean of ``1 - ~V^S`` over the part's surface voxels.

The likelihood is either *global* (Eqs. 6.17-6.22: scores pooled over parts weighted
by their sizes, one Gaussian with ``Sigma = diag(0.01, 0.01, 0.1, 0.1)``) or
*partitioned* (Eqs. 6.23-6.25: a product of per-part Gaussians with the covariances of
Table 6.2). Table 6.2 is garbled in the extracted text (two rows named "Forelegs", the
head with two matrices); reconstructed from its explanation: the end parts of the
limbs (forearms, shins) and the torso get halved empty/surface variances, the torso a
doubled double-occupancy variance, the other parts the base values.

``score_particles`` (numba, the hot loop) returns the four scores of every part of
every particle; the (cheap) combination into log-weights is numpy.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.pose.flesh import PART, PARTS, Flesh
from app.pose.model import DOF_AXIS, DOF_SEGMENT, SEG_OFFSET, SEG_PARENT, fk_segments
from app.pose.observation import Observation

__all__ = ["Scorer", "SIGMA2", "part_variances", "log_likelihood", "score_particles"]

#: Base variances (sigma_Out^2, sigma_DO^2, sigma_Empty^2, sigma_Surf^2), §6.5.1.2.
SIGMA2 = np.array([0.01, 0.01, 0.1, 0.1])


def part_variances() -> np.ndarray:
    """Per-part covariance diagonals ``(Q, 4)`` of the partitioned likelihood (Table 6.2,
    reconstructed, see module docstring)."""
    v = np.tile(SIGMA2, (len(PARTS), 1))
    for name in ("l_forearm", "r_forearm", "l_shin", "r_shin"):
        v[PART[name], 2:] *= 0.5
    v[PART["torso"], 1] *= 2.0
    v[PART["torso"], 2:] *= 0.5
    return v


@njit(cache=True, nogil=True)
def _cell(v, lo, inv, n):
    """Cell index of coordinate ``v`` along an axis (-1 outside), without np.floor."""
    f = (v - lo) * inv
    if f < 0.0:
        return -1
    i = int(f)
    return i if i < n else -1


@njit(cache=True, nogil=True)
def score_particles(states, height, pts, seg, part, surf, active, n_parts,
                    occ, prox, origin, vsize, room_lo, room_hi,
                    do_stamp, do_owner, do_multi, do_origin, do_size, token0, out,
                    seg_parent, seg_offset, dof_segment, dof_axis):
    """Scores ``out (P, Q, 5)`` = (outside, double, occupied, surface-miss, surface count)
    *counts* per part for every state ``(P, 27)``; only parts with ``active[q]``.

    Pass 1 moves every LUT point to the particle's pose, scores outside / occupancy /
    surface and stamps the double-occupancy grid (cell -> the first part there, and
    whether another part came too); pass 2 counts each part's points in shared cells.
    The LUT is grouped by part (one segment each), so a part's rotation and origin
    stay in registers and its counts in locals."""
    S = seg_parent.shape[0]
    R = np.empty((S, 3, 3))
    O = np.empty((S, 3))
    M = pts.shape[0]
    cells = np.empty(M, dtype=np.int64)
    X, Y, Z = occ.shape
    DX, DY, DZ = do_stamp.shape
    flat_stamp = do_stamp.reshape(-1)
    flat_owner = do_owner.reshape(-1)
    flat_multi = do_multi.reshape(-1)
    inv = 1.0 / vsize
    dinv = 1.0 / do_size
    # part ranges of the (part-sorted) LUT
    starts = np.zeros(n_parts + 1, dtype=np.int64)
    for m in range(M):
        starts[part[m] + 1] += 1
    for q in range(n_parts):
        starts[q + 1] += starts[q]
    for k in range(states.shape[0]):
        token = token0 + k
        fk_segments(states[k], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O)
        shared = False
        for q in range(n_parts):
            for c in range(5):
                out[k, q, c] = 0.0
            m0, m1 = starts[q], starts[q + 1]
            if not active[q] or m1 <= m0:
                for m in range(m0, m1):
                    cells[m] = -1
                continue
            s = seg[m0]
            r00, r01, r02 = R[s, 0, 0], R[s, 0, 1], R[s, 0, 2]
            r10, r11, r12 = R[s, 1, 0], R[s, 1, 1], R[s, 1, 2]
            r20, r21, r22 = R[s, 2, 0], R[s, 2, 1], R[s, 2, 2]
            o0, o1, o2 = O[s, 0], O[s, 1], O[s, 2]
            n_out = 0.0
            n_occ = 0.0
            n_miss = 0.0
            n_surf = 0.0
            for m in range(m0, m1):
                px, py, pz = pts[m, 0], pts[m, 1], pts[m, 2]
                x = o0 + r00 * px + r01 * py + r02 * pz
                y = o1 + r10 * px + r11 * py + r12 * pz
                z = o2 + r20 * px + r21 * py + r22 * pz
                if x < room_lo[0] or y < room_lo[1] or z < room_lo[2] or x > room_hi[0] or y > room_hi[1] \
                        or z > room_hi[2]:
                    n_out += 1.0
                i = _cell(x, origin[0], inv, X)
                j = _cell(y, origin[1], inv, Y)
                l = _cell(z, origin[2], inv, Z)
                inside = i >= 0 and j >= 0 and l >= 0
                if inside and occ[i, j, l] != 0:
                    n_occ += 1.0
                if surf[m]:
                    n_surf += 1.0
                    n_miss += 1.0 - (prox[i, j, l] if inside else 0.0)
                a = _cell(x, do_origin[0], dinv, DX)
                b = _cell(y, do_origin[1], dinv, DY)
                c = _cell(z, do_origin[2], dinv, DZ)
                if a >= 0 and b >= 0 and c >= 0:
                    f = (a * DY + b) * DZ + c
                    cells[m] = f
                    if flat_stamp[f] != token:
                        flat_stamp[f] = token
                        flat_owner[f] = q
                        flat_multi[f] = 0
                    elif flat_owner[f] != q:
                        flat_multi[f] = 1
                        shared = True
                else:
                    cells[m] = -1
            out[k, q, 0] = n_out
            out[k, q, 2] = n_occ
            out[k, q, 3] = n_miss
            out[k, q, 4] = n_surf
        if not shared:
            continue
        for m in range(M):
            f = cells[m]
            if f >= 0 and flat_multi[f] != 0:
                out[k, part[m], 1] += 1.0


def normalise(counts: np.ndarray, flesh: Flesh) -> np.ndarray:
    """Per-part scores ``(P, Q, 4)`` = (rho_Out, rho_DO, rho_Empty, rho_Surf) from counts."""
    size = flesh.part_size[None, :]
    out = np.empty(counts.shape[:2] + (4,))
    out[..., 0] = counts[..., 0] / size
    out[..., 1] = counts[..., 1] / size
    out[..., 2] = 1.0 - counts[..., 2] / size
    out[..., 3] = counts[..., 3] / np.maximum(counts[..., 4], 1.0)
    return out


def log_likelihood(scores: np.ndarray, flesh: Flesh, active: np.ndarray, mode: str = "partitioned") -> np.ndarray:
    """``log w(z, y)`` per particle from per-part scores ``(P, Q, 4)`` over the active parts:
    partitioned (Eqs. 6.23-6.25) or global (Eqs. 6.17-6.22)."""
    act = np.asarray(active, dtype=bool)
    if mode == "partitioned":
        var = part_variances()[act]
        return -0.5 * np.sum(scores[:, act, :] ** 2 / var[None], axis=(1, 2))
    if mode == "global":
        size = flesh.part_size[act]
        ssize = flesh.surface_size[act]
        g = np.empty((scores.shape[0], 4))
        g[:, :3] = np.einsum("pqc,q->pc", scores[:, act, :3], size) / size.sum()
        g[:, 3] = scores[:, act, 3] @ ssize / max(ssize.sum(), 1.0)
        return -0.5 * np.sum(g ** 2 / SIGMA2[None], axis=1)
    raise ValueError(f"likelihood must be 'partitioned' or 'global', not {mode!r}")


class Scorer:
    """Evaluates particles of one person's body against one observation at a time."""

    def __init__(self, flesh: Flesh, mode: str = "partitioned"):
        if mode not in ("partitioned", "global"):
            raise ValueError(f"likelihood must be 'partitioned' or 'global', not {mode!r}")
        self.flesh = flesh
        self.mode = mode
        self.obs: Observation | None = None
        self._token = 1
        self.evaluations = 0

    def set_observation(self, obs: Observation) -> None:
        self.obs = obs
        h = self.flesh.spacing
        span = obs.occ.shape[0] * obs.voxel_size, obs.occ.shape[1] * obs.voxel_size, obs.occ.shape[2] * obs.voxel_size
        dims = tuple(int(np.ceil(v / h)) + 1 for v in span)
        if getattr(self, "_do", None) is None or self._do[0].shape != dims:
            self._do = (np.zeros(dims, np.int64), np.zeros(dims, np.int16), np.zeros(dims, np.uint8))
            self._token = 1
        self._do_origin = obs.origin.astype(np.float64)

    def counts(self, states: np.ndarray, active=None) -> np.ndarray:
        obs, f = self.obs, self.flesh
        Q = len(PARTS)
        act = np.ones(Q, dtype=np.bool_) if active is None else np.asarray(active, dtype=np.bool_)
        states = np.ascontiguousarray(states, dtype=np.float64)
        out = np.empty((len(states), Q, 5))
        stamp, owner, multi = self._do
        score_particles(states, f.height, f.points, f.segment, f.part, f.surface, act, Q,
                        obs.occ, obs.prox, obs.origin, obs.voxel_size, obs.room_lo, obs.room_hi,
                        stamp, owner, multi, self._do_origin, f.spacing, self._token, out,
                        SEG_PARENT, SEG_OFFSET, DOF_SEGMENT, DOF_AXIS)
        self._token += len(states)
        self.evaluations += len(states)
        return out

    def scores(self, states: np.ndarray, active=None) -> np.ndarray:
        """Per-part (rho_Out, rho_DO, rho_Empty, rho_Surf) of every state ``(P, Q, 4)``."""
        return normalise(self.counts(states, active), self.flesh)

    def log_weights(self, states: np.ndarray, active=None) -> np.ndarray:
        act = np.ones(len(PARTS), dtype=bool) if active is None else np.asarray(active, dtype=bool)
        return log_likelihood(self.scores(states, act), self.flesh, act, self.mode)
