"""A joint-angle skeleton over the contract's 15 joints, fitted to joint positions.

The exports that carry angles (BVH) need a hierarchy, constant offsets (the person's
limb lengths) and per-frame local rotations whose forward kinematics give back the
joints. The body model is the thesis's articulated model (§6.1, Eq. 6.1: the position
of a joint is its parent's position plus the product of the rotations down the chain
applied to a constant offset). Its segments, and the joints that fix each segment's
frame, are:

==============  ==========  =============================================================
BVH joint       sits at     segment frame (x forward, y to the person's left, z up at rest)
==============  ==========  =============================================================
pelvis (root)   pelvis      y along r_hip -> l_hip, z along the hip midpoint -> pelvis
spine           pelvis      z along pelvis -> neck, y along r_shoulder -> l_shoulder
neck            neck        swing of the torso frame taking the rest head direction to
                            neck -> head (no twist information: twist follows the torso)
l/r_shoulder    shoulder    z along elbow -> shoulder, y the elbow's hinge axis
                            (normal of the shoulder-elbow-wrist plane)
l/r_elbow       elbow       z along wrist -> elbow, y the same hinge axis
l/r_hip         hip         z along knee -> hip, y the knee's hinge axis
l/r_knee        knee        z along ankle -> knee, y the same hinge axis
head, l/r_wrist, l/r_ankle  end joints: the frame of their parent (zero local rotation)
==============  ==========  =============================================================

A segment's offsets are the medians over the track's frames of its children's
positions in its frame; for a rigid body (the simulator's, the pose model's) they are
constant, so forward kinematics reproduces every joint up to the rounding of the input.
Where a limb is straight its hinge axis is undefined and the last defined axis is kept
(only the bone's roll depends on it, never a joint position). A segment whose joints are
inactive (a dropped limb) holds its last local rotation; before its first active frame it
stays at rest. Everything here is z-up world coordinates in metres; :mod:`app.export.bvh`
converts to the file's axes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.messages import JOINTS

__all__ = ["BONES", "Bone", "SkeletonFit", "fit_skeleton", "forward_kinematics", "rotation_about"]

J = {name: n for n, name in enumerate(JOINTS)}
HINGE_MIN_SIN = 0.1      # limb bent less than ~6 deg: the hinge axis is not measurable
ROOT_UP_MIN = 0.02       # m: pelvis above the hip midpoint by less -> root up axis from the neck


@dataclass(frozen=True)
class Bone:
    """A BVH joint: its name, parent, the contract joint it sits at, and how its frame is measured."""

    name: str
    parent: str | None
    at: str
    kind: str            # "root", "torso", "swing", "limb", "end"
    end_site: tuple = ()  # end joints: the End Site offset as a fraction of the parent segment's length


BONES = (
    Bone("pelvis", None, "pelvis", "root"),
    Bone("spine", "pelvis", "pelvis", "torso"),
    Bone("neck", "spine", "neck", "swing"),
    Bone("head", "neck", "head", "end", (0.0, 0.0, 0.6)),
    Bone("l_shoulder", "spine", "l_shoulder", "limb"),
    Bone("l_elbow", "l_shoulder", "l_elbow", "limb"),
    Bone("l_wrist", "l_elbow", "l_wrist", "end", (0.0, 0.0, -0.3)),
    Bone("r_shoulder", "spine", "r_shoulder", "limb"),
    Bone("r_elbow", "r_shoulder", "r_elbow", "limb"),
    Bone("r_wrist", "r_elbow", "r_wrist", "end", (0.0, 0.0, -0.3)),
    Bone("l_hip", "pelvis", "l_hip", "limb"),
    Bone("l_knee", "l_hip", "l_knee", "limb"),
    Bone("l_ankle", "l_knee", "l_ankle", "end", (0.45, 0.0, -0.1)),
    Bone("r_hip", "pelvis", "r_hip", "limb"),
    Bone("r_knee", "r_hip", "r_knee", "limb"),
    Bone("r_ankle", "r_knee", "r_ankle", "end", (0.45, 0.0, -0.1)),
)
BONE_INDEX = {b.name: n for n, b in enumerate(BONES)}

# limb bone -> (the joint its segment ends at, the limb's three joints for the hinge, +1 arms / -1 legs)
_LIMBS = {
    "l_shoulder": ("l_elbow", ("l_shoulder", "l_elbow", "l_wrist"), 1.0),
    "l_elbow": ("l_wrist", ("l_shoulder", "l_elbow", "l_wrist"), 1.0),
    "r_shoulder": ("r_elbow", ("r_shoulder", "r_elbow", "r_wrist"), 1.0),
    "r_elbow": ("r_wrist", ("r_shoulder", "r_elbow", "r_wrist"), 1.0),
    "l_hip": ("l_knee", ("l_hip", "l_knee", "l_ankle"), -1.0),
    "l_knee": ("l_ankle", ("l_hip", "l_knee", "l_ankle"), -1.0),
    "r_hip": ("r_knee", ("r_hip", "r_knee", "r_ankle"), -1.0),
    "r_knee": ("r_ankle", ("r_hip", "r_knee", "r_ankle"), -1.0),
}


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / n


def _frame_zy(z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rotation matrices (F, 3, 3) with columns x, y, z from a z direction and a y hint."""
    z = _unit(z)
    y = _unit(y - np.sum(y * z, axis=-1, keepdims=True) * z)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def rotation_about(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: rotations (F, 3, 3) of ``angle`` about unit ``axis`` (F, 3)."""
    axis = np.asarray(axis, float)
    angle = np.asarray(angle, float)[..., None, None]
    k = np.zeros(axis.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -axis[..., 2], axis[..., 1], -axis[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = axis[..., 2], -axis[..., 1], axis[..., 0]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotations (F, 3, 3) taking unit ``a`` (3,) to unit ``b`` (F, 3)."""
    a = np.broadcast_to(a, b.shape)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    c = np.sum(a * b, axis=-1)
    perp = np.cross(a, np.array([1.0, 0.0, 0.0]))
    perp = np.where(np.linalg.norm(perp, axis=-1, keepdims=True) < 1e-6, np.cross(a, [0.0, 1.0, 0.0]), perp)
    axis = np.where((s < 1e-12)[:, None], perp, axis)
    return rotation_about(_unit(axis), np.arctan2(s, c))


def _ffill(values: np.ndarray, valid: np.ndarray, rest) -> np.ndarray:
    """``values`` with each invalid row replaced by the last valid one (``rest`` before any)."""
    idx = np.where(valid, np.arange(len(valid)), -1)
    idx = np.maximum.accumulate(idx) if len(idx) else idx
    out = values[np.maximum(idx, 0)].copy()
    out[idx < 0] = rest
    return out


def _median(v: np.ndarray, valid: np.ndarray, default) -> np.ndarray:
    v = v[valid]
    v = v[np.all(np.isfinite(v.reshape(len(v), -1)), axis=1)] if len(v) else v
    return np.median(v, axis=0) if len(v) else np.asarray(default, float)


@dataclass
class SkeletonFit:
    """A fitted skeleton: per bone its offset (3,) in the parent's frame (the root's is
    zero), per frame the root position (F, 3) and every bone's local rotation (F, B, 3, 3),
    all in z-up world axes."""

    offsets: np.ndarray        # (B, 3)
    end_sites: dict            # bone name -> End Site offset (3,)
    root: np.ndarray           # (F, 3)
    local: np.ndarray          # (F, B, 3, 3)


def fit_skeleton(joints: np.ndarray, active: np.ndarray) -> SkeletonFit:
    """Fit offsets and local rotations to one track's joints (F, 15, 3) and active flags (F, 15)."""
    P = np.asarray(joints, float)
    A = np.asarray(active, bool) & np.all(np.isfinite(P), axis=-1)
    F = len(P)
    p = {name: P[:, J[name]] for name in JOINTS}
    a = {name: A[:, J[name]] for name in JOINTS}
    eye = np.eye(3)

    # measured world frames of the segments that have a frame of their own
    mid_hip = 0.5 * (p["l_hip"] + p["r_hip"])
    up = p["pelvis"] - mid_hip
    ok_root = a["pelvis"] & a["l_hip"] & a["r_hip"]
    if ok_root.any() and np.median(np.linalg.norm(up[ok_root], axis=-1)) < ROOT_UP_MIN:
        up = p["neck"] - mid_hip   # pelvis on the hip line: the spine gives the up axis
        ok_root = ok_root & a["neck"]
    measured = {"pelvis": (_frame_zy(up, p["l_hip"] - p["r_hip"]), ok_root),
                "spine": (_frame_zy(p["neck"] - p["pelvis"], p["l_shoulder"] - p["r_shoulder"]),
                          a["pelvis"] & a["neck"] & a["l_shoulder"] & a["r_shoulder"])}
    hinges = {}
    for bone, (end, (j0, j1, j2), sign) in _LIMBS.items():
        if (j0, j1, j2) not in hinges:
            u, f = p[j1] - p[j0], p[j2] - p[j1]
            n = sign * np.cross(f, u)
            with np.errstate(invalid="ignore", divide="ignore"):
                sin = np.linalg.norm(n, axis=-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(f, axis=-1))
            ok = a[j0] & a[j1] & a[j2] & (sin > HINGE_MIN_SIN)
            hinges[(j0, j1, j2)] = (_unit(n), ok)
        n, ok = hinges[(j0, j1, j2)]
        start = BONES[BONE_INDEX[bone]].at
        hint = _ffill(n, ok, np.nan)
        valid = a[start] & a[end]
        z = p[start] - p[end]
        # no hinge measured yet: the world y axis only fixes the roll until one is
        hint = np.where(np.isnan(hint), np.array([0.0, 1.0, 0.0]), hint)
        parallel = np.abs(np.sum(_unit(z) * hint, axis=-1)) > 0.999
        hint[parallel] = [1.0, 0.0, 0.0]
        measured[bone] = (_frame_zy(z, hint), valid)

    # offsets of each bone in its parent's measured frame
    B = len(BONES)
    offsets = np.zeros((B, 3))
    end_sites = {}
    lengths = {}
    for i, bone in enumerate(BONES):
        if bone.parent is None:
            continue
        parent = BONES[BONE_INDEX[bone.parent]]
        if bone.kind == "torso":
            continue  # the spine starts at the pelvis
        if parent.kind == "swing":   # the head: along the rest head direction
            continue
        R, ok = measured[parent.name]
        d = np.einsum("fji,fj->fi", R, p[bone.at] - p[parent.at])
        offsets[i] = _median(d, ok & a[bone.at] & a[parent.at], [0.0, 0.0, 0.0])
        lengths[bone.name] = float(np.linalg.norm(offsets[i]))
    # the head segment: direction in the torso frame, rest direction and length
    R_t, ok_t = measured["spine"]
    d_head = np.einsum("fji,fj->fi", R_t, _unit(p["head"] - p["neck"]))
    ok_head = ok_t & a["neck"] & a["head"]
    rest_head = _unit(_median(d_head, ok_head, [0.0, 0.0, 1.0]))
    head_len = float(_median(np.linalg.norm(p["head"] - p["neck"], axis=-1), ok_head, 0.2))
    offsets[BONE_INDEX["head"]] = head_len * rest_head
    lengths["head"] = head_len
    for bone in BONES:
        if bone.kind == "end":
            end_sites[bone.name] = np.asarray(bone.end_site, float) * max(lengths.get(bone.name, 0.1), 0.05)

    # local rotations: parent's forward-kinematics frame^T times the measured frame; held when not measured
    local = np.broadcast_to(eye, (F, B, 3, 3)).copy()
    world = np.broadcast_to(eye, (F, B, 3, 3)).copy()
    for i, bone in enumerate(BONES):
        if bone.kind == "root":
            R, ok = measured["pelvis"]
            local[:, i] = _ffill(R, ok, eye)
            world[:, i] = local[:, i]
            continue
        Wp = world[:, BONE_INDEX[bone.parent]]
        if bone.kind == "end":
            loc = np.broadcast_to(eye, (F, 3, 3))
        elif bone.kind == "swing":
            d = np.einsum("fji,fj->fi", Wp, _unit(p["head"] - p["neck"]))
            ok = ok_head.copy()
            ok[ok] &= np.all(np.isfinite(d[ok]), axis=-1)
            rot = np.broadcast_to(eye, (F, 3, 3)).copy()
            if ok.any():
                rot[ok] = _swing(rest_head, _unit(d[ok]))
            loc = _ffill(rot, ok, eye)
        else:
            R, ok = measured[bone.name]
            loc = _ffill(np.einsum("fji,fjk->fik", Wp, np.where(ok[:, None, None], R, eye)), ok, eye)
        local[:, i] = loc
        world[:, i] = Wp @ loc
    root = _ffill(p["pelvis"], a["pelvis"], _median(p["pelvis"], a["pelvis"], [0.0, 0.0, 0.0]))
    return SkeletonFit(offsets, end_sites, root, local)


def forward_kinematics(offsets: np.ndarray, root: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Positions (F, B, 3) of every bone from root positions (F, 3) and local rotations
    (F, B, 3, 3) (Eq. 6.1); bones in :data:`BONES` order, parents before children."""
    F, B = local.shape[:2]
    pos = np.zeros((F, B, 3))
    world = np.zeros((F, B, 3, 3))
    for i, bone in enumerate(BONES):
        if bone.parent is None:
            pos[:, i] = root + offsets[i]
            world[:, i] = local[:, i]
        else:
            k = BONE_INDEX[bone.parent]
            pos[:, i] = pos[:, k] + world[:, k] @ offsets[i]
            world[:, i] = world[:, k] @ local[:, i]
    return pos
