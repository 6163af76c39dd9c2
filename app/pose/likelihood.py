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

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from app.pose.flesh import PART, PARTS, Flesh
from app.pose.model import DOF_AXIS, DOF_SEGMENT, SEG_PARENT, fk_segments
from app.pose.observation import Observation

__all__ = ["Scorer", "SIGMA2", "part_variances", "log_likelihood", "score_particles", "Lut", "kernel_lut"]

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


_PART_VARIANCES = part_variances()   # the fast path of log_likelihood reads it


#: The surface sum of Eq. 6.16 adds ``1 - prox`` in fixed point (integers of 2^-40):
#: exact, hence the same in any order, for the float32 proximities of
#: :mod:`app.pose.observation` (>= 2^-17 or 0: its Gaussian is cut at 2 sigma), and
#: integer sums do not wait on each other as a chain of float additions does.
_FIXED = float(2 ** 40)


@njit(cache=True, nogil=True, inline="always")
def _place(lx, ly, lz, m0, m1, R, O, s, origin, inv, dims, dinv, do_dims, room_lo, room_hi, sentinel, box,
           room_test, do_test, cell, do_cell):
    """Moves the LUT points ``m0:m1`` of one part (segment ``s``) to the particle's pose:
    the data cell of each (``sentinel``, an empty cell, outside the box) into ``cell``,
    and if ``do_test`` its double-occupancy cell (-1 outside ``box``, the cells where
    another part may be) into ``do_cell``; returns how many lie outside the room (0
    without ``room_test``). Branch-free over structure-of-arrays coordinates, so LLVM
    vectorises it (the loop runs on unsigned indices: no negative-index wraparound,
    which would stop that; the two tests are loop-invariant, so it is unswitched)."""
    X, Y, Z = dims[0], dims[1], dims[2]
    DY, DZ = do_dims[1], do_dims[2]
    r00, r01, r02 = R[s, 0, 0], R[s, 0, 1], R[s, 0, 2]
    r10, r11, r12 = R[s, 1, 0], R[s, 1, 1], R[s, 1, 2]
    r20, r21, r22 = R[s, 2, 0], R[s, 2, 1], R[s, 2, 2]
    o0, o1, o2 = O[s, 0], O[s, 1], O[s, 2]
    ox, oy, oz = origin[0], origin[1], origin[2]
    rx0, ry0, rz0 = room_lo[0], room_lo[1], room_lo[2]
    rx1, ry1, rz1 = room_hi[0], room_hi[1], room_hi[2]
    a0, a1, b0, b1, c0, c1 = box[0], box[1], box[2], box[3], box[4], box[5]
    n_out = 0
    for m in range(np.uint64(m0), np.uint64(m1)):
        x = o0 + r00 * lx[m] + r01 * ly[m] + r02 * lz[m]
        y = o1 + r10 * lx[m] + r11 * ly[m] + r12 * lz[m]
        z = o2 + r20 * lx[m] + r21 * ly[m] + r22 * lz[m]
        if room_test:
            n_out += np.int64((x < rx0) | (y < ry0) | (z < rz0) | (x > rx1) | (y > ry1) | (z > rz1))
        tx, ty, tz = x - ox, y - oy, z - oz
        fi, fj, fl = tx * inv, ty * inv, tz * inv
        inside = (fi >= 0.0) & (fj >= 0.0) & (fl >= 0.0) & (fi < X) & (fj < Y) & (fl < Z)
        # (an index computed from a coordinate outside is discarded by the select)
        c = (np.int64(fi) * Y + np.int64(fj)) * Z + np.int64(fl)
        cell[m] = c if inside else sentinel
        if do_test:
            fa, fb, fc = tx * dinv, ty * dinv, tz * dinv
            near = (fa >= a0) & (fb >= b0) & (fc >= c0) & (fa < a1) & (fb < b1) & (fc < c1)
            d = (np.int64(fa) * DY + np.int64(fb)) * DZ + np.int64(fc)
            do_cell[m] = d if near else -1
    return n_out


