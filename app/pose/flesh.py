"""The fleshed body model: voxel look-up tables of truncated cones per body part
(thesis §6.5.1.1, Eq. 6.11, Fig. 6.9).

Each body part is a union of truncated cones rigidly attached to one segment of the
kinematic model (:mod:`app.pose.model`). In the neutral pose the cones are discretised
once, on a regular grid of spacing ``density * voxel_size`` (the density factor
``delta = s_V_HBM / s_V`` of Eq. 6.26: 1 samples the model at the data's voxel size, 2
at twice it, so 8x fewer points), and the voxel centres are stored in segment-local
coordinates: the LUT. A particle's voxel model ``V_y^HBM`` is the LUT moved by the
forward kinematics of its state (Eq. 6.1); nothing is re-voxelised per particle.
Each LUT point also carries whether it lies on the part's surface (``V^S_Y``, used by
the surface score of Eq. 6.16).

Cones are elliptic (torso, pelvis, head; semi-axes in x and y) or round (limbs),
along the segment's z axis between ``z0`` and ``z1``, or round between two local
points (feet). Sizes are fractions of the stature, close to the simulator's bodies.
Limb cones start a little below their joint so that a neutral pose has almost no
double occupancy (Eq. 6.14) between a limb and the trunk.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.pose.model import AVERAGE, SEGMENT, SHIN, Proportions

__all__ = ["PARTS", "PART", "Flesh", "build_flesh", "LIMBS", "LIMB_JOINTS"]

#: ``(part, segment, [cones])``; a cone is ``("z", z0, z1, (ax0, ay0), (ax1, ay1), (cx, cy))``
#: (elliptic, along local z) or ``("ab", a, b, ra, rb)`` (round, between two points).
_PARTS = (
    ("torso", "torso", [("z", 0.045, 0.275, (0.056, 0.080), (0.058, 0.086), (-0.004, 0.0))]),
    ("pelvis", "pelvis", [("z", -0.070, 0.045, (0.058, 0.090), (0.056, 0.082), (-0.006, 0.0))]),
    ("head", "head", [("z", 0.030, 0.155, (0.054, 0.044), (0.050, 0.042), (0.012, 0.0))]),
    ("l_upper_arm", "l_upper_arm", [("z", -0.030, -0.186, (0.029, 0.029), (0.023, 0.023), (0.0, 0.0))]),
    ("l_forearm", "l_forearm", [("z", -0.010, -0.218, (0.022, 0.022), (0.015, 0.015), (0.0, 0.0))]),
    ("r_upper_arm", "r_upper_arm", [("z", -0.030, -0.186, (0.029, 0.029), (0.023, 0.023), (0.0, 0.0))]),
    ("r_forearm", "r_forearm", [("z", -0.010, -0.218, (0.022, 0.022), (0.015, 0.015), (0.0, 0.0))]),
    ("l_thigh", "l_thigh", [("z", -0.045, -0.240, (0.048, 0.048), (0.032, 0.032), (0.0, 0.0))]),
    ("l_shin", "l_shin", [("z", -0.010, -0.246, (0.031, 0.031), (0.022, 0.022), (0.0, 0.0)),
                          ("ab", (-0.012, 0.0, -0.265), (0.108, 0.0, -0.270), 0.020, 0.016)]),
    ("r_thigh", "r_thigh", [("z", -0.045, -0.240, (0.048, 0.048), (0.032, 0.032), (0.0, 0.0))]),
    ("r_shin", "r_shin", [("z", -0.010, -0.246, (0.031, 0.031), (0.022, 0.022), (0.0, 0.0)),
                          ("ab", (-0.012, 0.0, -0.265), (0.108, 0.0, -0.270), 0.020, 0.016)]),
)
PARTS = tuple(p[0] for p in _PARTS)
PART = {n: i for i, n in enumerate(PARTS)}
#: The limb units of DDM-APF (§7.4, Fig. 7.11: each limb missing, or with its upper
#: part only, or whole): ``unit -> (parts, state DoFs, parent unit)``. A whole limb
#: lost takes its end with it; an end part (forearm, shin) can be lost alone.
LIMBS = {
    "l_arm": (("l_upper_arm", "l_forearm"), ("l_sh_flex", "l_sh_abd", "l_sh_rot", "l_elbow"), None),
    "r_arm": (("r_upper_arm", "r_forearm"), ("r_sh_flex", "r_sh_abd", "r_sh_rot", "r_elbow"), None),
    "l_leg": (("l_thigh", "l_shin"), ("l_hip_flex", "l_hip_abd", "l_hip_rot", "l_knee"), None),
    "r_leg": (("r_thigh", "r_shin"), ("r_hip_flex", "r_hip_abd", "r_hip_rot", "r_knee"), None),
    "l_forearm": (("l_forearm",), ("l_elbow",), "l_arm"),
    "r_forearm": (("r_forearm",), ("r_elbow",), "r_arm"),
    "l_shin": (("l_shin",), ("l_knee",), "l_leg"),
    "r_shin": (("r_shin",), ("r_knee",), "r_leg"),
}
#: Contract joints a lost unit drops from ``active``.
LIMB_JOINTS = {"l_arm": ("l_elbow", "l_wrist"), "r_arm": ("r_elbow", "r_wrist"), "l_leg": ("l_knee", "l_ankle"),
               "r_leg": ("r_knee", "r_ankle"), "l_forearm": ("l_wrist",), "r_forearm": ("r_wrist",),
               "l_shin": ("l_ankle",), "r_shin": ("r_ankle",)}


def _inside(cones, p, H) -> np.ndarray:
    """Which local points ``p (N, 3)`` (metres) are inside the union of ``cones``."""
    out = np.zeros(len(p), dtype=bool)
    for c in cones:
        if c[0] == "z":
            _, z0, z1, a0, a1, ctr = c
            lo, hi = min(z0, z1) * H, max(z0, z1) * H
            t = (p[:, 2] - z0 * H) / ((z1 - z0) * H)
            ax = (a0[0] + t * (a1[0] - a0[0])) * H
            ay = (a0[1] + t * (a1[1] - a0[1])) * H
            dx, dy = p[:, 0] - ctr[0] * H, p[:, 1] - ctr[1] * H
            out |= (p[:, 2] >= lo) & (p[:, 2] <= hi) & ((dx / ax) ** 2 + (dy / ay) ** 2 <= 1.0)
        else:
            _, a, b, ra, rb = c
            a, b = np.asarray(a) * H, np.asarray(b) * H
            ab = b - a
            L2 = float(ab @ ab)
            t = ((p - a) @ ab) / L2
            r = (ra + np.clip(t, 0, 1) * (rb - ra)) * H
            d = np.linalg.norm(p - (a + np.clip(t, 0, 1)[:, None] * ab), axis=1)
            out |= (t >= 0) & (t <= 1) & (d <= r)
    return out


def _bounds(cones, H):
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for c in cones:
        if c[0] == "z":
            _, z0, z1, a0, a1, ctr = c
            r = max(a0[0], a0[1], a1[0], a1[1])
            lo = np.minimum(lo, np.array([ctr[0] - r, ctr[1] - r, min(z0, z1)]) * H)
            hi = np.maximum(hi, np.array([ctr[0] + r, ctr[1] + r, max(z0, z1)]) * H)
        else:
            _, a, b, ra, rb = c
            r = max(ra, rb)
            lo = np.minimum(lo, (np.minimum(a, b) - r) * H)
            hi = np.maximum(hi, (np.maximum(a, b) + r) * H)
    return lo, hi


@dataclass
class Flesh:
    """The LUT of every part (Eq. 6.11): local points ``(M, 3)`` with their segment,
    part and surface flag; ``spacing`` is the model's voxel size ``s_V_HBM``."""

    height: float
    proportions: Proportions   # the kinematic kernels' offsets for this person (app.pose.model)
    spacing: float
    points: np.ndarray     # (M, 3) segment-local, metres
    segment: np.ndarray    # (M,) int64
    part: np.ndarray       # (M,) int64
    surface: np.ndarray    # (M,) bool
    part_size: np.ndarray  # (Q,) |Y|
    surface_size: np.ndarray  # (Q,) |Y^S|

    @property
    def size(self) -> int:
        return len(self.points)


