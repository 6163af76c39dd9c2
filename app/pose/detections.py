"""Detections in a person's voxels and the importance function built from them
(Fontmarty et al.'s IAPF, seed 001: detections as an importance function in the first
annealing layer, so a filter starts by itself and recovers when it has lost the pose).

Detections (cheap, from the voxel list):

* **head**: the top of the blob near the body axis (the median of the trunk band, so a
  hand raised above the head is not taken for it): the mean of the voxels within 8 cm
  of the highest one;
* **torso axis**: from the pelvis estimate to the head, and the principal horizontal
  axis of the shoulder band, whose normal is the heading up to a sign (two
  candidates; the track's velocity picks one while the person walks);
* **extremities**: voxels of the upper body far from the torso (farther than 0.30 m
  from the axis through the head, or above the head, or farther than 0.32 H from the
  shoulders' centre and above the hips, but within an arm's reach, 0.5 H): the 20
  farthest on each side of the shoulder line (hand candidates). Each is turned into
  arm angles by inverse kinematics: a look-up table of random arm configurations
  inside the joint limits (shoulder flexion, abduction, rotation and elbow) indexed
  by where they put the wrist relative to the shoulder in the torso frame (cells of
  2.5 % of the stature); a draw takes a configuration whose wrist falls in the
  target's cell (the target pulled back half a hand, within reach), so a bent arm (a
  forearm raised over a horizontal upper arm) is proposed as readily as a straight
  one. ``ik="straight"`` keeps the straight arm pointed at the target (the earlier
  proposal).

The importance function draws whole states: root under the head at the height the
blob's top allows, heading from the candidates, waist flexion from the lean, arms
toward extremities (or hanging), legs near standing (or, for a share ``low_legs`` of the
draws whose root is well below standing, bent so that the feet reach the floor: sitting,
crouching), all with Gaussian noise and inside the joint limits. Draws replace a
fraction of the first layer's particles (the mixture proposal of IAPF; the dynamics'
particles stay, so tracking is not disturbed when the detections are wrong).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from app.messages import JOINTS
from app.pose.model import (DOF, LIMITS_HI, LIMITS_LO, BodyModel, joints_subset, neutral_state, segments_needed,
                            standing_root_height)

__all__ = ["Detections", "detect", "Importance"]


@dataclass
class Detections:
    head: np.ndarray              # (3,) top-of-blob head estimate (centre ~ top - 0.066 H)
    top: float                    # z of the top of the blob
    centroid: np.ndarray          # (3,)
    headings: list = field(default_factory=list)   # candidate yaws
    hands: np.ndarray = None      # (K, 3) extremity candidates


def detect(centres: np.ndarray, height: float, velocity=None) -> Detections | None:
    """Detections in one person's voxel centres ``(N, 3)``; None when too few voxels."""
    if len(centres) < 30:
        return None
    c = np.ascontiguousarray(centres, dtype=np.float64)
    axis, top, head, centroid, xy = _body_axis_head(c, float(height))
    band = xy   # the shoulder band's horizontal coordinates, centred (B, 2)
    headings = []
    if velocity is not None and np.hypot(*velocity[:2]) > 0.3:
        headings.append(math.atan2(velocity[1], velocity[0]))
    if len(band) >= 10:
        evals, evecs = np.linalg.eigh(xy.T @ xy)
        major = evecs[:, 1]
        yaw = math.atan2(major[1], major[0]) - math.pi / 2    # the shoulder line's normal
        headings += [yaw, yaw + math.pi]
    if not headings:
        headings = list(np.linspace(-math.pi, math.pi, 4, endpoint=False))
    # extremities: upper-body voxels far from the torso, the farthest of each side
    # (far from the shoulders only above the hips: the hips are as far from them as a hand)
    # (and within an arm's reach: a hull's ghosts farther away are nobody's hand)
    far, r = _extremities(c, float(height), top, head)
    hands = None
    if len(far):
        side = np.ones(len(far), dtype=bool)
        if len(band) >= 10:
            side = (far[:, :2] - axis) @ major >= 0
        keep = []
        for group in (np.flatnonzero(side), np.flatnonzero(~side)):
            order = group[np.argsort(-r[group])]
            keep.extend(order[:20])
        hands = far[np.array(keep, dtype=np.int64)]
    return Detections(head=head, top=top, centroid=centroid, headings=headings, hands=hands)