@njit(cache=True, nogil=True)
def _part_boxes(on, n_on, R, O, part_segment, part_centre, part_half, origin, dinv, do_dims, room_lo, room_hi,
                cbox, box, in_room):
    """Per active part: whether all its points are inside the room (``in_room``, no
    per-point test then), and the box (double-occupancy cells, ``[lo, hi)`` per axis)
    outside which none of its points can share a cell with another part: the bounding
    box of its intersections with the other parts' boxes (each part's box from its
    LUT's bounds moved to the pose, widened by 1e-6 m against rounding). Empty box:
    lo >= hi."""
    for t in range(n_on):
        q = on[t]
        s = part_segment[q]
        inside = True
        for i in range(3):
            cen = O[s, i] + R[s, i, 0] * part_centre[q, 0] + R[s, i, 1] * part_centre[q, 1] \
                + R[s, i, 2] * part_centre[q, 2]
            half = abs(R[s, i, 0]) * part_half[q, 0] + abs(R[s, i, 1]) * part_half[q, 1] \
                + abs(R[s, i, 2]) * part_half[q, 2] + 1e-6
            inside = inside and cen - half > room_lo[i] and cen + half < room_hi[i]
            cbox[q, 2 * i] = max(math.floor((cen - half - origin[i]) * dinv), 0.0)
            cbox[q, 2 * i + 1] = min(math.floor((cen + half - origin[i]) * dinv) + 1.0, float(do_dims[i]))
            box[q, 2 * i] = 1e30
            box[q, 2 * i + 1] = -1e30
        in_room[q] = inside
    for t in range(n_on):
        q = on[t]
        for u in range(t + 1, n_on):
            r = on[u]
            lo0, hi0 = max(cbox[q, 0], cbox[r, 0]), min(cbox[q, 1], cbox[r, 1])
            lo1, hi1 = max(cbox[q, 2], cbox[r, 2]), min(cbox[q, 3], cbox[r, 3])
            lo2, hi2 = max(cbox[q, 4], cbox[r, 4]), min(cbox[q, 5], cbox[r, 5])
            if lo0 >= hi0 or lo1 >= hi1 or lo2 >= hi2:
                continue
            for p in (q, r):
                box[p, 0], box[p, 1] = min(box[p, 0], lo0), max(box[p, 1], hi0)
                box[p, 2], box[p, 3] = min(box[p, 2], lo1), max(box[p, 3], hi1)
                box[p, 4], box[p, 5] = min(box[p, 4], lo2), max(box[p, 5], hi2)


