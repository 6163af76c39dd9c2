"""BVH (Biovision Hierarchy) export: one file per track, for Blender, MotionBuilder, Maya.

The hierarchy is :data:`app.export.skeleton.BONES` (root = pelvis with 6 channels,
every other joint 3 rotation channels), the offsets are the person's limb lengths fitted
by :func:`app.export.skeleton.fit_skeleton`, the frame time is ``1 / fps`` of the
recording. Rotation channels are ``Zrotation Xrotation Yrotation`` (R = Rz Rx Ry,
degrees, applied to column vectors in the parent's frame, as in the BVH convention).

Axes: BVH files are y-up, so the world's z-up coordinates (CONTRACT) are written as
``(x, z, -y)`` (a rotation of -90 degrees about x), in metres. Blender's BVH importer
with its defaults (forward -Z, up Y, scale 1) puts every joint back at its world
position in the room. The rest pose (all angles zero) is the person standing, arms down.

Time: the files of one run share its timeline (``span``): each starts at the run's first
frame and ends at its last, the person holding their first pose until they appear and
their last pose after they leave. Blender imports every file at its frame 1, so people
who came in at different times stay in step.
"""
from __future__ import annotations

import numpy as np

from app.export.poses import TrackPoses
from app.export.skeleton import BONES, fit_skeleton

__all__ = ["EULER_ORDER", "TO_BVH", "write_bvh", "bvh_text", "euler_zxy", "matrix_zxy"]

EULER_ORDER = "ZXY"
CHANNELS = "Zrotation Xrotation Yrotation"
#: world (z-up) -> BVH (y-up): (x, y, z) -> (x, z, -y)
TO_BVH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
DIGITS = 6


def euler_zxy(R: np.ndarray) -> np.ndarray:
    """Angles (..., 3) in degrees, (z, x, y), with R = Rz(z) Rx(x) Ry(y)."""
    R = np.asarray(R, float)
    x = np.arctan2(R[..., 2, 1], np.hypot(R[..., 2, 0], R[..., 2, 2]))
    y = np.arctan2(-R[..., 2, 0], R[..., 2, 2])
    z = np.arctan2(-R[..., 0, 1], R[..., 1, 1])
    lock = np.hypot(R[..., 2, 0], R[..., 2, 2]) < 1e-9   # x = +-90 deg: put everything in z
    y = np.where(lock, 0.0, y)
    z = np.where(lock, np.arctan2(R[..., 1, 0], R[..., 0, 0]), z)
    return np.degrees(np.stack([z, x, y], axis=-1))


def _rot(axis: str, deg: np.ndarray) -> np.ndarray:
    a = np.radians(np.asarray(deg, float))
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    rows = {"X": [[i, o, o], [o, c, -s], [o, s, c]],
            "Y": [[c, o, s], [o, i, o], [-s, o, c]],
            "Z": [[c, -s, o], [s, c, o], [o, o, i]]}[axis]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))


def matrix_zxy(angles: np.ndarray) -> np.ndarray:
    """The inverse of :func:`euler_zxy`: R = Rz Rx Ry from (z, x, y) degrees."""
    angles = np.asarray(angles, float)
    return _rot("Z", angles[..., 0]) @ _rot("X", angles[..., 1]) @ _rot("Y", angles[..., 2])


def _num(v: float) -> str:
    s = f"{v:.{DIGITS}f}"
    return "0.000000" if s == "-0.000000" else s


def bvh_text(track: TrackPoses, fps: float, span: tuple[int, int] | None = None) -> str:
    """The BVH file of one track; ``span``: the run's frames ``(first, last)``, which the
    motion covers (the pose held before the track's first frame and after its last)."""
    fit = fit_skeleton(track.joints, track.active)   # fitted on the track's own frames
    if span is not None:
        before, after = track.first - span[0], span[1] - (track.first + len(track.joints) - 1)
        if before < 0 or after < 0:
            raise ValueError(f"track {track.track} reaches outside frames {span[0]}..{span[1]}")
        fit.root = np.pad(fit.root, ((before, after), (0, 0)), mode="edge")
        fit.local = np.pad(fit.local, ((before, after), (0, 0), (0, 0), (0, 0)), mode="edge")
    offsets = fit.offsets @ TO_BVH.T
    children = {b.name: [c for c in BONES if c.parent == b.name] for b in BONES}
    lines = ["HIERARCHY"]

    def emit(n: int, bone, depth: int) -> None:
        pad = "  " * depth
        if bone.parent is None:
            lines.append(f"{pad}ROOT {bone.name}")
        else:
            lines.append(f"{pad}JOINT {bone.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(_num(v) for v in offsets[n])}")
        if bone.parent is None:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {CHANNELS}")
        else:
            lines.append(f"{pad}  CHANNELS 3 {CHANNELS}")
        if bone.kind == "end":
            site = TO_BVH @ fit.end_sites[bone.name]
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {' '.join(_num(v) for v in site)}",
                          f"{pad}  }}"])
        for child in children[bone.name]:
            emit(BONES.index(child), child, depth + 1)
        lines.append(f"{pad}}}")

    emit(0, BONES[0], 0)
    F = len(fit.root)
    local = TO_BVH @ fit.local @ TO_BVH.T            # (F, B, 3, 3) conjugated into BVH axes
    angles = euler_zxy(local)                        # (F, B, 3)
    root = fit.root @ TO_BVH.T                       # (F, 3)
    motion = np.concatenate([root, angles.reshape(F, -1)], axis=1)
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / fps:.8f}"]
    lines += [" ".join(_num(v) for v in row) for row in motion]
    return "\n".join(lines) + "\n"


def write_bvh(path, track: TrackPoses, fps: float, span: tuple[int, int] | None = None) -> None:
    from app.files import write_atomic
    write_atomic(path, bvh_text(track, fps, span))
