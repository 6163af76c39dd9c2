"""Joint angles from a track sample: gait cycle, gestures, sitting, idle motion.

* **Gait.** Hip, knee and ankle follow the normative sagittal-plane curves of
  Winter's *Biomechanics and Motor Control of Human Movement* (keyframes every 10 % of
  the cycle, interpolated by a 5-harmonic Fourier series, so periodic and smooth), the
  right leg half a cycle behind the left. The amplitude grows with the walking speed;
  the arms swing against the legs, the pelvis rotates and tilts and the thorax
  counter-rotates. The stride length is measured on the person's own legs (how far
  the stance foot travels back while on the floor), so feet do not skate, and the
  root height is set each frame so that the lowest point of the feet touches the floor.
* **Gestures.** Keyframed arm/torso/head angles (wave, point, raise both arms, arms
  out, arm circle, explain, reach, stretch, bow, look around, shrug, hands on hips)
  blended over the base pose with the track's gesture weight.
* **Sitting.** The root moves from the standing spot onto the seat; the legs follow
  by two-link inverse kinematics to feet planted in front of the chair.

Every angle is clipped to :data:`app.simulation.body.LIMITS` (human joint limits).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.simulation.body import (DOF, BodyShape, Pose, clip_to_limits, forward_kinematics,
                                 neutral_pose, sole_height)
from app.simulation.gestures import GESTURES, LOW_GESTURES, gesture_angles
from app.simulation.motion import DT, SPOT_AHEAD, Track
from app.simulation.room import Chair

__all__ = ["Actor", "gait_angles", "GAIT_CURVES"]


def _fourier(keys_deg, harmonics: int = 5):
    """Periodic smooth curve through keyframes at 0, 10, ... 90 % of the cycle."""
    y = np.radians(np.asarray(keys_deg[:10], dtype=float))
    ph = np.arange(10) / 10.0
    coef = [(y.mean(), 0.0)]
    for h in range(1, harmonics):
        coef.append((2 * np.mean(y * np.cos(2 * np.pi * h * ph)), 2 * np.mean(y * np.sin(2 * np.pi * h * ph))))
    return tuple(coef)


def _eval(coef, phase):
    v = coef[0][0]
    for h in range(1, len(coef)):
        a, b = coef[h]
        v += a * math.cos(2 * math.pi * h * phase) + b * math.sin(2 * math.pi * h * phase)
    return v


#: Sagittal joint angles over the gait cycle (deg at 0, 10, ... 100 %; heel strike at 0).
GAIT_CURVES = {
    "hip": _fourier([30, 27, 20, 11, 2, -6, -9, 0, 18, 29, 30]),
    "knee": _fourier([4, 16, 17, 11, 6, 9, 38, 60, 45, 17, 4]),
    "ankle": _fourier([0, -6, 2, 8, 11, 6, -16, -8, 1, 2, 0]),
}


def gait_angles(phase: float):
    """(hip flexion, knee flexion, ankle dorsiflexion) in radians at a gait phase."""
    return (_eval(GAIT_CURVES["hip"], phase), _eval(GAIT_CURVES["knee"], phase),
            _eval(GAIT_CURVES["ankle"], phase))


def _smooth(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def _keyed(t: float, keys):
    """Interpolate ``[(time, value), ...]`` with smoothstep easing (clamped ends)."""
    if t <= keys[0][0]:
        return keys[0][1]
    for (t0, v0), (t1, v1) in zip(keys, keys[1:]):
        if t <= t1:
            return v0 + (v1 - v0) * _smooth((t - t0) / (t1 - t0))
    return keys[-1][1]


_GESTURE_NAMES = list(GESTURES)
#: What a person is doing, as the ground truth says (``activity``).
ACTIVITIES = ("walking", "standing", "gesturing", "sitting", "crouching")


def activity(sample: dict) -> str:
    """The activity of a track sample (:meth:`Actor.sample`): sitting (on a chair, also
    while talking with the hands), crouching (a crouch or a bend down under way),
    gesturing, walking, else standing (still, or turning in place)."""
    if sample["sit"] > 0.5:
        return "sitting"
    if sample["gesture"] >= 0 and sample["gweight"] > 0.3:
        return "crouching" if _GESTURE_NAMES[sample["gesture"]] in LOW_GESTURES else "gesturing"
    if sample["speed"] > 0.05:
        return "walking"
    return "standing"


def _leg_ik(shape: BodyShape, hip_local: np.ndarray, ankle_local: np.ndarray):
    """Two-link IK in the root frame (x forward, z up): hip flexion and knee flexion
    that put the ankle at ``ankle_local``, with the knee in front of the hip-ankle line,
    plus a small abduction for the lateral offset."""
    d = ankle_local - hip_local
    L1, L2 = shape.thigh, shape.shin
    sag = math.hypot(d[0], d[2])
    L = min(max(sag, abs(L1 - L2) + 1e-3), L1 + L2 - 1e-4)
    cos_knee = (L1 * L1 + L2 * L2 - L * L) / (2 * L1 * L2)
    knee = math.pi - math.acos(max(-1.0, min(1.0, cos_knee)))
    cos_a = (L1 * L1 + L * L - L2 * L2) / (2 * L1 * L)
    alpha = math.acos(max(-1.0, min(1.0, cos_a)))
    hip = math.atan2(d[0], -d[2]) + alpha
    abd = math.atan2(d[1], max(sag, 1e-6))
    return hip, knee, abd


@dataclass
class Actor:
    """One person of a scene: id, body, track and the idle-motion personality."""

    id: int
    shape: BodyShape
    track: Track
    chairs: tuple
    quirk: np.ndarray  # random phases / amplitudes for idle motion
    stride: float = 1.3

    def __post_init__(self):
        self.stride = self._measure_stride()
        # gait phase: cycles advance with distance walked (and with turning in place)
        cadence = 0.95  # cycles per second while turning in place / very slow walking
        rate = np.where(self.track.speed > 0, self.track.speed / (self._amplitude(self.track.speed) * self.stride
                                                                     + 1e-9), 0.0)
        rate = np.maximum(rate, np.where(np.abs(self.track.turn) > 0.05, cadence, 0.0))
        self.track.phase = np.concatenate([[self.quirk[0]], self.quirk[0] + np.cumsum(rate[:-1]) * DT])

    @staticmethod
    def _amplitude(speed):
        return np.clip(np.asarray(speed) / 1.25, 0.0, 1.1) * 0.85 + np.where(np.asarray(speed) > 0, 0.15, 0.0)

    def _measure_stride(self) -> float:
        """Stride length (m) at full amplitude: the stance foot's travel over the stance
        phase (heel strike to toe off, 0-60 %) divided by the stance fraction."""
        xs = []
        for ph in (0.0, 0.6):
            hip, knee, ankle = gait_angles(ph)
            x = self.shape.thigh * math.sin(hip) + self.shape.shin * math.sin(hip - knee)
            xs.append(x)
        return max(0.6, (xs[0] - xs[1]) / 0.6)

    # -- state at a time ------------------------------------------------------------
    def sample(self, t: float) -> dict:
        tr = self.track
        k, a = tr.index(t)
        b = k + 1
        lerp = lambda arr: float(arr[k] * (1 - a) + arr[b] * a)  # noqa: E731
        near = k if a < 0.5 else b
        return {
            "x": lerp(tr.x), "y": lerp(tr.y), "yaw": lerp(tr.yaw), "speed": lerp(tr.speed),
            "turn": lerp(tr.turn), "sit": lerp(tr.sit), "chair": int(tr.chair[near]),
            "gesture": int(tr.gesture[near]), "gtime": lerp(tr.gtime) if tr.gesture[k] == tr.gesture[b] else
            float(tr.gtime[near]), "gweight": lerp(tr.gweight), "present": bool(tr.present[near]),
            "phase": lerp(tr.phase), "t": t,
        }

    def pose(self, t: float) -> Pose:
        """The body pose at time ``t`` (root on the floor or the seat, angles in limits)."""
        s = self.sample(t)
        q = self.quirk
        pose = neutral_pose()
        a = pose.angles
        amp = float(self._amplitude(s["speed"])) if s["speed"] > 0 else 0.0
        if abs(s["turn"]) > 0.05:
            amp = max(amp, 0.2 * min(1.0, abs(s["turn"]) / 1.5))
        ph = s["phase"]
        # idle sway and breathing (also under everything else)
        tt = s["t"]
        a[DOF["torso_flex"]] += 0.03 + 0.015 * math.sin(2 * math.pi * 0.23 * tt + q[1])
        a[DOF["torso_lat"]] += 0.015 * math.sin(2 * math.pi * 0.17 * tt + q[2])
        a[DOF["neck_yaw"]] += (0.35 * math.sin(2 * math.pi * 0.06 * tt + q[3]) * (1 - amp)
                               + 0.08 * math.sin(2 * math.pi * 0.21 * tt + q[4]))
        a[DOF["neck_flex"]] += 0.08 + 0.05 * math.sin(2 * math.pi * 0.11 * tt + q[5])
        for side, off in (("l", 0.0), ("r", 0.5)):
            hip, knee, ankle = gait_angles((ph + off) % 1.0)
            a[DOF[f"{side}_hip_flex"]] = 0.02 * (1 - amp) + amp * hip
            a[DOF[f"{side}_knee"]] = 0.04 * (1 - amp) + amp * knee
            a[DOF[f"{side}_ankle"]] = amp * ankle
            a[DOF[f"{side}_hip_abd"]] = 0.02 + amp * 0.02 * math.cos(2 * math.pi * (ph + off))
            a[DOF[f"{side}_hip_rot"]] = 0.05
            # arms swing against the same-side leg
            a[DOF[f"{side}_sh_flex"]] = -amp * 0.85 * hip + 0.05
            a[DOF[f"{side}_elbow"]] = 0.2 + amp * (0.25 + 0.2 * max(0.0, -hip * 2.0))
        a[DOF["root_roll"]] = amp * 0.05 * math.sin(2 * math.pi * ph)
        a[DOF["root_pitch"]] = amp * 0.05
        a[DOF["torso_twist"]] = -amp * 0.12 * math.cos(2 * math.pi * ph)
        yaw = s["yaw"] + amp * 0.08 * math.cos(2 * math.pi * ph)
        pose.yaw = yaw
        pose.angles = a
        if s["sit"] > 0 and s["chair"] >= 0:
            pose = self._sitting(pose, s)
        self._gesture(pose.angles, s)
        pose.angles = clip_to_limits(pose.angles)
        if s["sit"] > 0 and s["chair"] >= 0:
            return pose
        pose.root = np.array([s["x"], s["y"], self.shape.standing_root_height])
        skel = forward_kinematics(self.shape, pose)
        pose.root[2] -= sole_height(self.shape, skel)
        return pose

    @staticmethod
    def _gesture(a: np.ndarray, s: dict) -> None:
        """Blend the current gesture's angles over the pose (in place)."""
        if s["gesture"] < 0 or s["gweight"] <= 0:
            return
        w = s["gweight"]
        for name, value in gesture_angles(_GESTURE_NAMES[s["gesture"]], s["gtime"]).items():
            i = DOF[name]
            if name.startswith(("neck", "torso")):  # on top of the idle motion
                a[i] += value * w
            else:
                a[i] = a[i] * (1 - w) + value * w

    def _sitting(self, pose: Pose, s: dict) -> Pose:
        """Blend from standing to seated: root onto the seat, legs by IK, torso leaning
        forward while the weight moves."""
        shape = self.shape
        chair: Chair = self.chairs[s["chair"]]
        b = _smooth(s["sit"])
        H = shape.height
        a = pose.angles
        fwd = np.array([math.cos(chair.yaw), math.sin(chair.yaw)])
        stand_xy = np.array([chair.x, chair.y]) + fwd * SPOT_AHEAD
        # shorter people sit further forward, so their thighs clear the seat's front edge
        x0 = min(0.14, max(0.02, 0.02 + (1.80 - H) * 0.45))
        seat_xy = np.array([chair.x, chair.y]) + fwd * x0
        stand_z = shape.standing_root_height - 0.01
        # the root high enough for the pelvis (buttocks) and the thighs to clear the seat,
        # also at its front edge, where a short person's thighs slope down to the knees
        r_hip, r_knee = 0.050 * H * shape.build, 0.032 * H * shape.build ** 0.5
        f = min(0.9, (chair.seat_half + 0.005 - x0) / (0.85 * shape.thigh))  # the seat edge along the thigh
        knee_top = shape.ankle_height + shape.shin
        hip_edge = (chair.seat_height + 0.02 + r_hip - (r_hip - r_knee) * f - knee_top * f) / (1.0 - f)
        seat_z = max(chair.seat_height + 0.012 + max(r_hip, 0.088 * H - shape.root_above_hips), hip_edge) \
            + shape.root_above_hips
        # the pelvis goes back and down together (a squat over the seat); the feet stay
        # planted in front of the seat until the hips are over it
        bx = _smooth(min(1.0, s["sit"] / 0.85))
        bz = _smooth(s["sit"])
        bf = _smooth(max(0.0, (s["sit"] - 0.55) / 0.45))
        xy = stand_xy + (seat_xy - stand_xy) * bx
        z = stand_z + (seat_z - stand_z) * bz
        pose.yaw = chair.yaw
        a[DOF["root_pitch"]] = 0.0
        a[DOF["root_roll"]] = 0.0
        lean = 0.55 * math.sin(math.pi * min(1.0, s["sit"])) + 0.1 * b
        a[DOF["torso_flex"]] = max(a[DOF["torso_flex"]], 0.0) * (1 - b) + lean
        pose.root = np.array([xy[0], xy[1], z])
        # feet: from under the standing hips to in front of the seat
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            hip_local = np.array([0.0, sgn * shape.hip_half_width, -shape.root_above_hips])
            # ankle target in the chair frame relative to the seat root
            stand_ankle = np.array([(stand_xy - seat_xy) @ fwd, sgn * shape.hip_half_width * 1.05,
                                    shape.ankle_height])
            # seated, the shins are vertical: the feet under the knees
            rise = seat_z - shape.root_above_hips - (shape.ankle_height + shape.shin)
            reach = math.sqrt(max(0.0, shape.thigh ** 2 - rise ** 2)) * 0.98
            seat_ankle = np.array([reach, sgn * shape.hip_half_width * 1.25, shape.ankle_height])
            ankle_chair = stand_ankle + (seat_ankle - stand_ankle) * bf
            # to the root frame: subtract the root's offset from the seat root along fwd
            root_off = (xy - seat_xy) @ fwd
            target = np.array([ankle_chair[0] - root_off, ankle_chair[1], ankle_chair[2] - z])
            hip, knee, abd = _leg_ik(shape, hip_local, target)
            a[DOF[f"{side}_hip_flex"]] = hip
            a[DOF[f"{side}_knee"]] = knee
            a[DOF[f"{side}_hip_abd"]] = abd
            a[DOF[f"{side}_hip_rot"]] = 0.05
            a[DOF[f"{side}_ankle"]] = knee - hip  # foot flat on the floor
            # hands come to rest on the thighs (gestures blend over this)
            a[DOF[f"{side}_sh_flex"]] = a[DOF[f"{side}_sh_flex"]] * (1 - b) + 0.30 * b
            a[DOF[f"{side}_elbow"]] = a[DOF[f"{side}_elbow"]] * (1 - b) + 1.30 * b
            a[DOF[f"{side}_sh_abd"]] = a[DOF[f"{side}_sh_abd"]] * (1 - b) + 0.10 * b
        pose.angles = a
        return pose
