"""Limb proposals from the markers themselves: Fontmarty's importance function (IAPF,
seed 001) fed by 3D marker candidates, so the marker APF follows limbs that move
farther in a frame than its diffusion reaches (a raised arm's wrist: 150 mm a frame at
25 fps; a walking foot's swing) and finds them again once lost.

* :func:`agreed_points`: the 3D marker candidates: points that two pairs of views or
  more triangulate within ``radius`` of each other (a marker seen by three views is
  triangulated by three pairs; a false detection's point rarely by two).
* :class:`LimbProposals`, the importance function ``(n, rng, base, dofs) -> (n, 27)``:
  on each drawn particle's own torso, each arm with probability one half gets its wrist
  on a candidate within an arm's reach of its shoulder (the pose stage's look-up inverse
  kinematics, :class:`app.pose.detections.Importance`), and each leg with probability
  one half its ankle on a candidate within a leg's reach below its hip (damped
  Gauss-Newton on hip flexion, abduction and knee, a few steps from the particle's own
  leg).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.pose.detections import Detections, Importance
from app.pose.model import (AVERAGE, DOF, DOF_AXIS, DOF_SEGMENT, JOINT_SEG, LIMITS_HI, LIMITS_LO, SEG_PARENT,
                            fk_probed, joints_subset, segments_needed)

__all__ = ["agreed_points", "LimbProposals"]

_ARMS = np.array([DOF[f"{side}_{n}"] for side in ("l", "r") for n in ("sh_flex", "sh_abd", "sh_rot", "elbow")])
_LEGS = {side: np.array([DOF[f"{side}_{n}"] for n in ("hip_flex", "hip_abd", "knee")]) for side in ("l", "r")}
_HIP = {"l": 9, "r": 12}
_ANKLE = {"l": 11, "r": 14}
_ANKLE_NEED = {side: segments_needed([_ANKLE[side]]) for side in ("l", "r")}
IK_STEPS = 6
#: of the stature: how far from its last place a two-view ankle candidate may be; 0 = none
#: (off: on synthetic detections 0.2 gained, held-out walk1 + occluded1 0.881 -> 0.905, but from
#: rendered images it pulled gesture1's knees to chance pairs, 0.886 -> 0.771: docs/benchmarks.md)
FOOT_SEARCH = 0.0
IK_DAMPING = 1e-3


def agreed_points(points: np.ndarray, radius: float = 0.03) -> np.ndarray:
    """The means (K, 3) of the groups of ``points`` that agree within ``radius``
    (module docstring): the point with the most others within ``radius`` takes them as its
    group, then the next one of those left, and so on; a point alone makes no group."""
    if len(points) < 2:
        return np.zeros((0, 3))
    points = np.ascontiguousarray(points, dtype=np.float64)
    first, near = _neighbours(points, float(radius))
    counts = np.diff(first)
    order = np.argsort(-counts, kind="quicksort")
    return _groups(points, first, near, order[counts[order] >= 2])


@njit(cache=True, nogil=True)
def _neighbours(points, radius):
    """Each point's neighbours within ``radius`` (itself among them), in index order:
    ``near[first[i]:first[i + 1]]``; the points sorted along x bound the search."""
    N = points.shape[0]
    r2 = radius * radius
    by_x = np.argsort(points[:, 0])
    xs = points[by_x, 0]
    rank = np.empty(N, np.int64)
    for k in range(N):
        rank[by_x[k]] = k
    first = np.zeros(N + 1, np.int64)
    rows = []
    for i in range(N):
        row = []
        k = rank[i]
        lo = k
        while lo > 0 and xs[lo - 1] >= points[i, 0] - radius:
            lo -= 1
        hi = k
        while hi + 1 < N and xs[hi + 1] <= points[i, 0] + radius:
            hi += 1
        for s in range(lo, hi + 1):
            j = by_x[s]
            dx = points[i, 0] - points[j, 0]
            dy = points[i, 1] - points[j, 1]
            dz = points[i, 2] - points[j, 2]
            if dx * dx + dy * dy + dz * dz < r2:
                row.append(j)
        row.sort()
        rows.append(row)
        first[i + 1] = first[i] + len(row)
    near = np.empty(first[N], np.int64)
    for i in range(N):
        for k in range(len(rows[i])):
            near[first[i] + k] = rows[i][k]
    return first, near


@njit(cache=True, nogil=True)
def _groups(points, first, near, order):
    """:func:`agreed_points`' groups, taken in ``order``: their means (K, 3)."""
    taken = np.zeros(points.shape[0], np.bool_)
    out = np.empty((order.shape[0], 3))
    K = 0
    for k in order:
        if taken[k]:
            continue
        g = 0
        total = np.zeros(3)
        for s in range(first[k], first[k + 1]):
            j = near[s]
            if taken[j]:
                continue
            taken[j] = True
            for i in range(3):
                total[i] += points[j, i]
            g += 1
        out[K] = total / g
        K += 1
    return out[:K].copy()


