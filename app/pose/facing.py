"""Which way a person faces, from the feet: a vote kept over the frames that sets the
yaw prior while the person does not walk (``PoseSettings.toes``; beyond the thesis).

A visual hull seen from the front and from the back is nearly the same once the arms
hang: 6.5 % of the posed person-frames of tuning seeds 0-7 faced the wrong way (23 % of
the summed joint error), most of them people who turn in place or stand still from the
start, when the walking direction gives no heading prior (:mod:`app.pose.coverage`).
The feet are the body's one clear front: a foot reaches 0.11 H ahead of the ankle and
nothing lies behind the heel (0.03 H).

Each frame, at the ankles of the frame's estimate that are on the floor (within
:data:`LIFT` of their standing height), the floor's footprint (the person's voxels lower
than :data:`FOOT_BAND`) is looked up along the estimate's facing ``u`` (from its hips)
at :data:`TOE_POINTS` ahead of the ankle and :data:`HEEL_POINTS` behind it. A foot says
*ahead* when every toe point is occupied and no heel point, *behind* for the reverse,
and nothing otherwise (a footprint the hull widened all round, or no floor voxels); no
foot says anything where the footprint near the pelvis is wider than :data:`WIDE`. The
frame's vote is ``(feet saying ahead - feet saying behind) u``, in the floor plane; the
person's vote is the sum of the frames' votes, each frame's worth :data:`DECAY` of the
one after it. On the whole 4 cm hulls of tuning seeds 0-15 (all the reconstruction's
voxels, not the consensus the pose stage poses on), with the true ankles and facing, a
standing person-frame votes for the true facing in 39 %, against it in 3 % and not at
all in 58 %.

Why a vote and not a likelihood term: scored per particle (each particle's own feet),
the test pays a particle for moving its heels to the edge of a footprint the hull
widened behind the person (a person with a wall behind them, fewer cameras seeing the
floor there): tried on tuning seeds 0-6, MMTA 0.874 -> 0.860 (one weight), 0.842 (twice
it). The vote is read at the estimate's ankles, which the filter does not move for it.

Off by default: as a yaw prior of 0.8 rad it moved the tuning seeds 0-15 (replays of
the default pipeline, two filter seeds) from MMTA 0.7205 to 0.7149. The pose stage poses
on the consensus voxels, which often lose the toes while keeping floor excess behind
the person, and the vote then turns a correct pose round (docs/benchmarks.md, "The
feet's vote for the facing"); the whole hull's footprint is the next thing to try.
"""
from __future__ import annotations

import math

import numpy as np

from app.messages import JOINTS

__all__ = ["TOE_POINTS", "HEEL_POINTS", "FOOT_BAND", "LIFT", "DECAY", "VOTE", "WIDE", "WIDE_RADIUS",
           "floor_footprint", "frame_vote", "FacingVote"]

#: fractions of the height ahead of the ankle where the foot is (it reaches 0.108 H) ...
TOE_POINTS = (0.06, 0.10)
#: ... and behind it where it is not (the heel ends 0.032 H behind the ankle)
HEEL_POINTS = (0.08, 0.12)
#: m: the person's voxels lower than this are the floor's footprint
FOOT_BAND = 0.10
#: m: a foot votes while its ankle is at most this above its standing height (0.039 H)
LIFT = 0.05
#: each frame's vote is worth this much of the next frame's (about 10 frames' memory)
DECAY = 0.9
#: the person's vote sets the yaw prior once it is this long (about 3 frames of both feet)
VOTE = 3.0
#: no vote where the footprint within WIDE_RADIUS (m) of the pelvis covers more than
#: WIDE H^2 (two feet cover about 0.016 H^2; 0.06 H^2 is 0.18 m^2 at 1.75 m)
WIDE, WIDE_RADIUS = 0.06, 0.4

_J = {n: i for i, n in enumerate(JOINTS)}


def floor_footprint(occ: np.ndarray, origin, voxel_size: float, floor_z: float = 0.0) -> np.ndarray:
    """``(X, Y)`` bool: the columns of an observation's occupancy box ``occ (X, Y, Z)``
    (cell 0 at ``origin``) with a voxel whose centre is lower than ``floor_z + FOOT_BAND``."""
    k = int(math.ceil((floor_z + FOOT_BAND - float(origin[2])) / voxel_size - 0.5))
    k = min(max(k, 0), occ.shape[2])
    return occ[:, :, :k].any(axis=2) if k else np.zeros(occ.shape[:2], bool)


def _occupied(footprint, origin, size, p) -> bool:
    i, j = int(math.floor((p[0] - origin[0]) / size)), int(math.floor((p[1] - origin[1]) / size))
    return bool(0 <= i < footprint.shape[0] and 0 <= j < footprint.shape[1] and footprint[i, j])


def _says(footprint, origin, size, ankle, u, height) -> int:
    """+1 when the foot at ``ankle`` points along ``u``, -1 against it, 0 undecided."""
    ahead = [_occupied(footprint, origin, size, ankle + u * t * height) for t in TOE_POINTS]
    behind = [_occupied(footprint, origin, size, ankle - u * t * height) for t in HEEL_POINTS]
    if all(ahead) and not any(behind):
        return 1
    if all(behind) and not any(ahead):
        return -1
    return 0


def frame_vote(joints: np.ndarray, footprint: np.ndarray, origin, voxel_size: float, height: float,
               floor_z: float = 0.0) -> np.ndarray:
    """The frame's vote ``(2,)`` (module docstring) at the estimate's ``joints (15, 3)``."""
    left = joints[_J["l_hip"], :2] - joints[_J["r_hip"], :2]
    n = float(np.hypot(*left))
    if n == 0:
        return np.zeros(2)
    u = np.array([left[1], -left[0]]) / n          # forward = left x up
    i, j = (joints[_J["pelvis"], :2] - np.asarray(origin[:2])) / voxel_size
    r = WIDE_RADIUS / voxel_size
    near = footprint[max(int(i - r), 0):max(int(i + r) + 1, 0), max(int(j - r), 0):max(int(j + r) + 1, 0)]
    if near.sum() * voxel_size ** 2 > WIDE * height ** 2:   # a footprint the hull widened: no foot to read
        return np.zeros(2)
    rest = floor_z + 0.039 * height + LIFT
    says = 0
    for ankle in ("l_ankle", "r_ankle"):
        a = joints[_J[ankle]]
        if a[2] <= rest:
            says += _says(footprint, origin, voxel_size, a[:2], u, height) \
                - _says(footprint, origin, voxel_size, a[:2], -u, height)
    return 0.5 * says * u   # each foot's two readings (along u and against it) count once together


class FacingVote:
    """A person's vote (module docstring): :meth:`add` each posed frame, :meth:`heading`
    the yaw it sets (None while it is shorter than :data:`VOTE`)."""

    def __init__(self, vector=None):
        self.vector = np.zeros(2) if vector is None else np.asarray(vector, dtype=np.float64).reshape(2).copy()

    def add(self, vote: np.ndarray) -> None:
        self.vector = DECAY * self.vector + vote

    def heading(self) -> float | None:
        if float(np.hypot(*self.vector)) < VOTE:
            return None
        return float(math.atan2(self.vector[1], self.vector[0]))
