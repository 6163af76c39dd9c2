"""The articulated human body model of the pose filters (thesis §6.3.4, Table 6.1).

A root (the pelvis joint) with 6 global DoF (position, yaw, pitch, roll) and 21 joint
DoF: 3 at the waist, 2 at the neck, 3 per shoulder, 1 per elbow, 3 per hip, 1 per knee:
27 in all, the state vector ``y`` of every particle (:data:`DOFS` gives the order).

Each DoF is a rotation about a fixed axis ``omega`` of its segment's local frame; a
segment's rotation is its parent's times the exponential maps of its DoFs,
``R = R_parent * exp(theta_1 [omega_1]x) * exp(theta_2 [omega_2]x) ...`` (Eq. 6.1,
Appendix A: ``exp(theta [omega]x) = I + sin(theta) [omega]x + (1 - cos(theta)) [omega]x^2``,
Rodrigues' formula), and its origin is the parent's origin plus the parent's rotation
applied to a fixed offset. Offsets and lengths are fractions of the stature ("set in a
linear manner proportionally to the height of the subject", §6.3.4; the fractions are
Drillis & Contini's, as in the simulator, so that both agree on where joints are).

Conventions (shared with :mod:`app.simulation.body`, which the pose core does not
import): local frames x forward, y to the person's left, z up; positive angles: flexion
brings a limb forward (knee flexion backwards), abduction away from the midline.

Public API for other users of the skeleton (BVH export...): :data:`SEGMENTS` (joint
tree: name, parent, offset as fractions of the height), :data:`DOFS` with
:data:`DOF_SEGMENT`, :data:`DOF_AXIS`, :data:`LIMITS_LO` / :data:`LIMITS_HI`,
:class:`BodyModel` (``offsets()``, ``forward(y)`` -> segment frames,
``joints(y)`` -> the contract's 15 joints in :data:`app.messages.JOINTS` order).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.messages import JOINTS

__all__ = ["DOFS", "DOF", "SEGMENTS", "SEGMENT", "DOF_SEGMENT", "DOF_AXIS", "LIMITS_LO", "LIMITS_HI",
           "SIGMA0", "BodyModel", "Proportions", "AVERAGE", "exp_map", "neutral_state", "N_DOF", "N_SEG"]

INF = np.inf
#: ``(name, segment, axis, lo, hi, sigma0)``: the state vector. Angular limits are the
#: ranges of Table 6.1 narrowed to human limits where the table is wider (e.g. shoulder
#: flexion, knee); ``sigma0`` is the propagation noise P_0 (§3.2.2: half of the largest
#: expected change over one frame at 25 fps).
_DOF_TABLE = (
    ("x", "pelvis", (0, 0, 0), -INF, INF, 0.030),
    ("y", "pelvis", (0, 0, 0), -INF, INF, 0.030),
    ("z", "pelvis", (0, 0, 0), -INF, INF, 0.020),
    ("yaw", "pelvis", (0, 0, 1), -INF, INF, 0.06),
    ("pitch", "pelvis", (0, 1, 0), -0.35, 0.35, 0.02),
    ("roll", "pelvis", (1, 0, 0), -0.20, 0.20, 0.015),
    ("torso_twist", "torso", (0, 0, 1), -math.pi / 8, math.pi / 8, 0.025),
    ("torso_lat", "torso", (1, 0, 0), -math.pi / 4 * 0.6, math.pi / 4 * 0.6, 0.025),
    ("torso_flex", "torso", (0, 1, 0), -0.30, 1.20, 0.03),
    ("neck_lat", "head", (1, 0, 0), -0.60, 0.60, 0.04),
    ("neck_flex", "head", (0, 1, 0), -0.70, 0.90, 0.04),
    ("l_sh_flex", "l_upper_arm", (0, -1, 0), -0.90, 3.10, 0.1),
    ("l_sh_abd", "l_upper_arm", (1, 0, 0), -0.30, 2.90, 0.1),
    ("l_sh_rot", "l_upper_arm", (0, 0, -1), -1.50, 1.50, 0.1),
    ("l_elbow", "l_forearm", (0, -1, 0), 0.0, 2.50, 0.125),
    ("r_sh_flex", "r_upper_arm", (0, -1, 0), -0.90, 3.10, 0.1),
    ("r_sh_abd", "r_upper_arm", (-1, 0, 0), -0.30, 2.90, 0.1),
    ("r_sh_rot", "r_upper_arm", (0, 0, 1), -1.50, 1.50, 0.1),
    ("r_elbow", "r_forearm", (0, -1, 0), 0.0, 2.50, 0.125),
    ("l_hip_flex", "l_thigh", (0, -1, 0), -0.45, 2.00, 0.075),
    ("l_hip_abd", "l_thigh", (1, 0, 0), -0.35, 0.70, 0.04),
    ("l_hip_rot", "l_thigh", (0, 0, 1), -0.60, 0.60, 0.04),
    ("l_knee", "l_shin", (0, 1, 0), 0.0, 2.40, 0.1),
    ("r_hip_flex", "r_thigh", (0, -1, 0), -0.45, 2.00, 0.075),
    ("r_hip_abd", "r_thigh", (-1, 0, 0), -0.35, 0.70, 0.04),
    ("r_hip_rot", "r_thigh", (0, 0, -1), -0.60, 0.60, 0.04),
    ("r_knee", "r_shin", (0, 1, 0), 0.0, 2.40, 0.1),
)
DOFS = tuple(d[0] for d in _DOF_TABLE)
DOF = {n: i for i, n in enumerate(DOFS)}
N_DOF = len(DOFS)
LIMITS_LO = np.array([d[3] for d in _DOF_TABLE])
LIMITS_HI = np.array([d[4] for d in _DOF_TABLE])
SIGMA0 = np.array([d[5] for d in _DOF_TABLE])
DOF_AXIS = np.array([d[2] for d in _DOF_TABLE], dtype=np.float64)

#: Joint tree: ``(segment, parent, offset of its origin in the parent's frame as
#: fractions of the height)``. The pelvis segment's origin is the state's position.
SEGMENTS = (
    ("pelvis", None, (0.0, 0.0, 0.0)),
    ("torso", "pelvis", (0.0, 0.0, 0.0)),
    ("head", "torso", (0.0, 0.0, 0.295)),                 # origin at the neck
    ("l_upper_arm", "torso", (-0.005, 0.104, 0.260)),     # shoulder: neck - 0.035 H, 0.104 H aside
    ("l_forearm", "l_upper_arm", (0.0, 0.0, -0.186)),     # elbow
    ("r_upper_arm", "torso", (-0.005, -0.104, 0.260)),
    ("r_forearm", "r_upper_arm", (0.0, 0.0, -0.186)),
    ("l_thigh", "pelvis", (0.0, 0.052, -0.025)),          # hip
    ("l_shin", "l_thigh", (0.0, 0.0, -0.240)),            # knee
    ("r_thigh", "pelvis", (0.0, -0.052, -0.025)),
    ("r_shin", "r_thigh", (0.0, 0.0, -0.240)),
)
SEGMENT = {s[0]: i for i, s in enumerate(SEGMENTS)}
N_SEG = len(SEGMENTS)
SEG_PARENT = np.array([-1 if p is None else SEGMENT[p] for _, p, _ in SEGMENTS], dtype=np.int64)
SEG_OFFSET = np.array([o for _, _, o in SEGMENTS], dtype=np.float64)
DOF_SEGMENT = np.array([SEGMENT[d[1]] for d in _DOF_TABLE], dtype=np.int64)
#: DoFs 0-2 are the translation; rotational DoFs are the others, grouped by segment in order.
FIRST_ROT = 3

#: Lengths (fractions of the height) of the chain ends and points of the 15 joints.
FOREARM, SHIN, HAND = 0.146, 0.246, 0.072
HEAD_CENTRE = (0.012, 0.0, 0.090)
#: For each contract joint: (segment, local point as fractions of the height).
JOINT_POINTS = {
    "pelvis": ("pelvis", (0, 0, 0)), "neck": ("head", (0, 0, 0)), "head": ("head", HEAD_CENTRE),
    "l_shoulder": ("l_upper_arm", (0, 0, 0)), "l_elbow": ("l_forearm", (0, 0, 0)),
    "l_wrist": ("l_forearm", (0, 0, -FOREARM)),
    "r_shoulder": ("r_upper_arm", (0, 0, 0)), "r_elbow": ("r_forearm", (0, 0, 0)),
    "r_wrist": ("r_forearm", (0, 0, -FOREARM)),
    "l_hip": ("l_thigh", (0, 0, 0)), "l_knee": ("l_shin", (0, 0, 0)), "l_ankle": ("l_shin", (0, 0, -SHIN)),
    "r_hip": ("r_thigh", (0, 0, 0)), "r_knee": ("r_shin", (0, 0, 0)), "r_ankle": ("r_shin", (0, 0, -SHIN)),
}
JOINT_SEG = np.array([SEGMENT[JOINT_POINTS[j][0]] for j in JOINTS], dtype=np.int64)
JOINT_LOCAL = np.array([JOINT_POINTS[j][1] for j in JOINTS], dtype=np.float64)


def exp_map(theta: float, omega) -> np.ndarray:
    """Rotation ``exp(theta [omega]x)`` about the unit axis ``omega`` (App. A, Rodrigues)."""
    w = np.asarray(omega, dtype=np.float64)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


@njit(cache=True, nogil=True)
def _exp_into(theta, wx, wy, wz, out):
    s, c = math.sin(theta), 1.0 - math.cos(theta)
    out[0, 0] = 1.0 + c * (-wz * wz - wy * wy)
    out[0, 1] = -s * wz + c * wx * wy
    out[0, 2] = s * wy + c * wx * wz
    out[1, 0] = s * wz + c * wx * wy
    out[1, 1] = 1.0 + c * (-wz * wz - wx * wx)
    out[1, 2] = -s * wx + c * wy * wz
    out[2, 0] = -s * wy + c * wx * wz
    out[2, 1] = s * wx + c * wy * wz
    out[2, 2] = 1.0 + c * (-wy * wy - wx * wx)


@njit(cache=True, nogil=True, inline="always")
def _unit_axis(wx, wy, wz):
    """0, 1 or 2 when ``omega`` is +-x, +-y or +-z (every DoF of Table 6.1), else -1."""
    if wy == 0.0 and wz == 0.0 and abs(wx) == 1.0:
        return 0
    if wx == 0.0 and wz == 0.0 and abs(wy) == 1.0:
        return 1
    if wx == 0.0 and wy == 0.0 and abs(wz) == 1.0:
        return 2
    return -1


@njit(cache=True, nogil=True, inline="always")
def _rotate_about_axis(R, s, k, sign, theta):
    """``R[s] <- R[s] exp(theta [sign e_k]x)`` for a coordinate axis: the two columns of
    the rotation plane ``a < b`` only. Each entry is the same floating-point sum as the
    general product with :func:`_exp_into`'s matrix (whose other entries are exact 0
    and 1, which add nothing), so the results are identical; it saves the product's
    zero terms."""
    sn = math.sin(theta) * sign
    c = 1.0 - math.cos(theta)
    e = 1.0 + c * -1.0                     # _exp_into's diagonal entries of the plane
    if k == 0:
        a, b, e_ab, e_ba = 1, 2, -sn, sn
    elif k == 1:
        a, b, e_ab, e_ba = 0, 2, sn, -sn
    else:
        a, b, e_ab, e_ba = 0, 1, -sn, sn
    for i in range(3):
        ra, rb = R[s, i, a], R[s, i, b]
        R[s, i, a] = ra * e + rb * e_ba
        R[s, i, b] = ra * e_ab + rb * e


@njit(cache=True, nogil=True)
def fk_segments(y, height, seg_parent, seg_offset, dof_segment, dof_axis, R, O, need=None):
    """Forward kinematics of one state ``y`` (Eq. 6.1): segment rotations ``R (S, 3, 3)``
    (columns: local axes in the world) and origins ``O (S, 3)``, filled in place.
    ``need (S,)`` bool, if given, limits it to those segments (each with its ancestors
    set too): the others and their DoFs' sines and cosines are skipped, untouched."""
    E = np.empty((3, 3))
    T = np.empty((3, 3))
    d = FIRST_ROT
    n_dof = y.shape[0]
    for s in range(seg_parent.shape[0]):
        if need is not None and not need[s]:
            while d < n_dof and dof_segment[d] == s:
                d += 1
            continue
        p = seg_parent[s]
        if p < 0:
            for i in range(3):
                O[s, i] = y[i]
                for j in range(3):
                    R[s, i, j] = 1.0 if i == j else 0.0
        else:
            for i in range(3):
                O[s, i] = O[p, i] + height * (R[p, i, 0] * seg_offset[s, 0] + R[p, i, 1] * seg_offset[s, 1]
                                              + R[p, i, 2] * seg_offset[s, 2])
                for j in range(3):
                    R[s, i, j] = R[p, i, j]
        while d < n_dof and dof_segment[d] == s:
            wx, wy, wz = dof_axis[d, 0], dof_axis[d, 1], dof_axis[d, 2]
            k = _unit_axis(wx, wy, wz)
            if k >= 0:
                _rotate_about_axis(R, s, k, wx + wy + wz, y[d])
                d += 1
                continue
            _exp_into(y[d], wx, wy, wz, E)
            for i in range(3):
                for j in range(3):
                    T[i, j] = R[s, i, 0] * E[0, j] + R[s, i, 1] * E[1, j] + R[s, i, 2] * E[2, j]
            for i in range(3):
                for j in range(3):
                    R[s, i, j] = T[i, j]
            d += 1


