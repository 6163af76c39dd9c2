"""Arm, torso and head gestures: keyframed joint angles and how far they reach.

Each gesture is a function of the time since it started giving target angles, blended
over the base pose with the track's gesture weight (:mod:`app.simulation.poses`).
:data:`REACH` says how far from the root, horizontally, the body reaches during the
gesture - overall (``high``: walls are full height) and below 1 m (``low``: tables,
chairs and the sideboard are lower) - measured with the body model on the largest
person the simulator makes (1.95 m, build 1.2); the choreographer scales it to each
person and keeps people and walls that far away (:mod:`app.simulation.motion`).
"""
from __future__ import annotations

import math

__all__ = ["GESTURES", "REACH", "STAND_REACH", "REFERENCE_HEIGHT", "gesture_angles", "measure_reach"]

#: Gesture name -> duration (s). The last three move the whole body: crouching down
#: (to the floor and up again), bending down with straight legs, reaching up on tiptoe.
GESTURES = {
    "wave": 3.0, "point": 2.4, "raise_both": 2.6, "arms_out": 2.8, "circle": 3.2, "explain": 3.5,
    "reach": 2.4, "stretch": 3.0, "bow": 2.4, "look_around": 3.0, "shrug": 1.8, "hands_on_hips": 2.5,
    "crouch": 4.0, "bend_down": 3.0, "reach_up": 3.0,
}
GESTURE_IDS = {name: i for i, name in enumerate(GESTURES)}
#: The gestures wandering people pick from (the built-in scenes' choice, kept so their
#: recordings stay the same); random scenes script the others (app.simulation.random_scene).
WANDER_GESTURES = tuple(GESTURES)[:12]
#: Gestures that bring the body low (the ground truth calls the person "crouching").
LOW_GESTURES = ("crouch", "bend_down")

#: Horizontal reach (m) from the root during each gesture: (overall, below 1 m), for the
#: reference body (see :func:`measure_reach`, which recomputes this table).
REACH = {
    "wave": (1.0, 0.71), "point": (0.91, 0.5), "raise_both": (0.87, 0.27), "arms_out": (1.04, 0.6),
    "circle": (1.03, 0.76), "explain": (0.76, 0.61), "reach": (0.93, 0.75), "stretch": (0.9, 0.27),
    "bow": (0.67, 0.39), "look_around": (0.33, 0.33), "shrug": (0.73, 0.59), "hands_on_hips": (0.53, 0.42),
    "crouch": (0.78, 0.78), "bend_down": (0.76, 0.68), "reach_up": (0.87, 0.57),
}
#: Horizontal reach of the reference body standing at rest.
STAND_REACH = 0.335
REFERENCE_HEIGHT, REFERENCE_BUILD = 1.95, 1.2


