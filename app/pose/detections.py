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
* **extremities**: surface voxels of the upper body farthest from the torso axis (hand
  candidates), each turned into shoulder angles that point a straight arm at it.

The importance function draws whole states: root under the head at the height the
blob's top allows, heading from the candidates, waist flexion from the lean, arms
toward extremities (or hanging), legs near standing, all with Gaussian noise and
inside the joint limits. Draws replace a fraction of the first layer's particles (the
mixture proposal of IAPF; the dynamics' particles stay, so tracking is not disturbed
when the detections are wrong).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.pose.model import DOF, LIMITS_HI, LIMITS_LO, neutral_state, standing_root_height

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
    c = np.asarray(centres)
    # the body axis: the median of the trunk band (raised arms do not move it much)
    trunk = c[(c[:, 2] > 0.50 * height) & (c[:, 2] < 0.70 * height)]
    axis = np.median(trunk[:, :2], axis=0) if len(trunk) >= 10 else np.median(c[:, :2], axis=0)
    # the head: the top of the blob near that axis (a hand above the head is not it)
    near_axis = c[np.hypot(c[:, 0] - axis[0], c[:, 1] - axis[1]) < 0.18]
    if len(near_axis) < 10:
        near_axis = c
    top = float(near_axis[:, 2].max())
    near_top = near_axis[near_axis[:, 2] >= top - 0.08]
    head = near_top.mean(axis=0)
    head[2] = top - 0.066 * height
    centroid = c.mean(axis=0)
    band = c[(c[:, 2] > top - 0.30 * height) & (c[:, 2] < top - 0.12 * height)]
    headings = []
    if velocity is not None and np.hypot(*velocity[:2]) > 0.3:
        headings.append(math.atan2(velocity[1], velocity[0]))
    if len(band) >= 10:
        xy = band[:, :2] - band[:, :2].mean(axis=0)
        evals, evecs = np.linalg.eigh(xy.T @ xy)
        major = evecs[:, 1]
        yaw = math.atan2(major[1], major[0]) - math.pi / 2    # the shoulder line's normal
        headings += [yaw, yaw + math.pi]
    if not headings:
        headings = list(np.linspace(-math.pi, math.pi, 4, endpoint=False))
    # extremities: upper-body voxels far from the vertical axis through the head
    upper = c[(c[:, 2] > top - 0.55 * height)]
    d = np.hypot(upper[:, 0] - head[0], upper[:, 1] - head[1])
    far = upper[d > 0.30]
    hands = None
    if len(far):
        order = np.argsort(-np.hypot(far[:, 0] - head[0], far[:, 1] - head[1]))
        hands = far[order[:min(len(order), 20)]]
    return Detections(head=head, top=top, centroid=centroid, headings=headings, hands=hands)


def _arm_angles(direction: np.ndarray, side: int):
    """Shoulder (flexion, abduction) that point a straight arm along ``direction`` (in the
    torso frame): the arm axis is ``(sin f cos a, s sin a, -cos f cos a)``."""
    d = direction / max(np.linalg.norm(direction), 1e-9)
    a = math.asin(max(-1.0, min(1.0, side * d[1])))
    f = math.atan2(d[0], -d[2])
    return f, a


class Importance:
    """The importance function ``q(y | detections)`` of one frame (callable
    ``(n, rng, base) -> (n, 27)``; ``base`` gives the DoFs the detections say nothing about)."""

    def __init__(self, det: Detections, height: float):
        self.det, self.height = det, height

    def __call__(self, n: int, rng: np.random.Generator, base: np.ndarray | None = None) -> np.ndarray:
        H, det = self.height, self.det
        out = np.tile(neutral_state(H), (n, 1)) if base is None else np.array(base, dtype=np.float64)
        stand = standing_root_height(H)
        crouch = max(0.0, (H - (det.top - 0.0)) / H)      # how much lower than standing the top is
        yaw = np.array(det.headings)[rng.integers(len(det.headings), size=n)] + rng.normal(0, 0.15, n)
        out[:, DOF["yaw"]] = yaw
        root_z = min(stand, det.top - (H - stand)) + rng.normal(0, 0.02, n)
        out[:, DOF["z"]] = np.clip(root_z, 0.25 * H, stand + 0.02)
        flex = np.clip(crouch * 2.5, 0.0, 1.0) * rng.random(n)
        out[:, DOF["torso_flex"]] = flex
        # root under the head, moved back by the lean
        back = np.sin(flex) * 0.295 * H
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
            if det.hands is not None and len(det.hands):
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
        return np.clip(out, LIMITS_LO, LIMITS_HI)