@njit(cache=True, nogil=True)
def fk_joints_batch(states, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg, joint_local, out):
    """The 15 joints of every state ``(P, 27)`` into ``out (P, 15, 3)``."""
    S = seg_parent.shape[0]
    R = np.empty((S, 3, 3))
    O = np.empty((S, 3))
    for k in range(states.shape[0]):
        fk_segments(states[k], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O)
        for j in range(joint_seg.shape[0]):
            s = joint_seg[j]
            for i in range(3):
                out[k, j, i] = O[s, i] + height * (R[s, i, 0] * joint_local[j, 0] + R[s, i, 1] * joint_local[j, 1]
                                                   + R[s, i, 2] * joint_local[j, 2])


@njit(cache=True, nogil=True)
def fk_joints_subset_batch(states, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg, joint_local,
                           joints, need, out):
    """Some ``joints`` (indices into the 15) of every state into ``out (P, len(joints), 3)``:
    :func:`fk_joints_batch`'s arithmetic (bit-identical), over the ``need``-ed segments
    only (:func:`segments_needed`: the floor prior's ankles need 5 of 11, a torso frame 2)."""
    S = seg_parent.shape[0]
    R = np.empty((S, 3, 3))
    O = np.empty((S, 3))
    for k in range(states.shape[0]):
        fk_segments(states[k], height, seg_parent, seg_offset, dof_segment, dof_axis, R, O, need)
        for t in range(joints.shape[0]):
            j = joints[t]
            s = joint_seg[j]
            for i in range(3):
                out[k, t, i] = O[s, i] + height * (R[s, i, 0] * joint_local[j, 0] + R[s, i, 1] * joint_local[j, 1]
                                                   + R[s, i, 2] * joint_local[j, 2])