def leg_ik(states: np.ndarray, side: str, targets: np.ndarray, height: float) -> np.ndarray:
    """``states`` with each row's ``side`` leg (hip flexion, abduction, knee) moved so
    that its ankle comes as near ``targets`` (n, 3) as the joint limits allow."""
    S = np.array(states, dtype=np.float64)
    dofs = _LEGS[side]
    joint = np.array([_ANKLE[side]], np.int64)
    need = _ANKLE_NEED[side]
    eps = 1e-4
    # the knee first, from the hip-ankle distance (law of cosines: thigh 0.240 H, shin
    # 0.246 H): from a straight leg, a knee's first-order effect moves the ankle sideways,
    # not nearer, and the steps below would stall there
    hip = joints_subset(S, height, np.array([_HIP[side]], np.int64))[:, 0]
    thigh, shin = 0.240 * height, 0.246 * height
    d = np.clip(np.linalg.norm(targets - hip, axis=1), abs(thigh - shin) + 1e-3, thigh + shin - 1e-3)
    cos_k = (thigh * thigh + shin * shin - d * d) / (2 * thigh * shin)
    knee = dofs[2]
    S[:, knee] = np.clip(np.pi - np.arccos(np.clip(cos_k, -1.0, 1.0)), LIMITS_LO[knee], LIMITS_HI[knee])
    _leg_steps(S, np.ascontiguousarray(targets, dtype=np.float64), dofs, joint, need, float(height), SEG_PARENT,
               AVERAGE.seg_offset, DOF_SEGMENT, DOF_AXIS, JOINT_SEG, AVERAGE.joint_local, LIMITS_LO[dofs],
               LIMITS_HI[dofs], IK_STEPS, eps, IK_DAMPING)
    return S


@njit(cache=True, nogil=True)
def _leg_steps(S, targets, dofs, joint, need, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg,
               joint_local, lo, hi, steps, eps, damping):
    """:func:`leg_ik`'s damped Gauss-Newton steps, row by row in place: the ankle's
    Jacobian over ``dofs`` by forward differences of ``eps``, each step solved from the
    normal equations (``damping`` on the diagonal) and clipped to ``lo``, ``hi``."""
    D = dofs.shape[0]
    probes = np.empty((D + 1, S.shape[1]))
    ankles = np.empty((D + 1, 1, 3))
    J = np.empty((3, D))
    A = np.empty((D, D))
    b = np.empty(D)
    for row in range(S.shape[0]):
        for _ in range(steps):
            fk_probed(S[row], dofs, eps, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg,
                      joint_local, joint, need, probes, ankles)
            for k in range(D):
                for i in range(3):
                    J[i, k] = (ankles[k + 1, 0, i] - ankles[0, 0, i]) / eps
            for k in range(D):
                for l in range(D):
                    a = 0.0
                    for i in range(3):
                        a += J[i, k] * J[i, l]
                    A[k, l] = a + (damping if k == l else 0.0)
                r = 0.0
                for i in range(3):
                    r += J[i, k] * (targets[row, i] - ankles[0, 0, i])
                b[k] = r
            step = np.linalg.solve(A, b)
            for k in range(D):
                S[row, dofs[k]] = min(max(S[row, dofs[k]] + step[k], lo[k]), hi[k])


class LimbProposals:
    """The importance function of one frame (module docstring) around the joints
    ``joints`` (15, 3) of the person's last pose; None-safe: :meth:`of` returns None
    without candidates near the person."""

    def __init__(self, candidates: np.ndarray, joints: np.ndarray, height: float, yaw: float,
                 pairs: np.ndarray | None = None):
        self.height = float(height)
        H = self.height
        d_sh = np.linalg.norm(candidates[:, None] - joints[[3, 6]][None], axis=2).min(axis=1)
        self.hands = candidates[(d_sh < 0.36 * H) & (d_sh > 0.12 * H)]
        hips = joints[[_HIP["l"], _HIP["r"]]]
        d_hip = np.linalg.norm(candidates[:, None] - hips[None], axis=2).min(axis=1)
        below = candidates[:, 2] < hips[:, 2].max() - 0.1 * H
        self.feet = candidates[(d_hip < 0.52 * H) & (d_hip > 0.2 * H) & below]
        if FOOT_SEARCH > 0 and pairs is not None and len(pairs):
            # an ankle low in the room is often seen by two cameras only (no third view
            # supports it): pairs near the last ankles and near the floor are candidates too
            d_ank = np.linalg.norm(pairs[:, None] - joints[[_ANKLE["l"], _ANKLE["r"]]][None], axis=2).min(axis=1)
            low = pairs[(d_ank < FOOT_SEARCH * H) & (pairs[:, 2] < 0.15 * H)]
            self.feet = np.concatenate([self.feet, low])
        self.arms = None
        if len(self.hands):
            det = Detections(head=joints[2], top=float(joints[2, 2] + 0.066 * H), centroid=joints[0],
                             headings=[float(yaw)], hands=self.hands)
            self.arms = Importance(det, H)

    @classmethod
    def of(cls, candidates, joints, height, yaw, pairs=None):
        p = cls(candidates, joints, height, yaw, pairs) if len(candidates) or (pairs is not None and len(pairs)) \
            else None
        return p if p is not None and (p.arms is not None or len(p.feet)) else None

    def __call__(self, n: int, rng: np.random.Generator, base: np.ndarray, dofs=None) -> np.ndarray:
        out = np.array(base, dtype=np.float64)
        if self.arms is not None:
            out = self.arms(n, rng, out, _ARMS)
        if len(self.feet):
            for side in ("l", "r"):
                use = np.flatnonzero(rng.random(n) < 0.5)
                if len(use):
                    targets = self.feet[rng.integers(len(self.feet), size=len(use))]
                    out[use] = leg_ik(out[use], side, targets, self.height)
        return np.clip(out, LIMITS_LO, LIMITS_HI)