@njit(cache=True, nogil=True)
def score_particles(states, height, lx, ly, lz, part_start, part_segment, part_surface, part_centre, part_half,
                    active, need, grid, sentinel, dims, origin, vsize, room_lo, room_hi,
                    do_stamp, do_dims, do_size, token0, out, seg_parent, seg_offset, dof_segment, dof_axis):
    """Scores ``out (P, Q, 5)`` = (outside, double, occupied, surface-miss, surface count)
    *counts* per part for every state ``(P, 27)``; only parts with ``active[q]``.

    The LUT (:class:`Lut`) is in structure-of-arrays form ``lx, ly, lz``, grouped by
    part (``part_start``), each part's surface points first. ``grid`` (float32) is the
    observation flattened into one array: the proximity ``~V^S`` of each cell with its
    sign bit set where the cell is occupied (``-0.0`` for an occupied cell of
    proximity 0), so that one gather gives both (exact: the magnitude is the
    proximity, untouched), with ``sentinel`` the index of a cell empty in both (``+0.0``:
    where points outside the box look).
    Per particle: forward kinematics of the ``need``-ed segments only, the parts'
    :func:`_part_boxes`; per active part: every point placed (:func:`_place`,
    vectorised), occupancy and surface gathered, and the double-occupancy grid
    ``do_stamp`` stamped by the points in the part's box, one int64 per cell packing
    ``token * 2048 + 128 * part + 64 * shared + points`` (a cell stamped by an earlier
    particle has a smaller token, so the grid is never cleared; ``points`` counts the
    first part's points in the cell: a part's points lie on a lattice of the cell's
    spacing, so a cell holds at most 8 of them, well under the field's 63): a point
    counts for Eq. 6.14 when it lands in a shared cell, and the first part's points of
    a cell when another part makes it shared, so every point in a shared cell is
    counted once, without a second pass over the parts' points."""
    S = seg_parent.shape[0]
    Q = part_start.shape[0] - 1
    R = np.zeros((S, 3, 3))
    O = np.zeros((S, 3))
    M = lx.shape[0]
    cell = np.empty(M, dtype=np.int64)
    do_cell = np.empty(M, dtype=np.int64)
    inv = 1.0 / vsize
    dinv = 1.0 / do_size
    n_do = np.zeros(Q, dtype=np.int64)
    cbox = np.empty((Q, 6))
    box = np.empty((Q, 6))
    in_room = np.zeros(Q, dtype=np.bool_)
    on = np.empty(Q, dtype=np.int64)
    n_on = 0
    for q in range(Q):
        if active[q] and part_start[q + 1] > part_start[q]:
            on[n_on] = q
            n_on += 1
    for k in range(states.shape[0]):
        token = (token0 + k) * 2048
        fk_segments(states[k], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O, need)
        _part_boxes(on, n_on, R, O, part_segment, part_centre, part_half, origin, dinv, do_dims, room_lo, room_hi,
                    cbox, box, in_room)
        for q in range(Q):
            n_do[q] = 0
            for c in range(5):
                out[k, q, c] = 0.0
        for t in range(n_on):
            q = on[t]
            m0, m1 = part_start[q], part_start[q + 1]
            ms = m0 + part_surface[q]
            stamp = box[q, 0] < box[q, 1]
            n_out = _place(lx, ly, lz, m0, m1, R, O, part_segment[q], origin, inv, dims, dinv, do_dims,
                           room_lo, room_hi, sentinel, box[q], not in_room[q], stamp, cell, do_cell)
            n_occ = 0
            n_miss = 0
            for m in range(np.uint64(m0), np.uint64(ms)):
                v = grid[cell[m]]
                n_occ += np.int64(math.copysign(1.0, v) < 0.0)
                n_miss += np.int64((1.0 - abs(v)) * _FIXED)
            for m in range(np.uint64(ms), np.uint64(m1)):
                n_occ += np.int64(math.copysign(1.0, grid[cell[m]]) < 0.0)
            out[k, q, 0] = n_out
            out[k, q, 2] = n_occ
            out[k, q, 3] = n_miss / _FIXED
            out[k, q, 4] = part_surface[q]
            if not stamp:
                continue
            mine = token + q * 128
            for m in range(np.uint64(m0), np.uint64(m1)):
                f = do_cell[m]
                if f >= 0:
                    code = do_stamp[f]
                    if code < token:                  # first in this particle: the part's, one point
                        do_stamp[f] = mine + 1
                    elif code & 64:                   # already shared: this point counts
                        n_do[q] += 1
                    elif (code & 1984) == mine & 1984:   # the part's own cell: one more point
                        do_stamp[f] = code + 1
                    else:                             # shared from now: the owner's points and this one
                        do_stamp[f] = code | 64
                        n_do[(code >> 7) & 15] += code & 63
                        n_do[q] += 1
        for q in range(Q):
            out[k, q, 1] = n_do[q]


@njit(cache=True, nogil=True)
def _normalise(counts, size, out):
    for k in range(counts.shape[0]):
        for q in range(counts.shape[1]):
            out[k, q, 0] = counts[k, q, 0] / size[q]
            out[k, q, 1] = counts[k, q, 1] / size[q]
            out[k, q, 2] = 1.0 - counts[k, q, 2] / size[q]
            out[k, q, 3] = counts[k, q, 3] / max(counts[k, q, 4], 1.0)