@njit(cache=True, nogil=True)
def fk_probed(x, dofs, eps, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg, joint_local, joints,
              need, probes, out):
    """Forward differences' kinematics: ``joints`` of the state ``x`` into ``out[0]`` and,
    into ``out[k + 1]``, of ``x`` with ``dofs[k]`` moved by ``eps`` (``probes``
    ``(len(dofs) + 1, 27)`` is the scratch; :func:`fk_joints_subset_batch`'s arithmetic)."""
    for k in range(dofs.shape[0] + 1):
        probes[k] = x
    for k in range(dofs.shape[0]):
        probes[k + 1, dofs[k]] += eps
    fk_joints_subset_batch(probes, height, seg_parent, seg_offset, dof_segment, dof_axis, joint_seg, joint_local,
                           joints, need, out)


#: Shares of the stature of the legs (hip to ankle) and the trunk (pelvis to neck) in the
#: average proportions above.
LEG_SHARE, TRUNK_SHARE = 0.240 + SHIN, 0.295


class Proportions:
    """A person's limb lengths against the average fractions above (issue 22): ``legs``
    scales thigh and shin, ``arms`` upper arm, forearm and hand; the trunk takes what the
    legs give or take so that the stature stays (as :func:`app.simulation.body.trunk_for_legs`:
    the shoulders stay 0.035 H under the neck). ``seg_offset`` and ``joint_local`` are
    :data:`SEG_OFFSET` and :data:`JOINT_LOCAL` for this person (the same arrays, bit for
    bit, for the average), what every kinematic kernel takes."""

    __slots__ = ("legs", "arms", "torso", "seg_offset", "joint_local")

    def __init__(self, legs: float = 1.0, arms: float = 1.0):
        if not (0.8 <= legs <= 1.2 and 0.8 <= arms <= 1.2):
            raise ValueError(f"proportions legs {legs}, arms {arms} are outside 0.8 .. 1.2")
        self.legs, self.arms = float(legs), float(arms)
        self.torso = (TRUNK_SHARE + LEG_SHARE * (1.0 - self.legs)) / TRUNK_SHARE
        if self.legs == 1.0 and self.arms == 1.0:
            self.seg_offset, self.joint_local = SEG_OFFSET, JOINT_LOCAL
            return
        off = SEG_OFFSET.copy()
        off[SEGMENT["head"], 2] = TRUNK_SHARE * self.torso
        for side in "lr":
            off[SEGMENT[f"{side}_upper_arm"], 2] += off[SEGMENT["head"], 2] - TRUNK_SHARE   # 0.035 H under the neck
            off[SEGMENT[f"{side}_forearm"], 2] *= self.arms
            off[SEGMENT[f"{side}_shin"], 2] *= self.legs
        local = JOINT_LOCAL.copy()
        for j, name in enumerate(JOINTS):
            if name.endswith("wrist"):
                local[j] *= self.arms
            elif name.endswith("ankle"):
                local[j] *= self.legs
        self.seg_offset, self.joint_local = np.ascontiguousarray(off), np.ascontiguousarray(local)

    def part_scale(self, segment: str) -> float:
        """The factor of a segment's length along its z axis (its flesh's cones)."""
        if segment in ("l_thigh", "r_thigh", "l_shin", "r_shin"):
            return self.legs
        if segment in ("l_upper_arm", "r_upper_arm", "l_forearm", "r_forearm"):
            return self.arms
        if segment == "torso":
            return self.torso
        return 1.0

    def __eq__(self, other) -> bool:
        return isinstance(other, Proportions) and (self.legs, self.arms) == (other.legs, other.arms)

    def __hash__(self) -> int:
        return hash((self.legs, self.arms))

    def __repr__(self) -> str:
        return f"Proportions(legs={self.legs:g}, arms={self.arms:g})"


