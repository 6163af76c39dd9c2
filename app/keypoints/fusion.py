"""2D body keypoints fused into the annealed particle filter (issue 23): a likelihood
term and detections for the importance function.

Fontmarty et al. (seed 001) fuse several cues into the APF's measurement function as a
product of Gaussian sub-likelihoods, ``p(z^c | x) ∝ exp(-D_c^2 / (2 sigma_c^2))``, one per
cue (§III-B; their 3D blob distance: ``D`` the mean Euclidean distance between the model's
hands and head and the triangulated skin blobs, ``sigma_3d = 0.15 m``), and draw part of
the first layer's particles from the detections through inverse kinematics (IAPF,
§III-A). Here the cue is a learned detector's keypoints in every camera
(:mod:`app.keypoints.detector`):

* **Reprojection term** (:func:`keypoint_penalty`): for each joint ``j`` that the
  detector saw in some camera, ``D_j`` is the confidence-weighted mean over those cameras
  of the distance between the model's joint and the keypoint's viewing ray, measured at
  the joint's depth (``|n_model - n_kp| * z``, ``n`` undistorted normalised image
  coordinates: metres, independent of the image's size), truncated at ``gate`` (a wrong
  detection, a left/right swap, costs at most ``gate`` and cannot pull a limb through
  the body); the term is ``sum_j D_j^2 / (2 sigma^2)``: Fontmarty's Gaussian per joint,
  multiplied over the joints. Keypoints below ``min_conf`` cost nothing. Only joints of
  the model parts being scored count (SHBM-APF scores partial models).
* **Triangulated joints** (:func:`triangulate`): each joint seen with confidence in two
  or more cameras, by linear least squares on the rays, the worst view dropped while
  the others disagree with it by more than ``gate``; the wrists feed the importance
  function's arm inverse kinematics (:class:`app.pose.detections.Importance`) as hand
  detections, as Fontmarty's triangulated hands do.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from app.messages import JOINTS
from app.pose.flesh import PART
from app.pose.model import AVERAGE, JOINT_LOCAL, JOINT_SEG, SEG_PARENT, SEGMENTS, Proportions, joints_subset

__all__ = ["PersonKeypoints", "person_keypoints", "keypoint_penalty", "triangulate", "keypoint_hands", "frame_keypoints", "JOINT_PART"]


def _joint_parts() -> np.ndarray:
    """The model part each joint moves with: its segment's, or for a joint at a segment's
    origin (elbow, knee, shoulder, hip, neck) the parent segment's."""
    out = np.empty(len(JOINTS), dtype=np.int64)
    for j in range(len(JOINTS)):
        s = int(JOINT_SEG[j])
        if not np.any(JOINT_LOCAL[j]) and SEG_PARENT[s] >= 0:
            s = int(SEG_PARENT[s])
        out[j] = PART[SEGMENTS[s][0]]
    return out


JOINT_PART = _joint_parts()
_ARM_ENDS = [JOINTS.index(n) for n in ("l_elbow", "l_wrist", "r_elbow", "r_wrist")]   # keypoint_hands' joints


@dataclass
class PersonKeypoints:
    """One person's keypoints in the cameras of a frame: ``R`` (C, 3, 3), ``t`` (C, 3) the
    cameras' poses, ``obs`` (C, 15, 2) undistorted normalised image coordinates, ``conf``
    (C, 15) the detector's confidence (0 where the camera gave none)."""

    R: np.ndarray
    t: np.ndarray
    obs: np.ndarray
    conf: np.ndarray

    @property
    def cameras(self) -> int:
        return len(self.R)

    def weights(self, min_conf: float) -> np.ndarray:
        return np.where(self.conf >= min_conf, self.conf, 0.0)


def person_keypoints(views) -> PersonKeypoints | None:
    """From ``[(camera, (15, 3) u, v, confidence in the camera's calibrated pixels)]``; None
    without a view."""
    views = [(cam, np.asarray(kp, dtype=np.float64)) for cam, kp in views]
    if not views:
        return None
    R = np.stack([cam.R for cam, _ in views])
    t = np.stack([cam.t for cam, _ in views])
    obs = np.stack([cam.undistort_points(kp[:, :2]) for cam, kp in views])
    conf = np.stack([np.clip(kp[:, 2], 0.0, 1.0) for _, kp in views])
    return PersonKeypoints(R, t, obs, conf)


@njit(cache=True, nogil=True)
def _penalty(joints, R, t, obs, w, gate, inv2s2, out):
    """``out[k] = inv2s2 * sum_j D_j^2`` of :func:`keypoint_penalty` for the joints
    ``(n, J, 3)`` and their keypoints ``obs (C, J, 2)``, weights ``w (C, J)``."""
    n, J = joints.shape[0], joints.shape[1]
    C = R.shape[0]
    for k in range(n):
        total = 0.0
        for j in range(J):
            num = 0.0
            den = 0.0
            for c in range(C):
                wc = w[c, j]
                if wc <= 0.0:
                    continue
                X = R[c, 0, 0] * joints[k, j, 0] + R[c, 0, 1] * joints[k, j, 1] + R[c, 0, 2] * joints[k, j, 2] + t[c, 0]
                Y = R[c, 1, 0] * joints[k, j, 0] + R[c, 1, 1] * joints[k, j, 1] + R[c, 1, 2] * joints[k, j, 2] + t[c, 1]
                Z = R[c, 2, 0] * joints[k, j, 0] + R[c, 2, 1] * joints[k, j, 1] + R[c, 2, 2] * joints[k, j, 2] + t[c, 2]
                if Z < 0.05:
                    e = gate
                else:
                    dx = X / Z - obs[c, j, 0]
                    dy = Y / Z - obs[c, j, 1]
                    e = min(np.sqrt(dx * dx + dy * dy) * Z, gate)
                num += wc * e
                den += wc
            if den > 0.0:
                d = num / den
                total += d * d
        out[k] = total * inv2s2