def normalise(counts: np.ndarray, flesh: Flesh) -> np.ndarray:
    """Per-part scores ``(P, Q, 4)`` = (rho_Out, rho_DO, rho_Empty, rho_Surf) from counts."""
    out = np.empty(counts.shape[:2] + (4,))
    _normalise(np.ascontiguousarray(counts, dtype=np.float64), np.asarray(flesh.part_size, np.float64), out)
    return out


@njit(cache=True, nogil=True)
def _partitioned(scores, act, var):
    """Eq. 6.25 summed as numpy sums ``(s**2 / var)`` over the last axis, then the parts."""
    out = np.empty(scores.shape[0])
    for k in range(scores.shape[0]):
        acc = 0.0
        for q in range(scores.shape[1]):
            if act[q]:
                t = scores[k, q, 0] * scores[k, q, 0] / var[q, 0]
                for c in range(1, 4):
                    t += scores[k, q, c] * scores[k, q, c] / var[q, c]
                acc += t
        out[k] = -0.5 * acc
    return out



def log_likelihood(scores: np.ndarray, flesh: Flesh, active: np.ndarray, mode: str = "partitioned") -> np.ndarray:
    """``log w(z, y)`` per particle from per-part scores ``(P, Q, 4)`` over the active parts:
    partitioned (Eqs. 6.23-6.25) or global (Eqs. 6.17-6.22)."""
    act = np.asarray(active, dtype=bool)
    if mode == "partitioned":
        if scores.shape[1:] == _PART_VARIANCES.shape and act.shape == (len(PARTS),):
            return _partitioned(np.ascontiguousarray(scores, dtype=np.float64), act, _PART_VARIANCES)
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


@dataclass
class Lut:
    """The flesh's LUT in the kernel's layout: coordinates as three contiguous arrays,
    grouped by part with each part's surface points first (both stable, so the order
    within a group is the flesh's), and per part its first point, segment, surface
    count and the centre and half extent of its points (segment-local)."""

    lx: np.ndarray
    ly: np.ndarray
    lz: np.ndarray
    part_start: np.ndarray    # (Q + 1,)
    part_segment: np.ndarray  # (Q,)
    part_surface: np.ndarray  # (Q,)
    part_centre: np.ndarray   # (Q, 3)
    part_half: np.ndarray     # (Q, 3)
    part_needs: np.ndarray    # (Q, S) bool: the segments whose pose the part needs
    seg_offset: np.ndarray    # (S, 3) the person's segment offsets (app.pose.model.Proportions)


def kernel_lut(flesh: Flesh) -> Lut:
    Q = len(PARTS)
    order = np.lexsort((~flesh.surface, flesh.part))
    pts = flesh.points[order]
    part = flesh.part[order]
    start = np.zeros(Q + 1, dtype=np.int64)
    start[1:] = np.cumsum(np.bincount(part, minlength=Q))
    segment = np.zeros(Q, dtype=np.int64)
    centre, half = np.zeros((Q, 3)), np.zeros((Q, 3))
    needs = np.zeros((Q, len(SEG_PARENT)), dtype=np.bool_)
    for q in range(Q):
        if start[q + 1] == start[q]:
            continue
        segs = np.unique(flesh.segment[order][start[q]:start[q + 1]])
        if len(segs) != 1:
            raise ValueError(f"body part {PARTS[q]} spans {len(segs)} segments; the kernel needs one")
        segment[q] = segs[0]
        lo, hi = pts[start[q]:start[q + 1]].min(axis=0), pts[start[q]:start[q + 1]].max(axis=0)
        centre[q], half[q] = (lo + hi) / 2, (hi - lo) / 2
        s = segment[q]
        while s >= 0:
            needs[q, s] = True
            s = SEG_PARENT[s]
    surface = np.bincount(part[flesh.surface[order]], minlength=Q).astype(np.int64)
    return Lut(*(np.ascontiguousarray(pts[:, i]) for i in range(3)), start, segment, surface, centre, half, needs,
               flesh.proportions.seg_offset)


