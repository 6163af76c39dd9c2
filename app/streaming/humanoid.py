"""The contract's 15 joints as a humanoid avatar's bones: what the VMC protocol carries.

VMC (Virtual Motion Capture protocol, OSC over UDP) drives a VRM avatar in Unity
(EVMC4U), Blender add-ons and VR tools: a root transform and, per humanoid bone
(Unity's ``HumanBodyBones`` names), a local position and a local rotation. A VRM
model's humanoid is *normalised*: in its rest T-pose every bone's local rotation is
the identity and its axes are the world's (Unity: x to the avatar's right, y up, z
forward, left-handed, metres). So a bone's local rotation is ``R_parent^T R_bone``,
where ``R_bone`` is the world rotation taking the bone's rest T-pose directions to the
measured ones, and a receiver that applies them to any VRM avatar gets our pose.

Room to Unity axes: ``(x, y, z) -> (x, z, y)`` (z-up right-handed to y-up left-handed:
the floor stays the floor, a person's left stays on their left).

Each bone's world frame is measured from two directions (a primary one, the bone, and
a secondary one fixing its roll):

=============  ======================  ====================================  ============
bone           sits at                 primary (rest direction)              secondary
=============  ======================  ====================================  ============
Hips           pelvis                  up: pelvis - hip midpoint (+y)        right: r_hip - l_hip (+x)
Spine          pelvis                  neck - pelvis (+y)                    r_shoulder - l_shoulder (+x)
Chest          torso midpoint          as Spine (local identity)
Neck           neck                    head - neck (+y)                      the Spine's right (+x)
Head           head                    as Neck (local identity)
*UpperArm      shoulder                elbow - shoulder (left -x, right +x)  elbow hinge n
*LowerArm      elbow                   wrist - elbow                         elbow hinge n
*Hand          wrist                   as LowerArm (local identity)
*UpperLeg      hip                     knee - hip (-y)                       knee hinge n
*LowerLeg      knee                    ankle - knee (-y)                     knee hinge n
*Foot          ankle                   as LowerLeg (local identity)
=============  ======================  ====================================  ============

The hinge axis is ``n = upper x lower`` of the limb's two segments (in Unity axes); its
rest value is the one of a T-pose arm bent forward (left +y, right -y) and of a leg bent
at the knee (+x). A limb too straight for ``n`` to be measured (bent less than ~6 deg)
keeps the person's last measured hinge, or, before any, the parent's rest secondary
axis carried by the parent's rotation.

Local positions place every bone on the measured joints (the person's own limb
lengths, frame by frame), so forward kinematics of what is sent gives back all 15
joints: the root is the point of the floor under the pelvis (identity rotation), the
Hips' local position the pelvis height above it.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from app.messages import JOINTS

__all__ = ["HUMANOID_BONES", "to_unity", "from_unity", "HumanoidPose", "humanoid_poses", "quaternions",
           "rotation_matrices", "HingeMemory", "forward_kinematics"]

J = {name: n for n, name in enumerate(JOINTS)}
HINGE_MIN_SIN = 0.1        # a limb bent less than ~6 deg: its hinge axis is not measurable
ROOT_UP_MIN = 0.02         # m: pelvis above the hip midpoint by less -> the Hips' up from the neck

#: bone -> parent (Unity HumanBodyBones names, parents first)
HUMANOID_BONES = {
    "Hips": None, "Spine": "Hips", "Chest": "Spine", "Neck": "Chest", "Head": "Neck",
    "LeftUpperArm": "Chest", "LeftLowerArm": "LeftUpperArm", "LeftHand": "LeftLowerArm",
    "RightUpperArm": "Chest", "RightLowerArm": "RightUpperArm", "RightHand": "RightLowerArm",
    "LeftUpperLeg": "Hips", "LeftLowerLeg": "LeftUpperLeg", "LeftFoot": "LeftLowerLeg",
    "RightUpperLeg": "Hips", "RightLowerLeg": "RightUpperLeg", "RightFoot": "RightLowerLeg",
}
BONES = tuple(HUMANOID_BONES)
B = {name: n for n, name in enumerate(BONES)}
_PARENT_INDEX = np.array([-1 if parent is None else B[parent] for parent in HUMANOID_BONES.values()])

X, Y, Z = np.eye(3)
# limb -> (its joints: root, middle, end; rest direction of the segment; rest hinge axis)
_LIMBS = {
    "LeftArm": (("l_shoulder", "l_elbow", "l_wrist"), -X, Y),
    "RightArm": (("r_shoulder", "r_elbow", "r_wrist"), X, -Y),
    "LeftLeg": (("l_hip", "l_knee", "l_ankle"), -Y, X),
    "RightLeg": (("r_hip", "r_knee", "r_ankle"), -Y, X),
}
_LIMB_BONES = {"LeftArm": ("LeftUpperArm", "LeftLowerArm", "LeftHand", "Chest"),
               "RightArm": ("RightUpperArm", "RightLowerArm", "RightHand", "Chest"),
               "LeftLeg": ("LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "Hips"),
               "RightLeg": ("RightUpperLeg", "RightLowerLeg", "RightFoot", "Hips")}
# the same as arrays, limbs in _LIMBS order
_LIMB_JOINTS = np.array([[J[j] for j in joints] for joints, _, _ in _LIMBS.values()])        # (4, 3)
_LIMB_REST = np.array([[d, h] for _, d, h in _LIMBS.values()])                              # (4, 2, 3)
_LIMB_UPPER, _LIMB_LOWER, _LIMB_END, _LIMB_PARENTS = (np.array([B[bones[i]] for bones in _LIMB_BONES.values()])
                                                      for i in range(4))
_LIMB_PARENT_NAMES = [bones[3] for bones in _LIMB_BONES.values()]


def to_unity(points: np.ndarray) -> np.ndarray:
    """Room points (..., 3) (z up, right-handed) in Unity's axes (y up, left-handed)."""
    return np.asarray(points, float)[..., [0, 2, 1]]