def _proportioned(segment: str, cones, proportions: Proportions):
    """A part's cones for a person of ``proportions``: stretched along the segment as its
    bone (the radii stay), a foot moved with the shin's end."""
    k = proportions.part_scale(segment)
    if k == 1.0:
        return cones
    out = []
    for c in cones:
        if c[0] == "z":
            out.append((c[0], c[1] * k, c[2] * k) + tuple(c[3:]))
        else:   # a foot: hangs from the ankle, the shin's end
            dz = -SHIN * (k - 1.0)
            out.append((c[0], (c[1][0], c[1][1], c[1][2] + dz), (c[2][0], c[2][1], c[2][2] + dz)) + tuple(c[3:]))
    return out


def build_flesh(height: float, voxel_size: float, density: float = 1.0,
                proportions: Proportions = AVERAGE) -> Flesh:
    """Discretise every part's cones in the neutral pose at spacing ``density * voxel_size``
    for a person of stature ``height`` and ``proportions``."""
    if not density >= 1.0:
        raise ValueError(f"density factor {density} must be >= 1 (Eq. 6.26)")
    h = float(voxel_size) * float(density)
    pts, seg, part, surf = [], [], [], []
    offsets = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0], [0, 0, h], [0, 0, -h]])
    for q, (name, segment, cones) in enumerate(_PARTS):
        cones = _proportioned(segment, cones, proportions)
        lo, hi = _bounds(cones, height)
        axes = [np.arange(lo[i] + h / 2, hi[i], h) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        inside = grid[_inside(cones, grid, height)]
        if len(inside) == 0:   # a part thinner than the spacing keeps its axis points
            inside = grid[np.argsort(np.linalg.norm(grid[:, :2], axis=1))[:1]]
        on_surface = np.zeros(len(inside), dtype=bool)
        for off in offsets:
            on_surface |= ~_inside(cones, inside + off, height)
        pts.append(inside)
        seg.append(np.full(len(inside), SEGMENT[segment]))
        part.append(np.full(len(inside), q))
        surf.append(on_surface)
    part = np.concatenate(part)
    surf = np.concatenate(surf)
    Q = len(_PARTS)
    return Flesh(height=float(height), proportions=proportions, spacing=h,
                 points=np.ascontiguousarray(np.concatenate(pts)),
                 segment=np.concatenate(seg).astype(np.int64), part=part.astype(np.int64), surface=surf,
                 part_size=np.bincount(part, minlength=Q).astype(np.float64),
                 surface_size=np.bincount(part[surf], minlength=Q).astype(np.float64))
