"""Synthetic marker detections from true joints, as the thesis generates them (§6.6.1,
Fig. 6.12), so the marker filter can be swept over detector qualities (Fig. 6.13).

For every view: (1) every marker (the 15 contract joints of every person) is projected;
(2) those hidden by a body are removed: the bodies are fleshed out with capsules (torso,
head, upper arms, forearms, thighs, shins; the thesis uses super-ellipsoids) and a marker
is hidden when the line from the camera to it crosses a capsule that is not one of its
own joint's segments (its own limb carries it, on the side it is seen from); markers
outside the image are removed too; (3) a marker is detected with probability ``DR``
(detection rate); (4) ``U[0, 2 FP]`` false detections (rounded) are drawn uniformly in the
rectangle tightly surrounding the people's projected markers; (5) zero-mean Gaussian
noise of variance ``sigma2`` (px^2, per coordinate) is added to every detection.

Detections are returned in each camera's observed pixels (with its lens distortion), as a
detector would report them, with which marker each came from (-1 for a false one) for
scoring the detector itself.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.messages import JOINTS

__all__ = ["DetectorModel", "synthetic_detections", "visible_markers", "CAPSULES"]

J = {name: n for n, name in enumerate(JOINTS)}
#: (joint a, joint b, radius as a fraction of the stature); the head is a sphere (a = b)
CAPSULES = (
    ("pelvis", "neck", 0.085), ("head", "head", 0.060),
    ("l_shoulder", "l_elbow", 0.030), ("l_elbow", "l_wrist", 0.025),
    ("r_shoulder", "r_elbow", 0.030), ("r_elbow", "r_wrist", 0.025),
    ("l_hip", "l_knee", 0.045), ("l_knee", "l_ankle", 0.032),
    ("r_hip", "r_knee", 0.045), ("r_knee", "r_ankle", 0.032),
)
_CAP_A = np.array([J[a] for a, _, _ in CAPSULES])
_CAP_B = np.array([J[b] for _, b, _ in CAPSULES])
_CAP_R = np.array([r for _, _, r in CAPSULES])
# the capsules each joint belongs to (its own flesh: never hides it)
_TORSO_JOINTS = ("pelvis", "neck", "l_shoulder", "r_shoulder", "l_hip", "r_hip")
_OWN = np.zeros((len(JOINTS), len(CAPSULES)), bool)
for _c, (_a, _b, _) in enumerate(CAPSULES):
    _OWN[J[_a], _c] = _OWN[J[_b], _c] = True
    if _c == 0:
        for _j in _TORSO_JOINTS:
            _OWN[J[_j], _c] = True
_OWN[J["neck"], 1] = _OWN[J["head"], 0] = True


@dataclass(frozen=True)
class DetectorModel:
    """A marker detector's quality (§6.4.1.1): detection rate, mean false detections per
    image, position error variance (px^2 per coordinate)."""

    dr: float = 0.9
    fp: float = 20.0
    sigma2: float = 4.0


def _segment_distance(p0, p1, q0, q1) -> np.ndarray:
    """Shortest distances between segments ``p0-p1`` and ``q0-q1`` (broadcast, (..., 3))."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.sum(d1 * d1, axis=-1)
    e = np.sum(d2 * d2, axis=-1)
    f = np.sum(d2 * r, axis=-1)
    c = np.sum(d1 * r, axis=-1)
    b = np.sum(d1 * d2, axis=-1)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = np.where(e > 1e-12, (b * s + f) / e, 0.0)
        s = np.where(t < 0.0, np.where(a > 1e-12, np.clip(-c / a, 0.0, 1.0), 0.0), s)
        s = np.where(t > 1.0, np.where(a > 1e-12, np.clip((b - c) / a, 0.0, 1.0), 0.0), s)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p0 + d1 * s[..., None] - (q0 + d2 * t[..., None]), axis=-1)


def visible_markers(people_joints: np.ndarray, statures, camera) -> np.ndarray:
    """``(P, 15)``: which markers of ``P`` people (joints (P, 15, 3)) ``camera`` sees."""
    X = np.asarray(people_joints, float).reshape(-1, len(JOINTS), 3)
    P = len(X)
    inside = camera.sees(X.reshape(-1, 3)).reshape(P, len(JOINTS))
    o = camera.centre
    a = X[:, _CAP_A].reshape(-1, 3)                    # (P*S, 3) every person's capsules
    b = X[:, _CAP_B].reshape(-1, 3)
    radius = (np.asarray(statures, float)[:, None] * _CAP_R[None]).reshape(-1)
    owner = np.repeat(np.arange(P), len(CAPSULES))
    d = _segment_distance(o[None, None], X.reshape(-1, 3)[:, None], a[None], b[None])   # (P*15, P*S)
    own = np.zeros((P * len(JOINTS), P * len(CAPSULES)), bool)
    for p in range(P):
        own[p * len(JOINTS):(p + 1) * len(JOINTS), owner == p] = _OWN
    hidden = np.any((d < radius[None]) & ~own, axis=1).reshape(P, len(JOINTS))
    return inside & ~hidden


def synthetic_detections(people_joints: np.ndarray, statures, cameras, detector: DetectorModel,
                         rng: np.random.Generator) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per camera: detections (Q, 2) in observed pixels and the index ``p * 15 + joint``
    of the marker each came from (-1: a false detection)."""
    X = np.asarray(people_joints, float).reshape(-1, len(JOINTS), 3)
    out, labels = [], []
    for cam in cameras:
        seen = visible_markers(X, statures, cam) if len(X) else np.zeros((0, len(JOINTS)), bool)
        uv = cam.project(X.reshape(-1, 3)).reshape(len(X), len(JOINTS), 2) if len(X) else np.zeros((0, 15, 2))
        idx = np.flatnonzero(seen.reshape(-1) & (rng.random(seen.size) < detector.dr))
        pts = uv.reshape(-1, 2)[idx]
        n_false = int(round(rng.uniform(0.0, 2.0 * detector.fp))) if len(X) else 0
        if n_false:
            on = uv.reshape(-1, 2)[seen.reshape(-1)] if seen.any() else uv.reshape(-1, 2)
            lo = np.clip(np.nanmin(on, axis=0), 0, [cam.width - 1, cam.height - 1])
            hi = np.clip(np.nanmax(on, axis=0), 0, [cam.width - 1, cam.height - 1])
            false = lo + rng.random((n_false, 2)) * np.maximum(hi - lo, 1.0)
            pts = np.concatenate([pts, false])
            idx = np.concatenate([idx, -np.ones(n_false, np.int64)])
        if detector.sigma2 > 0 and len(pts):
            pts = pts + rng.normal(0.0, np.sqrt(detector.sigma2), pts.shape)
        order = rng.permutation(len(pts))     # a detector reports no marker identities
        out.append(pts[order])
        labels.append(idx[order])
    return out, labels