#: Drillis & Contini's average, the thesis's model
AVERAGE = Proportions()


def segments_needed(joints) -> np.ndarray:
    """``need (S,)`` for :func:`fk_segments`: the segments of ``joints`` and their ancestors."""
    need = np.zeros(len(SEG_PARENT), dtype=np.bool_)
    for j in joints:
        s = int(JOINT_SEG[j])
        while s >= 0:
            need[s] = True
            s = int(SEG_PARENT[s])
    return need


def joints_subset(states: np.ndarray, height: float, joints: np.ndarray, need: np.ndarray | None = None,
                  proportions: Proportions = AVERAGE) -> np.ndarray:
    """``(P, len(joints), 3)``: the ``joints`` (int64 indices into the 15) of states
    ``(P, 27)``, the same numbers as :meth:`BodyModel.joints`, from the segments they
    need only (``need`` from :func:`segments_needed`, computed when not given), for a
    person of stature ``height`` and ``proportions``."""
    joints = np.asarray(joints, dtype=np.int64)
    need = segments_needed(joints) if need is None else need
    states = np.ascontiguousarray(states, dtype=np.float64)
    out = np.empty((len(states), len(joints), 3))
    fk_joints_subset_batch(states, float(height), SEG_PARENT, proportions.seg_offset, DOF_SEGMENT, DOF_AXIS,
                           JOINT_SEG, proportions.joint_local, joints, need, out)
    return out