def from_unity(points: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_unity` (the same swap)."""
    return np.asarray(points, float)[..., [0, 2, 1]]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    return v / np.where(n > 1e-9, n, 1.0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``numpy.cross`` of (..., 3) arrays, without its axis handling (a few times faster
    on the handful of vectors of a frame)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _frame(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) with columns (p, s', p x s') from a primary direction and a
    secondary one (made orthogonal to it)."""
    p = _unit(primary)
    s = _unit(secondary - np.sum(secondary * p, axis=-1, keepdims=True) * p)
    return np.stack([p, s, _cross(p, s)], axis=-1)


@lru_cache(maxsize=16)
def _rest_frame(rest_primary: tuple, rest_secondary: tuple) -> np.ndarray:
    return _frame(np.asarray(rest_primary, float)[None], np.asarray(rest_secondary, float)[None])[0]


def _rotation(primary, secondary, rest_primary, rest_secondary) -> np.ndarray:
    """The world rotations (N, 3, 3) taking the rest directions to the measured ones."""
    rest = _rest_frame(tuple(np.asarray(rest_primary, float)), tuple(np.asarray(rest_secondary, float)))
    return _frame(primary, secondary) @ rest.T


class HingeMemory:
    """Each person's last measured hinge axis per limb (Unity axes), for the frames
    where the limb is straight. Keyed by track id; :meth:`keep` forgets tracks gone."""

    def __init__(self):
        self.axes: dict[tuple[int, str], np.ndarray] = {}

    def keep(self, tracks) -> None:
        live = {int(t) for t in tracks}
        self.axes = {k: v for k, v in self.axes.items() if k[0] in live}


@dataclass
class HumanoidPose:
    """The avatar of N people: root positions (N, 3) on the floor (identity rotation),
    per bone (in :data:`HUMANOID_BONES` order) local positions (N, B, 3) and local
    rotations (N, B, 3, 3), all in Unity axes and metres."""

    root: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray


def humanoid_poses(joints: np.ndarray, tracks=None, memory: HingeMemory | None = None) -> HumanoidPose:
    """The humanoid bones of N people from their joints (N, 15, 3) in room coordinates
    (module docstring). ``tracks`` and ``memory`` carry each person's hinge axes from
    frame to frame (without them a straight limb takes its parent's rest axis)."""
    P = to_unity(np.asarray(joints, float).reshape(-1, len(JOINTS), 3))
    N = len(P)
    p = {name: P[:, J[name]] for name in JOINTS}
    world = np.zeros((N, len(BONES), 3, 3))
    local = np.zeros_like(world)
    pos = np.zeros((N, len(BONES), 3))

    mid_hip = 0.5 * (p["l_hip"] + p["r_hip"])
    up = p["pelvis"] - mid_hip
    low = np.linalg.norm(up, axis=-1) < ROOT_UP_MIN
    up[low] = (p["neck"] - mid_hip)[low]
    world[:, B["Hips"]] = _rotation(up, p["r_hip"] - p["l_hip"], Y, X)
    world[:, B["Spine"]] = _rotation(p["neck"] - p["pelvis"], p["r_shoulder"] - p["l_shoulder"], Y, X)
    world[:, B["Chest"]] = world[:, B["Spine"]]
    spine_right = world[:, B["Spine"]] @ X
    world[:, B["Neck"]] = _rotation(p["head"] - p["neck"], spine_right, Y, X)
    world[:, B["Head"]] = world[:, B["Neck"]]

    torso = np.linalg.norm(p["neck"] - p["pelvis"], axis=-1)
    chest_at = p["pelvis"] + 0.5 * torso[:, None] * (world[:, B["Spine"]] @ Y)
    root = p["pelvis"].copy()
    root[:, 1] = 0.0
    pos[:, B["Hips"]] = np.stack([np.zeros(N), p["pelvis"][:, 1], np.zeros(N)], axis=-1)
    pos[:, B["Chest"], 1] = 0.5 * torso
    pos[:, B["Neck"], 1] = 0.5 * torso
    pos[:, B["Head"], 1] = np.linalg.norm(p["head"] - p["neck"], axis=-1)

    # the four limbs at once (N, 4, ...): a frame's cost is numpy's per-call overhead, not its size
    j0, j1, j2 = _LIMB_JOINTS.T
    upper, lower = P[:, j1] - P[:, j0], P[:, j2] - P[:, j1]
    n = _cross(upper, lower)
    up_len, low_len = np.linalg.norm(upper, axis=-1), np.linalg.norm(lower, axis=-1)
    measured = np.linalg.norm(n, axis=-1) > HINGE_MIN_SIN * up_len * low_len
    hinge = _unit(n)
    parents = world[:, _LIMB_PARENTS]                                   # (N, 4, 3, 3)
    if not measured.all():
        fallback = np.einsum("nlij,lj->nli", parents, _LIMB_REST[:, 1])
        hinge[~measured] = fallback[~measured]
    if memory is not None and tracks is not None:
        ids = [int(t) for t in tracks]
        for k in range(N):
            for m, limb in enumerate(_LIMBS):
                key = (ids[k], limb)
                if measured[k, m]:
                    memory.axes[key] = hinge[k, m]
                elif key in memory.axes:
                    hinge[k, m] = memory.axes[key]
    across = np.einsum("nlij,lj->nli", parents, _cross(_LIMB_REST[:, 0], _LIMB_REST[:, 1]))
    rest = _frame(_LIMB_REST[:, 0], _LIMB_REST[:, 1])                   # (4, 3, 3)
    for segment, bones in ((upper, _LIMB_UPPER), (lower, _LIMB_LOWER)):
        s = hinge.copy()
        parallel = np.abs(np.sum(_unit(segment) * s, axis=-1)) > 0.999
        s[parallel] = across[parallel]
        world[:, bones] = _frame(segment, s) @ np.swapaxes(rest, -1, -2)
    world[:, _LIMB_END] = world[:, _LIMB_LOWER]
    parent_at = np.where(np.array([b == "Chest" for b in _LIMB_PARENT_NAMES])[None, :, None],
                         chest_at[:, None], p["pelvis"][:, None])
    pos[:, _LIMB_UPPER] = np.einsum("nlji,nlj->nli", parents, P[:, j0] - parent_at)
    pos[:, _LIMB_LOWER] = up_len[..., None] * _LIMB_REST[:, 0]
    pos[:, _LIMB_END] = low_len[..., None] * _LIMB_REST[:, 0]

    local[:, 0] = world[:, 0]
    local[:, 1:] = np.swapaxes(world[:, _PARENT_INDEX[1:]], -1, -2) @ world[:, 1:]
    return HumanoidPose(root, pos, local)


def forward_kinematics(root: np.ndarray, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """World positions (N, B, 3) of every bone (Unity axes) from what VMC carries: the
    root positions (N, 3) (identity rotation) and the bones' local positions and rotations."""
    N = len(root)
    world_pos = np.zeros((N, len(BONES), 3))
    world_rot = np.zeros((N, len(BONES), 3, 3))
    for name, parent in HUMANOID_BONES.items():
        i = B[name]
        if parent is None:
            world_pos[:, i] = root + positions[:, i]
            world_rot[:, i] = rotations[:, i]
        else:
            k = B[parent]
            world_pos[:, i] = world_pos[:, k] + np.einsum("nij,nj->ni", world_rot[:, k], positions[:, i])
            world_rot[:, i] = world_rot[:, k] @ rotations[:, i]
    return world_pos


def quaternions(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (x, y, z, w), Unity's order, of rotation matrices
    (..., 3, 3) (Shepperd's method: the largest of w, x, y, z is computed first)."""
    R = np.asarray(rotations, float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    diag = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=-1)
    which = np.argmax(diag, axis=-1)
    q = np.zeros((len(R), 4))
    for case in range(4):
        m = which == case
        if not m.any():
            continue
        r = R[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            q[m] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                             (r[:, 1, 0] - r[:, 0, 1]) / s, 0.25 * s], axis=-1)
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])
            q[m] = np.stack([0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s,
                             (r[:, 2, 1] - r[:, 1, 2]) / s], axis=-1)
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2])
            q[m] = np.stack([(r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s,
                             (r[:, 0, 2] - r[:, 2, 0]) / s], axis=-1)
        else:
            s = 2.0 * np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1])
            q[m] = np.stack([(r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s,
                             (r[:, 1, 0] - r[:, 0, 1]) / s], axis=-1)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)   # w >= 0: one of the two equal quaternions, always the same
    return q.reshape(shape + (4,))


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) as (x, y, z, w) (what a
    receiver does with them; :func:`quaternions`' inverse)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)], axis=-2)