def keypoint_penalty(states: np.ndarray, height: float, person: PersonKeypoints, sigma: float, gate: float = 0.3,
                     min_conf: float = 0.5, active=None, proportions: Proportions = AVERAGE) -> np.ndarray:
    """``-log p(z^kp | x)`` up to a constant for states ``(n, 27)``: ``sum_j D_j^2 / (2 sigma^2)``
    (module docstring); ``active`` (parts) restricts it to the joints of the scored parts;
    ``proportions``: the person's (:class:`app.pose.model.Proportions`)."""
    states = np.asarray(states, dtype=np.float64).reshape(-1, 27)
    out = np.zeros(len(states))
    w = person.weights(min_conf)
    use = w.sum(axis=0) > 0
    if active is not None:
        use &= np.asarray(active, dtype=bool)[JOINT_PART]
    if not use.any() or not len(states):
        return out
    idx = np.flatnonzero(use)   # the model's joints are computed for these only (a partial model: the torso's)
    joints = joints_subset(states, height, idx, proportions=proportions)
    _penalty(joints, np.ascontiguousarray(person.R),
             np.ascontiguousarray(person.t), np.ascontiguousarray(person.obs[:, idx]), np.ascontiguousarray(w[:, idx]),
             float(gate), 0.5 / (sigma * sigma), out)
    return out


def _solve(R, t, obs, w):
    """Least-squares point closest to the rays of the views (weights ``w``)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for Rc, tc, o, wc in zip(R, t, obs, w):
        d = Rc.T @ np.array([o[0], o[1], 1.0])
        d /= np.linalg.norm(d)
        c = -Rc.T @ tc
        P = np.eye(3) - np.outer(d, d)
        A += wc * P
        b += wc * P @ c
    return np.linalg.solve(A, b)


def _ray_errors(point, R, t, obs):
    pc = np.einsum("cij,j->ci", R, point) + t
    z = np.maximum(pc[:, 2], 1e-6)
    return np.hypot(pc[:, 0] / z - obs[:, 0], pc[:, 1] / z - obs[:, 1]) * z, pc[:, 2] > 0.05


def triangulate(person: PersonKeypoints, min_conf: float = 0.5, gate: float = 0.15,
                min_views: int = 2, joints=None) -> tuple[np.ndarray, np.ndarray]:
    """``(points (15, 3), found (15,))``: each joint from the cameras that saw it with at
    least ``min_conf``; while the worst view is farther than ``gate`` (m, at the point's
    depth) from the point, it is dropped and the point solved again; found where at least
    ``min_views`` views agree. ``joints``: the indices to solve (default all; the others
    are not found)."""
    points = np.zeros((len(JOINTS), 3))
    found = np.zeros(len(JOINTS), dtype=bool)
    for j in range(len(JOINTS)) if joints is None else joints:
        views = np.flatnonzero(person.conf[:, j] >= min_conf)
        while len(views) >= min_views:
            R, t, o, w = person.R[views], person.t[views], person.obs[views, j], person.conf[views, j]
            try:
                p = _solve(R, t, o, w)
            except np.linalg.LinAlgError:
                break
            err, front = _ray_errors(p, R, t, o)
            err = np.where(front, err, np.inf)
            worst = int(np.argmax(err))
            if err[worst] <= gate:
                points[j], found[j] = p, True
                break
            views = np.delete(views, worst)
    return points, found


def keypoint_hands(person: PersonKeypoints, height: float, min_conf: float = 0.5) -> np.ndarray:
    """``(K, 3)`` hand points for the importance function's arm inverse kinematics (which
    puts the wrist half a hand, 0.04 H, nearer the shoulder than the hand it aims at):
    each triangulated wrist moved 0.04 H on along its forearm (from the triangulated
    elbow; straight down without one). Empty when no wrist was triangulated."""
    points, found = triangulate(person, min_conf, joints=_ARM_ENDS)
    out = []
    for side in ("l", "r"):
        w, e = JOINTS.index(f"{side}_wrist"), JOINTS.index(f"{side}_elbow")
        if not found[w]:
            continue
        d = points[w] - points[e] if found[e] else np.array([0.0, 0.0, -1.0])
        n = np.linalg.norm(d)
        out.append(points[w] + 0.04 * height * (d / n if n > 1e-6 else np.array([0.0, 0.0, -1.0])))
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def frame_keypoints(messages, calibration) -> dict:
    """``{track: PersonKeypoints}`` from a frame's :class:`~app.messages.Keypoints`
    messages (one per keypoints worker) and the run's calibration; cameras the
    calibration does not know are left out, as are views without a sure joint."""
    views: dict[int, list] = {}
    for msg in messages:
        for c, name in enumerate(msg.cameras):
            if name not in calibration.names:
                continue
            camera = calibration.camera(name)
            for k, tid in enumerate(np.asarray(msg.tracks).tolist()):
                kp = np.asarray(msg.points[k, c], dtype=np.float64)
                if kp[:, 2].max() > 0:
                    views.setdefault(int(tid), []).append((camera, kp))
    return {tid: person_keypoints(v) for tid, v in views.items()}