@njit(cache=True, nogil=True)
def _body_axis_head(c, height):
    """:func:`detect`'s body axis, blob top, head, centroid and the centred horizontal
    coordinates of the shoulder band, in passes over the voxel list instead of numpy's
    masked copies (the same operations: medians, sums in order, the same numbers)."""
    n = c.shape[0]
    buf = np.empty(n)
    m = 0
    for i in range(n):
        if c[i, 2] > 0.50 * height and c[i, 2] < 0.70 * height:
            m += 1
    axis = np.empty(2)
    for d in range(2):
        k = 0
        for i in range(n):
            if m < 10 or (c[i, 2] > 0.50 * height and c[i, 2] < 0.70 * height):
                buf[k] = c[i, d]
                k += 1
        axis[d] = np.median(buf[:k])
    near = np.empty(n, dtype=np.bool_)
    k = 0
    for i in range(n):
        near[i] = np.hypot(c[i, 0] - axis[0], c[i, 1] - axis[1]) < 0.18
        k += near[i]
    if k < 10:
        near[:] = True
    top = -np.inf
    for i in range(n):
        if near[i] and c[i, 2] > top:
            top = c[i, 2]
    head = np.zeros(3)
    k = 0
    for i in range(n):
        if near[i] and c[i, 2] >= top - 0.08:
            for d in range(3):
                head[d] += c[i, d]
            k += 1
    head /= k
    head[2] = top - 0.066 * height
    centroid = np.zeros(3)
    for i in range(n):
        for d in range(3):
            centroid[d] += c[i, d]
    centroid /= n
    lo, hi = top - 0.30 * height, top - 0.12 * height
    mean = np.zeros(2)
    k = 0
    for i in range(n):
        if c[i, 2] > lo and c[i, 2] < hi:
            mean[0] += c[i, 0]
            mean[1] += c[i, 1]
            k += 1
    xy = np.empty((k, 2))
    if k:
        mean /= k
        k = 0
        for i in range(n):
            if c[i, 2] > lo and c[i, 2] < hi:
                xy[k, 0] = c[i, 0] - mean[0]
                xy[k, 1] = c[i, 1] - mean[1]
                k += 1
    return axis, top, head, centroid, xy


@njit(cache=True, nogil=True)
def _extremities(c, height, top, head):
    """:func:`detect`'s extremity candidates (upper-body voxels far from the torso,
    within an arm's reach) and their distances to the shoulders' centre, in voxel order."""
    n = c.shape[0]
    far = np.empty((n, 3))
    r = np.empty(n)
    chest2 = head[2] - 0.125 * height
    k = 0
    for i in range(n):
        z = c[i, 2]
        if not z > top - 0.55 * height:
            continue
        d = np.hypot(c[i, 0] - head[0], c[i, 1] - head[1])
        e0, e1, e2 = c[i, 0] - head[0], c[i, 1] - head[1], z - chest2
        ri = np.sqrt((e0 * e0 + e1 * e1) + e2 * e2)
        if (d > 0.30 or z > top + 0.04 or (ri > 0.32 * height and z > top - 0.42 * height)) and ri < 0.50 * height:
            far[k, 0], far[k, 1], far[k, 2] = c[i, 0], c[i, 1], z
            r[k] = ri
            k += 1
    return far[:k], r[:k]


def _arm_angles(direction: np.ndarray, side: int):
    """Shoulder (flexion, abduction) that point a straight arm along ``direction`` (in the
    torso frame): the arm axis is ``(sin f cos a, s sin a, -cos f cos a)``."""
    d = direction / max(np.linalg.norm(direction), 1e-9)
    a = math.asin(max(-1.0, min(1.0, side * d[1])))
    f = math.atan2(d[0], -d[2])
    return f, a


_ARM_DOFS = {side: np.array([DOF[f"{side}_{n}"] for n in ("sh_flex", "sh_abd", "sh_rot", "elbow")])
             for side in ("l", "r")}
_IK_CELL = 0.025
_ARM_COLS = np.arange(4)   # the arm DoFs' columns in a table's configurations
_IK_TABLES: dict = {}