def gesture_angles(name: str, t: float) -> dict:
    """Target angles of a gesture ``t`` seconds after it started."""
    dur = GESTURES[name]
    w = 2 * math.pi
    if name == "wave":
        return {"r_sh_abd": 1.75, "r_sh_flex": 0.35, "r_sh_rot": -1.35,
                "r_elbow": 1.25 + 0.38 * math.sin(w * 1.8 * t), "neck_yaw": -0.15, "torso_lat": 0.05}
    if name == "point":
        return {"l_sh_flex": 1.45, "l_sh_abd": 0.35, "l_sh_rot": 0.0, "l_elbow": 0.08,
                "neck_yaw": 0.35, "torso_twist": 0.15}
    if name == "raise_both":
        return {"l_sh_flex": 2.85, "r_sh_flex": 2.85, "l_sh_abd": 0.25, "r_sh_abd": 0.25,
                "l_elbow": 0.15, "r_elbow": 0.15, "neck_flex": -0.3}
    if name == "arms_out":
        return {"l_sh_abd": 1.55, "r_sh_abd": 1.55, "l_sh_flex": 0.05, "r_sh_flex": 0.05,
                "l_elbow": 0.05, "r_elbow": 0.05, "l_sh_rot": 0.0, "r_sh_rot": 0.0}
    if name == "circle":
        a = w * t / dur * 1.5
        return {"r_sh_flex": 1.4 + 0.9 * math.sin(a), "r_sh_abd": 0.9 + 0.7 * math.cos(a), "r_elbow": 0.15,
                "r_sh_rot": 0.0}
    if name == "explain":
        s = math.sin(w * 1.1 * t)
        return {"l_sh_flex": 0.45 + 0.12 * s, "r_sh_flex": 0.45 - 0.12 * s, "l_sh_abd": 0.3, "r_sh_abd": 0.3,
                "l_elbow": 1.45 + 0.2 * math.sin(w * 0.8 * t), "r_elbow": 1.35 - 0.2 * s,
                "l_sh_rot": -0.35, "r_sh_rot": -0.35, "neck_yaw": 0.3 * math.sin(w * 0.3 * t)}
    if name == "reach":
        return {"l_sh_flex": 1.35, "r_sh_flex": 1.35, "l_sh_abd": 0.1, "r_sh_abd": 0.1, "l_elbow": 0.1,
                "r_elbow": 0.1, "torso_flex": 0.35, "neck_flex": -0.2}
    if name == "stretch":
        lean = 0.3 * math.sin(math.pi * min(1.0, t / dur))
        return {"l_sh_flex": 2.9, "r_sh_flex": 2.9, "l_sh_abd": 0.4, "r_sh_abd": 0.4, "l_elbow": 0.3,
                "r_elbow": 0.3, "torso_lat": lean, "torso_flex": -0.12}
    if name == "bow":
        return {"torso_flex": 0.75, "neck_flex": 0.3, "l_sh_flex": 0.35, "r_sh_flex": 0.35, "l_elbow": 0.3,
                "r_elbow": 0.3, "l_hip_flex": 0.15, "r_hip_flex": 0.15}
    if name == "look_around":
        return {"neck_yaw": 1.0 * math.sin(w * t / dur), "torso_twist": 0.3 * math.sin(w * t / dur),
                "neck_flex": -0.1}
    if name == "shrug":
        return {"l_sh_abd": 0.35, "r_sh_abd": 0.35, "l_elbow": 1.4, "r_elbow": 1.4, "l_sh_rot": -0.45,
                "r_sh_rot": -0.45, "l_sh_flex": 0.25, "r_sh_flex": 0.25, "neck_lat": 0.2}
    if name == "hands_on_hips":
        return {"l_sh_abd": 0.75, "r_sh_abd": 0.75, "l_elbow": 1.75, "r_elbow": 1.75, "l_sh_rot": 0.9,
                "r_sh_rot": 0.9, "l_sh_flex": -0.35, "r_sh_flex": -0.35}
    if name == "crouch":   # a deep squat, hands to the floor in front, feet flat (ankle = knee - hip)
        return {"l_hip_flex": 1.75, "r_hip_flex": 1.75, "l_knee": 2.15, "r_knee": 2.15, "l_ankle": 0.40,
                "r_ankle": 0.40, "l_hip_abd": 0.25, "r_hip_abd": 0.25, "torso_flex": 0.45, "neck_flex": 0.1,
                "l_sh_flex": 0.9, "r_sh_flex": 0.75, "l_sh_abd": 0.15, "r_sh_abd": 0.15, "l_elbow": 0.35,
                "r_elbow": 0.5}
    if name == "bend_down":   # picking something up with straight legs
        return {"torso_flex": 1.05, "l_hip_flex": 0.35, "r_hip_flex": 0.35, "l_knee": 0.25, "r_knee": 0.25,
                "l_ankle": -0.1, "r_ankle": -0.1, "neck_flex": -0.25, "l_sh_flex": 1.0, "r_sh_flex": 1.1,
                "l_elbow": 0.2, "r_elbow": 0.25, "l_sh_abd": 0.1, "r_sh_abd": 0.1}
    if name == "reach_up":   # one arm up to a high shelf, on tiptoe, looking up
        return {"r_sh_flex": 2.95, "r_sh_abd": 0.3, "r_elbow": 0.1, "r_sh_rot": 0.0, "l_sh_flex": 0.4,
                "l_elbow": 0.5, "neck_flex": -0.45, "torso_lat": -0.08, "l_ankle": -0.45, "r_ankle": -0.45}
    raise KeyError(name)



def measure_reach(samples: int = 30, spacing: float = 0.02) -> dict:
    """Recompute :data:`REACH` with the body model (reference body, blend weights from a
    quarter to one, as the gesture ramps in and out)."""
    import numpy as np

    from app.simulation.body import (DOF, BodyShape, body_primitives, clip_to_limits, forward_kinematics,
                                     neutral_pose)
    from app.simulation.checks import surface_points

    shape = BodyShape(height=REFERENCE_HEIGHT, build=REFERENCE_BUILD, belly=1.3)
    out = {}
    for name, dur in GESTURES.items():
        hi = lo = 0.0
        for t, w in [(t, w) for t in np.linspace(0.0, dur, samples) for w in (0.25, 0.5, 0.75, 1.0)]:
            pose = neutral_pose()
            a = pose.angles
            for n, v in gesture_angles(name, float(t)).items():
                i = DOF[n]
                a[i] = a[i] + w * v if n.startswith(("neck", "torso")) else (1 - w) * a[i] + w * v
            pose.angles = clip_to_limits(a)
            pose.root = np.array([0.0, 0.0, shape.standing_root_height])
            kinds, rows, _ = body_primitives(shape, forward_kinematics(shape, pose))
            pts = surface_points(kinds, rows, spacing)
            d = np.hypot(pts[:, 0], pts[:, 1])
            hi, lo = max(hi, float(d.max())), max(lo, float(d[pts[:, 2] < 1.0].max()))
        out[name] = (round(hi, 2), round(lo, 2))
    return out