def neutral_state(height: float = 1.75, position=(0.0, 0.0, None), yaw: float = 0.0) -> np.ndarray:
    """Standing at rest (the neutral pose of §6.5.1.1), arms slightly away from the body;
    the root at standing height unless ``position[2]`` is given."""
    y = np.zeros(N_DOF)
    y[0], y[1] = position[0], position[1]
    y[2] = standing_root_height(height) if position[2] is None else position[2]
    y[3] = yaw
    y[DOF["l_sh_abd"]] = y[DOF["r_sh_abd"]] = 0.10
    y[DOF["l_elbow"]] = y[DOF["r_elbow"]] = 0.15
    return y


#: the top of a standing person's voxels over their stature (the hair above the crown)
TOP_OVER_STATURE = 1.015


def stature_from_top(top: float, voxel_size: float) -> float:
    """The stature (m, within 1.45-2.05) of a person whose highest voxel centre near the
    body axis is at ``top``: the voxel's upper face over :data:`TOP_OVER_STATURE`."""
    return float(np.clip((top + voxel_size / 2) / TOP_OVER_STATURE, 1.45, 2.05))


def standing_top(height: float, voxel_size: float) -> float:
    """The highest voxel centre of a person of stature ``height`` standing straight (the
    inverse of :func:`stature_from_top`)."""
    return TOP_OVER_STATURE * height - voxel_size / 2