def arm_table(side: str, n: int = 40000):
    """Inverse kinematics by look-up: ``(configs (n, 4), wrist (n, 3), keys sorted, order)``
    of random arm configurations of one side inside the joint limits, with the wrist
    relative to the shoulder in the torso frame in units of the stature."""
    if side not in _IK_TABLES:
        rng = np.random.default_rng(20091)
        d = _ARM_DOFS[side]
        cfg = rng.uniform(LIMITS_LO[d], LIMITS_HI[d], size=(n, 4))
        states = np.tile(neutral_state(1.0, (0.0, 0.0, 1.0)), (n, 1))
        states[:, d] = cfg
        j = BodyModel(1.0).joints(states)
        wrist = j[:, JOINTS.index(f"{side}_wrist")] - j[:, JOINTS.index(f"{side}_shoulder")]
        keys = _ik_keys(wrist)
        order = np.argsort(keys, kind="stable")
        _IK_TABLES[side] = (cfg[order], wrist[order], keys[order])
    return _IK_TABLES[side]


def _ik_keys(rel: np.ndarray) -> np.ndarray:
    q = np.floor(np.asarray(rel) / _IK_CELL).astype(np.int64) + 64
    return (q[..., 0] * 128 + q[..., 1]) * 128 + q[..., 2]


_TORSO_JOINTS = np.array([JOINTS.index(n) for n in ("l_shoulder", "r_shoulder", "neck", "pelvis")], dtype=np.int64)
_TORSO_NEED = segments_needed(_TORSO_JOINTS)


def _torso_frames(states: np.ndarray, height: float):
    """Shoulders ``{side: (n, 3)}`` and torso frames ``(n, 3, 3)`` (columns x forward,
    y left, z up) of states, from their joints."""
    j = joints_subset(states, height, _TORSO_JOINTS, _TORSO_NEED)    # the trunk's segments only
    frames = np.empty((len(j), 3, 3))
    _frames_of(j, frames)
    return {"l": j[:, 0], "r": j[:, 1]}, frames


@njit(cache=True, nogil=True)
def _frames_of(j, frames):
    """The torso frames of :func:`_torso_frames` from the joints ``(n, 4, 3)`` (left and
    right shoulder, neck, pelvis): numpy's operations one by one (sums of three in
    order, the cross product as numpy's), so the same numbers in one loop."""
    for m in range(j.shape[0]):
        u0, u1, u2 = j[m, 2, 0] - j[m, 3, 0], j[m, 2, 1] - j[m, 3, 1], j[m, 2, 2] - j[m, 3, 2]
        nu = max(np.sqrt((u0 * u0 + u1 * u1) + u2 * u2), 1e-9)
        u0, u1, u2 = u0 / nu, u1 / nu, u2 / nu
        l0, l1, l2 = j[m, 0, 0] - j[m, 1, 0], j[m, 0, 1] - j[m, 1, 1], j[m, 0, 2] - j[m, 1, 2]
        dot = (l0 * u0 + l1 * u1) + l2 * u2
        l0, l1, l2 = l0 - dot * u0, l1 - dot * u1, l2 - dot * u2
        nl = max(np.sqrt((l0 * l0 + l1 * l1) + l2 * l2), 1e-9)
        l0, l1, l2 = l0 / nl, l1 / nl, l2 / nl
        frames[m, 0, 0], frames[m, 1, 0], frames[m, 2, 0] = l1 * u2 - l2 * u1, l2 * u0 - l0 * u2, l0 * u1 - l1 * u0
        frames[m, 0, 1], frames[m, 1, 1], frames[m, 2, 1] = l0, l1, l2
        frames[m, 0, 2], frames[m, 1, 2], frames[m, 2, 2] = u0, u1, u2