class Scorer:
    """Evaluates particles of one person's body against one observation at a time."""

    def __init__(self, flesh: Flesh, mode: str = "partitioned"):
        if mode not in ("partitioned", "global"):
            raise ValueError(f"likelihood must be 'partitioned' or 'global', not {mode!r}")
        if len(PARTS) > 16:
            raise ValueError("the double-occupancy stamp packs the part in 4 bits")
        self.flesh = flesh
        self.mode = mode
        self.obs: Observation | None = None
        self.lut = kernel_lut(flesh)
        self._token = 1
        self._stamp = None
        self.evaluations = 0

    def set_observation(self, obs: Observation) -> None:
        self.obs = obs
        h = self.flesh.spacing
        span = obs.occ.shape[0] * obs.voxel_size, obs.occ.shape[1] * obs.voxel_size, obs.occ.shape[2] * obs.voxel_size
        dims = tuple(int(np.ceil(v / h)) + 1 for v in span)
        # the stamps of earlier particles (smaller tokens) never count, whatever the grid's
        # shape then: the grid is reused as long as it is large enough, never cleared
        need = int(np.prod(dims))
        if self._stamp is None or len(self._stamp) < need:
            self._stamp = np.zeros(need + need // 4, np.int64)
        self._do_dims = np.array(dims, dtype=np.int64)
        self._origin = np.asarray(obs.origin, dtype=np.float64)
        self._dims = np.array(obs.occ.shape, dtype=np.int64)
        occ, prox = np.ravel(obs.occ), np.ravel(obs.prox)
        # the cell where points outside the box look: empty in both grids (the box's
        # margin makes its first cell one; otherwise the first such cell, or one added)
        if occ[0] == 0 and prox[0] == 0:
            sentinel = 0
        else:
            empty = np.flatnonzero((occ == 0) & (prox == 0))
            if len(empty):
                sentinel = int(empty[0])
            else:
                occ, prox = np.append(occ, np.uint8(0)), np.append(prox, np.float32(0))
                sentinel = len(occ) - 1
        grid = np.array(prox, dtype=np.float32)       # the kernel's one gather: sign bit = occupied
        np.negative(grid, out=grid, where=occ != 0)
        self._grid, self._sentinel = grid, sentinel

    def counts(self, states: np.ndarray, active=None) -> np.ndarray:
        obs, f, lut = self.obs, self.flesh, self.lut
        Q = len(PARTS)
        act = np.ones(Q, dtype=np.bool_) if active is None else np.asarray(active, dtype=np.bool_)
        states = np.ascontiguousarray(states, dtype=np.float64)
        out = np.empty((len(states), Q, 5))
        need = lut.part_needs[act].any(axis=0)
        score_particles(states, f.height, lut.lx, lut.ly, lut.lz, lut.part_start, lut.part_segment,
                        lut.part_surface, lut.part_centre, lut.part_half, act, need,
                        self._grid, self._sentinel, self._dims, self._origin, obs.voxel_size,
                        np.asarray(obs.room_lo, np.float64), np.asarray(obs.room_hi, np.float64),
                        self._stamp, self._do_dims, f.spacing, self._token, out,
                        SEG_PARENT, lut.seg_offset, DOF_SEGMENT, DOF_AXIS)
        self._token += len(states)
        self.evaluations += len(states)
        return out

    def scores(self, states: np.ndarray, active=None) -> np.ndarray:
        """Per-part (rho_Out, rho_DO, rho_Empty, rho_Surf) of every state ``(P, Q, 4)``."""
        return normalise(self.counts(states, active), self.flesh)

    def log_weights(self, states: np.ndarray, active=None) -> np.ndarray:
        act = np.ones(len(PARTS), dtype=bool) if active is None else np.asarray(active, dtype=bool)
        return log_likelihood(self.scores(states, act), self.flesh, act, self.mode)