def standing_root_height(height: float, proportions: Proportions = AVERAGE) -> float:
    """Height of the root (pelvis joint) above the floor standing straight: ankle
    (0.039 H) + shin + thigh + hips below the root."""
    return (0.039 + LEG_SHARE * proportions.legs + 0.025) * height


class BodyModel:
    """The kinematic model of one person of a given height (metres)."""

    def __init__(self, height: float = 1.75, proportions: Proportions = AVERAGE):
        if not 1.0 <= height <= 2.3:
            raise ValueError(f"body height {height} m is outside 1.0 .. 2.3 m")
        self.height = float(height)
        self.proportions = proportions

    def offsets(self) -> np.ndarray:
        """Segment origin offsets in the parent's frame (metres), :data:`SEGMENTS` order."""
        return self.proportions.seg_offset * self.height

    def forward(self, y) -> tuple[np.ndarray, np.ndarray]:
        """Segment rotations ``(11, 3, 3)`` and origins ``(11, 3)`` of the state ``y``."""
        R, O = np.empty((N_SEG, 3, 3)), np.empty((N_SEG, 3))
        fk_segments(np.asarray(y, dtype=np.float64), self.height, SEG_PARENT, self.proportions.seg_offset,
                    DOF_SEGMENT, DOF_AXIS, R, O)
        return R, O

    def joints(self, y) -> np.ndarray:
        """The 15 contract joints ``(15, 3)`` of one state, or ``(P, 15, 3)`` of ``(P, 27)``."""
        y = np.asarray(y, dtype=np.float64)
        batch = np.atleast_2d(y)
        out = np.empty((batch.shape[0], len(JOINTS), 3))
        fk_joints_batch(np.ascontiguousarray(batch), self.height, SEG_PARENT, self.proportions.seg_offset,
                        DOF_SEGMENT, DOF_AXIS, JOINT_SEG, self.proportions.joint_local, out)
        return out[0] if y.ndim == 1 else out

    @staticmethod
    def within_limits(states, tol: float = 1e-9) -> bool:
        s = np.asarray(states)
        return bool(np.all(s >= LIMITS_LO - tol) and np.all(s <= LIMITS_HI + tol))


def posed_tracks(count: int, wanted=None) -> np.ndarray:
    """Boolean mask of ``count`` tracks: those in ``wanted`` (indices; None: every track),
    the people a pose worker poses (issue 26: a shard's share)."""
    pick = np.zeros(int(count), np.bool_)
    pick[np.arange(int(count)) if wanted is None else np.asarray(list(wanted), np.int64)] = True
    return pick