@njit(cache=True, nogil=True)
def _ik_cells(frames, shoulders, use, targets, height, keys, lo, hi):
    """For each row ``use[r]``: the wrist target ``targets[r]`` in that row's torso frame
    relative to its shoulder, in statures, pulled back half a hand and kept within reach
    (as :meth:`Importance._arms_ik` describes), its look-up cell and the range
    ``[lo, hi)`` of the table's sorted ``keys`` in that cell (numpy's operations one by
    one: the same cells); returns how many rows' cells have configurations."""
    found = 0
    for r in range(use.shape[0]):
        m = use[r]
        v0 = targets[r, 0] - shoulders[m, 0]
        v1 = targets[r, 1] - shoulders[m, 1]
        v2 = targets[r, 2] - shoulders[m, 2]
        x0 = ((frames[m, 0, 0] * v0 + frames[m, 1, 0] * v1) + frames[m, 2, 0] * v2) / height
        x1 = ((frames[m, 0, 1] * v0 + frames[m, 1, 1] * v1) + frames[m, 2, 1] * v2) / height
        x2 = ((frames[m, 0, 2] * v0 + frames[m, 1, 2] * v1) + frames[m, 2, 2] * v2) / height
        norm = max(np.sqrt((x0 * x0 + x1 * x1) + x2 * x2), 1e-9)
        f = min(max(norm - 0.04, 0.02), 0.325) / norm
        q0 = np.int64(np.floor(x0 * f / _IK_CELL)) + 64
        q1 = np.int64(np.floor(x1 * f / _IK_CELL)) + 64
        q2 = np.int64(np.floor(x2 * f / _IK_CELL)) + 64
        key = (q0 * 128 + q1) * 128 + q2
        a, b = 0, keys.shape[0]          # first index with keys >= key
        while a < b:
            c = (a + b) >> 1
            if keys[c] < key:
                a = c + 1
            else:
                b = c
        lo[r] = a
        b = keys.shape[0]                # first index with keys > key
        while a < b:
            c = (a + b) >> 1
            if keys[c] <= key:
                a = c + 1
            else:
                b = c
        hi[r] = a
        found += hi[r] > lo[r]
    return found


@njit(cache=True, nogil=True)
def _ik_assign(out, use, lo, hi, u, cfg, dofs, cols, noise):
    """The rows ``use`` whose cell has configurations (``hi > lo``), in order, take the
    table's configuration ``lo + int(u (hi - lo))`` plus ``noise`` on the arm DoFs
    ``dofs[cols]`` (numpy's operations: the same numbers as the fancy-indexed update)."""
    k = 0
    for r in range(use.shape[0]):
        if hi[r] <= lo[r]:
            continue
        pick = lo[r] + np.int64(u[k] * np.float64(hi[r] - lo[r]))
        for c in range(cols.shape[0]):
            out[use[r], dofs[cols[c]]] = cfg[pick, cols[c]] + noise[k, c]
        k += 1


#: the importance draws' DoFs after the root's, in the order they are drawn: (DoF, mean,
#: deviation, folded to |.|): the trunk and neck near upright, legs near standing, arms hanging
_REST = ([(n, 0.0, 0.05, False) for n in ("pitch", "roll", "torso_twist", "torso_lat", "neck_lat", "neck_flex")]
         + [(f"{side}_{n}", loc, scale, fold) for side in ("l", "r") for n, loc, scale, fold in (
             ("hip_flex", 0.05, 0.15, False), ("hip_abd", 0.0, 0.05, False), ("hip_rot", 0.0, 0.05, False),
             ("knee", 0.1, 0.2, True), ("sh_flex", 0.0, 0.2, False), ("sh_abd", 0.1, 0.2, True),
             ("sh_rot", 0.0, 0.2, False), ("elbow", 0.2, 0.3, True))])
_REST_DOFS = np.array([DOF[r[0]] for r in _REST], dtype=np.int64)
_REST_LOC = np.array([r[1] for r in _REST])
_REST_SCALE = np.array([r[2] for r in _REST])
_REST_ABS = np.array([r[3] for r in _REST])


class Importance:
    """The importance function ``q(y | detections)`` of one frame (callable
    ``(n, rng, base, dofs) -> (n, 27)``; ``base`` gives the DoFs the detections say
    nothing about, ``dofs`` (optional) the only DoFs drawn: the others stay the base's,
    and the arms' inverse kinematics is solved on the base's torso)."""

    def __init__(self, det: Detections, height: float, ik: str = "table", low_legs: float = 0.0):
        if ik not in ("table", "straight"):
            raise ValueError(f"ik {ik!r} must be table or straight")
        self.det, self.height, self.ik, self.low_legs = det, height, ik, float(low_legs)

    def __call__(self, n: int, rng: np.random.Generator, base: np.ndarray | None = None, dofs=None) -> np.ndarray:
        out = self._draw(n, rng, base)
        if dofs is not None and base is not None:
            merged = np.array(base, dtype=np.float64)
            merged[:, dofs] = out[:, dofs]
            out = merged
        if self.ik == "table" and self.det.hands is not None and len(self.det.hands):
            self._arms_ik(out, rng, dofs)
        if self.low_legs > 0:
            self._low_legs(out, rng, dofs)
        return np.clip(out, LIMITS_LO, LIMITS_HI)

    def _low_legs(self, out: np.ndarray, rng: np.random.Generator, dofs) -> None:
        """Legs that reach the floor from a lowered root (sitting, crouching): of the
        draws whose root is more than 0.05 H below standing, ``low_legs`` get each leg
        bent so that its ankle is at its standing height (0.039 H) below the hip, with
        the shin at a random angle ``phi`` from vertical (-0.4..0.5 rad, forward
        positive): the thigh's angle ``a`` from vertical by ``L_thigh cos(a) + L_shin
        cos(phi) = hip_z - 0.039 H``, hip flexion ``a`` plus the pelvis's pitch, knee
        ``a - phi``. The near-standing legs of :meth:`_draw` put a lowered root on
        its knees, and the annealing's steps (0.075 rad of hip flexion a frame) do not
        reach a seated pose from there: a person who sat down was posed kneeling into
        the floor (tuning seed 4, 350 mm off for the 5 s she sat)."""
        legs = [DOF[f"{side}_{n}"] for side in ("l", "r") for n in ("hip_flex", "knee")]
        if dofs is not None and not np.isin(legs, dofs).any():
            return
        H = self.height
        hip_z = out[:, DOF["z"]] - 0.025 * H
        low = out[:, DOF["z"]] < standing_root_height(H) - 0.05 * H
        use = np.flatnonzero(low & (rng.random(len(out)) < self.low_legs))
        if len(use) == 0:
            return
        thigh, shin = 0.240 * H, 0.246 * H
        pitch = out[use, DOF["pitch"]]   # a pelvis pitched by p swings the thighs back by p
        for side in ("l", "r"):
            phi = rng.uniform(-0.4, 0.5, len(use))
            c = (hip_z[use] - 0.039 * H - shin * np.cos(phi)) / thigh
            thigh_angle = np.arccos(np.clip(c, -1.0, 1.0)) + rng.normal(0.0, 0.03, len(use))
            out[use, DOF[f"{side}_hip_flex"]] = thigh_angle + pitch
            out[use, DOF[f"{side}_knee"]] = np.maximum(thigh_angle - phi, 0.0)

    def _arms_ik(self, out: np.ndarray, rng: np.random.Generator, dofs) -> None:
        """Half of the draws point each arm's wrist at a hand candidate on its side
        (look-up inverse kinematics on each draw's own torso)."""
        H, hands = self.height, self.det.hands
        shoulders, frames = _torso_frames(out, H)
        drawn = None
        if dofs is not None:
            drawn = np.zeros(out.shape[1], dtype=bool)
            drawn[np.asarray(dofs)] = True
        for side in ("l", "r"):
            d = _ARM_DOFS[side]
            if drawn is not None and not drawn[d].any():
                continue
            cfg, wrist, keys = arm_table(side)
            use = np.flatnonzero(rng.random(len(out)) < 0.5)
            if len(use) == 0:
                continue
            target = hands[rng.integers(len(hands), size=len(use))]
            lo, hi = np.empty(len(use), np.int64), np.empty(len(use), np.int64)
            # the extremity is on the hand, the wrist half a hand (0.04 H) nearer the
            # shoulder, and never beyond the arm's reach (0.332 H)
            found = _ik_cells(frames, shoulders[side], use, target, float(H), keys, lo, hi)
            if found == 0:
                continue
            # a configuration of the cell, uniformly (lo + u (hi - lo)), with noise on the drawn DoFs
            u = rng.random(found)
            cols = _ARM_COLS if drawn is None else _ARM_COLS[drawn[d]]
            noise = rng.normal(0, 0.05, (found, len(cols)))
            _ik_assign(out, use, lo, hi, u, cfg, d, cols, noise)

    def _draw(self, n: int, rng: np.random.Generator, base: np.ndarray | None = None) -> np.ndarray:
        H, det = self.height, self.det
        out = np.tile(neutral_state(H), (n, 1)) if base is None else np.array(base, dtype=np.float64)
        stand = standing_root_height(H)
        crouch = max(0.0, (H - (det.top - 0.0)) / H)      # how much lower than standing the top is
        straight = det.hands is not None and len(det.hands) and self.ik == "straight"
        heading = np.array(det.headings)[rng.integers(len(det.headings), size=n)]
        if straight:   # (the draws interleave with the arms' below: one call each, in order)
            yaw = heading + rng.normal(0, 0.15, n)
            root_z = min(stand, det.top - (H - stand)) + rng.normal(0, 0.02, n)
        else:          # consecutive normal draws in one call: the same numbers (loc + scale z, in order)
            z = rng.standard_normal((2, n))
            yaw = heading + (0.0 + 0.15 * z[0])
            root_z = min(stand, det.top - (H - stand)) + (0.0 + 0.02 * z[1])
        out[:, DOF["yaw"]] = yaw
        out[:, DOF["z"]] = np.clip(root_z, 0.25 * H, stand + 0.02)
        flex = np.clip(crouch * 2.5, 0.0, 1.0) * rng.random(n)
        out[:, DOF["torso_flex"]] = flex
        # root under the head, moved back by the lean
        back = np.sin(flex) * 0.295 * H
        if not straight:
            z = rng.standard_normal((2 + len(_REST_DOFS), n))
            out[:, DOF["x"]] = det.head[0] - np.cos(yaw) * back + (0.0 + 0.03 * z[0])
            out[:, DOF["y"]] = det.head[1] - np.sin(yaw) * back + (0.0 + 0.03 * z[1])
            rest = _REST_LOC[:, None] + _REST_SCALE[:, None] * z[2:]
            np.abs(rest, out=rest, where=_REST_ABS[:, None])
            out[:, _REST_DOFS] = rest.T
            return out
        out[:, DOF["x"]] = det.head[0] - np.cos(yaw) * back + rng.normal(0, 0.03, n)
        out[:, DOF["y"]] = det.head[1] - np.sin(yaw) * back + rng.normal(0, 0.03, n)
        for name in ("pitch", "roll", "torso_twist", "torso_lat", "neck_lat", "neck_flex"):
            out[:, DOF[name]] = rng.normal(0, 0.05, n)
        for side, s in (("l", 1), ("r", -1)):
            out[:, DOF[f"{side}_hip_flex"]] = rng.normal(0.05, 0.15, n)
            out[:, DOF[f"{side}_hip_abd"]] = rng.normal(0.0, 0.05, n)
            out[:, DOF[f"{side}_hip_rot"]] = rng.normal(0.0, 0.05, n)
            out[:, DOF[f"{side}_knee"]] = np.abs(rng.normal(0.1, 0.2, n))
            out[:, DOF[f"{side}_sh_flex"]] = rng.normal(0.0, 0.2, n)
            out[:, DOF[f"{side}_sh_abd"]] = np.abs(rng.normal(0.1, 0.2, n))
            out[:, DOF[f"{side}_sh_rot"]] = rng.normal(0.0, 0.2, n)
            out[:, DOF[f"{side}_elbow"]] = np.abs(rng.normal(0.2, 0.3, n))
            # straight arms toward the extremities (the earlier proposal)
            use = rng.random(n) < 0.5
            for k in np.flatnonzero(use):
                cy, sy = math.cos(yaw[k]), math.sin(yaw[k])
                shoulder = np.array([det.head[0], det.head[1], det.head[2] - 0.125 * H])
                shoulder[:2] += s * 0.104 * H * np.array([-sy, cy])
                target = det.hands[rng.integers(len(det.hands))]
                v = target - shoulder
                local = np.array([cy * v[0] + sy * v[1], -sy * v[0] + cy * v[1], v[2]])
                if s * local[1] < -0.05:
                    continue   # that extremity is on the other side
                f, a = _arm_angles(local, s)
                out[k, DOF[f"{side}_sh_flex"]] = f + rng.normal(0, 0.1)
                out[k, DOF[f"{side}_sh_abd"]] = a + rng.normal(0, 0.1)
                out[k, DOF[f"{side}_elbow"]] = abs(rng.normal(0.0, 0.15))
        return out
