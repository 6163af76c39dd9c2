"""Articulated human bodies: skeleton, human joint limits, forward kinematics, flesh.

The kinematic model is the thesis's HBM (§6.3.4, Table 6.1): a root at the pelvis with
a world position and heading, 3 DoF at the waist (torso flexion, lateral bend, twist),
3 at each shoulder, 1 at each elbow, 3 at each hip, 1 at each knee, plus the neck (2 DoF
in the thesis, here 3 so the head can turn) and 1 DoF ankles for the feet of the gait.
Segment lengths are fractions of the stature (the thesis sets them "proportionally to
the height of the subject as suggested in [DBT03]"; the fractions here are
Drillis & Contini's anthropometric table). Forward kinematics chains rotation
matrices (Eq. 6.1 with the exponential maps written as rotations about the local axes).

Local frames: x forward, y to the person's left, z up. Positive angles: flexion brings
a limb forward (knee flexion backwards), abduction away from the midline, rotation
internal (limbs) or to the left (neck yaw).

The body is fleshed out with round cones (limbs, neck, feet, shoulder girdle) and
ellipsoids (head, chest, abdomen, pelvis), see :mod:`app.simulation.geometry`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.messages import JOINTS
from app.simulation.geometry import CONE, ELLIPSOID, cone_row, ellipsoid_row

__all__ = [
    "DOFS", "LIMITS", "DOF", "Pose", "BodyShape", "Skeleton", "FrameBodies",
    "forward_kinematics", "body_primitives", "random_shape", "within_limits", "clip_to_limits",
    "neutral_pose", "MAT_SKIN", "MAT_HEAD", "MAT_SHIRT", "MAT_TROUSERS", "MAT_SHOES",
    "MAT_PELVIS", "MAT_SLEEVE",
]

#: Degrees of freedom of the pose (besides the root position and heading).
DOFS = (
    "torso_flex", "torso_lat", "torso_twist",
    "neck_flex", "neck_lat", "neck_yaw",
    "l_sh_flex", "l_sh_abd", "l_sh_rot", "l_elbow",
    "r_sh_flex", "r_sh_abd", "r_sh_rot", "r_elbow",
    "l_hip_flex", "l_hip_abd", "l_hip_rot", "l_knee", "l_ankle",
    "r_hip_flex", "r_hip_abd", "r_hip_rot", "r_knee", "r_ankle",
    "root_pitch", "root_roll",
)
DOF = {name: i for i, name in enumerate(DOFS)}

#: Human joint limits (radians), inside the thesis's Table 6.1 ranges where it has them.
LIMITS = {
    "torso_flex": (-0.30, 1.20), "torso_lat": (-0.45, 0.45), "torso_twist": (-math.pi / 8, math.pi / 8),
    "neck_flex": (-0.70, 0.90), "neck_lat": (-0.60, 0.60), "neck_yaw": (-1.20, 1.20),
    "l_sh_flex": (-0.90, 3.10), "l_sh_abd": (-0.30, 2.90), "l_sh_rot": (-1.50, 1.50), "l_elbow": (0.0, 2.50),
    "r_sh_flex": (-0.90, 3.10), "r_sh_abd": (-0.30, 2.90), "r_sh_rot": (-1.50, 1.50), "r_elbow": (0.0, 2.50),
    "l_hip_flex": (-0.45, 2.00), "l_hip_abd": (-0.35, 0.70), "l_hip_rot": (-0.60, 0.60),
    "l_knee": (0.0, 2.40), "l_ankle": (-0.70, 0.45),
    "r_hip_flex": (-0.45, 2.00), "r_hip_abd": (-0.35, 0.70), "r_hip_rot": (-0.60, 0.60),
    "r_knee": (0.0, 2.40), "r_ankle": (-0.70, 0.45),
    "root_pitch": (-0.35, 0.35), "root_roll": (-0.20, 0.20),
}
LIMITS_LO = np.array([LIMITS[d][0] for d in DOFS])
LIMITS_HI = np.array([LIMITS[d][1] for d in DOFS])

#: A person's colour palette: slot order of :meth:`BodyShape.palette`.
PALETTE = ("skin", "hair", "shirt", "trousers", "shoes", "belt")
SLOT_SKIN, SLOT_HAIR, SLOT_SHIRT, SLOT_TROUSERS, SLOT_SHOES, SLOT_BELT = range(6)
#: Body materials of the primitives. Most take one palette slot; the head splits into
#: hair and face, the pelvis into shirt, belt and trousers (see app.simulation.render).
MAT_SKIN, MAT_SHIRT, MAT_TROUSERS, MAT_SHOES = SLOT_SKIN, SLOT_SHIRT, SLOT_TROUSERS, SLOT_SHOES
MAT_HEAD, MAT_PELVIS, MAT_SLEEVE = 6, 7, 8


@dataclass
class Pose:
    """Root (pelvis joint) position, heading (yaw about z, 0 = facing +x) and the DoFs."""

    root: np.ndarray
    yaw: float
    angles: np.ndarray = field(default_factory=lambda: np.zeros(len(DOFS)))

    def get(self, name: str) -> float:
        return float(self.angles[DOF[name]])

    def set(self, name: str, value: float) -> None:
        self.angles[DOF[name]] = value


def neutral_pose() -> Pose:
    """Standing at rest, arms hanging slightly away from the body."""
    p = Pose(np.zeros(3), 0.0)
    for side in "lr":
        p.set(f"{side}_sh_abd", 0.10)
        p.set(f"{side}_elbow", 0.15)
        p.set(f"{side}_knee", 0.04)
        p.set(f"{side}_hip_flex", 0.02)
    return p


def within_limits(angles: np.ndarray, tol: float = 1e-9) -> bool:
    a = np.asarray(angles)
    return bool(np.all(a >= LIMITS_LO - tol) and np.all(a <= LIMITS_HI + tol))


def clip_to_limits(angles: np.ndarray) -> np.ndarray:
    return np.clip(angles, LIMITS_LO, LIMITS_HI)


# -- shape and appearance --------------------------------------------------------------

_SKIN = [(0.96, 0.80, 0.69), (0.92, 0.74, 0.60), (0.84, 0.64, 0.50), (0.72, 0.52, 0.38),
         (0.55, 0.38, 0.26), (0.40, 0.27, 0.19)]
_HAIR = [(0.08, 0.06, 0.05), (0.22, 0.14, 0.08), (0.40, 0.27, 0.15), (0.70, 0.55, 0.32),
         (0.55, 0.54, 0.52), (0.30, 0.12, 0.06)]
_SHIRT = [(0.12, 0.18, 0.38), (0.88, 0.88, 0.86), (0.45, 0.46, 0.48), (0.10, 0.10, 0.11),
          (0.62, 0.12, 0.13), (0.18, 0.42, 0.25), (0.52, 0.70, 0.86), (0.78, 0.66, 0.45),
          (0.42, 0.13, 0.25), (0.86, 0.70, 0.18), (0.90, 0.45, 0.20), (0.30, 0.55, 0.60)]
_TROUSERS = [(0.14, 0.20, 0.36), (0.08, 0.08, 0.09), (0.30, 0.31, 0.33), (0.60, 0.52, 0.38),
             (0.28, 0.20, 0.14), (0.22, 0.28, 0.45)]
_SHOES = [(0.06, 0.06, 0.06), (0.25, 0.15, 0.09), (0.85, 0.85, 0.85), (0.18, 0.18, 0.22)]


@dataclass(frozen=True)
class BodyShape:
    """One person's body: stature, build and appearance (colours RGB 0-1)."""

    height: float = 1.75
    build: float = 1.0           # width factor, 0.85 (slim) .. 1.2 (heavy)
    belly: float = 1.0           # abdomen depth factor
    skin: tuple = _SKIN[1]
    hair: tuple = _HAIR[1]
    shirt: tuple = _SHIRT[0]
    trousers: tuple = _TROUSERS[0]
    shoes: tuple = _SHOES[0]
    belt: tuple = (0.10, 0.08, 0.06)
    short_sleeves: bool = False
    stripes: float = 0.0         # stripe period of the shirt (m), 0 = plain
    hair_front: float = 0.45     # hairline height at the forehead (unit head sphere)
    hair_back: float = -0.35     # hairline height at the nape (lower = longer hair)
    legs: float = 1.0            # proportions: leg, arm and trunk lengths against the average
    arms: float = 1.0            # (Drillis & Contini's) fractions; see proportioned()
    torso: float = 1.0

    # segment lengths (m), Drillis & Contini fractions of the stature
    @property
    def thigh(self) -> float:
        return 0.240 * self.height * self.legs

    @property
    def shin(self) -> float:
        return 0.246 * self.height * self.legs

    @property
    def ankle_height(self) -> float:
        return 0.039 * self.height

    @property
    def hip_half_width(self) -> float:
        return 0.052 * self.height * self.build ** 0.5

    @property
    def root_above_hips(self) -> float:
        return 0.025 * self.height

    @property
    def spine(self) -> float:
        return 0.295 * self.height * self.torso

    @property
    def shoulder_half_width(self) -> float:
        return 0.104 * self.height * self.build ** 0.5

    @property
    def upper_arm(self) -> float:
        return 0.186 * self.height * self.arms

    @property
    def forearm(self) -> float:
        return 0.146 * self.height * self.arms

    @property
    def hand(self) -> float:
        return 0.072 * self.height * self.arms

    @property
    def foot(self) -> float:
        return 0.152 * self.height

    @property
    def standing_root_height(self) -> float:
        """Height of the root (pelvis joint) standing straight."""
        return self.ankle_height + self.shin + self.thigh + self.root_above_hips

    def palette(self) -> np.ndarray:
        """``(8, 3)`` albedo per body material slot (skin, hair, shirt, trousers, shoes, belt)."""
        out = np.zeros((8, 3))
        for i, name in enumerate(PALETTE):
            out[i] = getattr(self, name)
        return out

    def colours(self) -> dict:
        """Clothing and skin colours, RGB 0-255 (the ground truth's optional field)."""
        return {k: [int(round(255 * c)) for c in getattr(self, k)] for k in ("shirt", "trousers", "skin", "hair")}


def trunk_for_legs(legs: float) -> float:
    """The trunk factor that keeps the stature when the legs are ``legs`` times the
    average's: shin + thigh (0.486 of the stature) and spine (0.295) share 0.781 of it."""
    return (0.781 - 0.486 * legs) / 0.295


def random_shape(rng: np.random.Generator, height: float | None = None) -> BodyShape:
    """A plausible random person: stature 1.55-1.95 m, build, clothing and hair."""
    h = float(np.clip(rng.normal(1.74, 0.1), 1.55, 1.95)) if height is None else float(height)
    build = float(np.clip(rng.normal(1.0, 0.08), 0.86, 1.2))
    long_hair = rng.random() < 0.3
    pick = lambda seq: seq[int(rng.integers(len(seq)))]  # noqa: E731
    return BodyShape(
        height=h,
        build=build,
        belly=float(np.clip(rng.normal(1.0, 0.08) * (build ** 1.5), 0.85, 1.35)),
        skin=pick(_SKIN), hair=pick(_HAIR), shirt=pick(_SHIRT), trousers=pick(_TROUSERS),
        shoes=pick(_SHOES),
        short_sleeves=bool(rng.random() < 0.35),
        stripes=float(rng.choice([0.0, 0.0, 0.0, 0.045, 0.06])),
        hair_front=float(rng.uniform(0.35, 0.55)),
        hair_back=float(rng.uniform(-0.85, -0.65) if long_hair else rng.uniform(-0.4, -0.2)),
    )


# -- kinematics ----------------------------------------------------------------------

def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Skeleton:
    """Forward kinematics result: the 15 contract joints (in :data:`JOINTS` order) and
    the frames and extra points the flesh needs."""

    joints: np.ndarray            # (15, 3)
    frames: dict                  # name -> 3x3 rotation (columns: local axes in world)
    points: dict                  # name -> (3,) extra points (heels, toes, hand tips, head)

    def joint(self, name: str) -> np.ndarray:
        return self.joints[JOINTS.index(name)]


def forward_kinematics(shape: BodyShape, pose: Pose) -> Skeleton:
    """Joint positions of a pose (Eq. 6.1: a product of rotations down each chain)."""
    H = shape.height
    a = pose.angles
    g = lambda n: a[DOF[n]]  # noqa: E731
    root = np.asarray(pose.root, dtype=np.float64)
    R_root = _rz(pose.yaw) @ _ry(g("root_pitch")) @ _rx(g("root_roll"))
    R_torso = R_root @ _rz(g("torso_twist")) @ _rx(g("torso_lat")) @ _ry(g("torso_flex"))
    neck = root + R_torso @ np.array([0.0, 0.0, shape.spine])
    R_head = R_torso @ _rz(g("neck_yaw")) @ _rx(g("neck_lat")) @ _ry(g("neck_flex"))
    head = neck + R_head @ np.array([0.012 * H, 0.0, 0.090 * H])
    J = {"pelvis": root, "neck": neck, "head": head}
    frames = {"root": R_root, "torso": R_torso, "head": R_head}
    points = {}
    for side, s in (("l", 1.0), ("r", -1.0)):
        sh = neck + R_torso @ np.array([-0.005 * H, s * shape.shoulder_half_width, -0.035 * H])
        R_ua = R_torso @ _ry(-g(f"{side}_sh_flex")) @ _rx(s * g(f"{side}_sh_abd")) @ _rz(-s * g(f"{side}_sh_rot"))
        elbow = sh + R_ua @ np.array([0.0, 0.0, -shape.upper_arm])
        R_fa = R_ua @ _ry(-g(f"{side}_elbow"))
        wrist = elbow + R_fa @ np.array([0.0, 0.0, -shape.forearm])
        points[f"{side}_hand_tip"] = wrist + R_fa @ np.array([0.0, 0.0, -shape.hand])
        hip = root + R_root @ np.array([0.0, s * shape.hip_half_width, -shape.root_above_hips])
        R_th = R_root @ _ry(-g(f"{side}_hip_flex")) @ _rx(s * g(f"{side}_hip_abd")) @ _rz(s * g(f"{side}_hip_rot"))
        knee = hip + R_th @ np.array([0.0, 0.0, -shape.thigh])
        R_sh = R_th @ _ry(g(f"{side}_knee"))
        ankle = knee + R_sh @ np.array([0.0, 0.0, -shape.shin])
        R_ft = R_sh @ _ry(-g(f"{side}_ankle"))
        points[f"{side}_heel"] = ankle + R_ft @ np.array([-0.012 * H, 0.0, -0.019 * H])
        points[f"{side}_toe"] = ankle + R_ft @ np.array([0.108 * H, 0.0, -0.024 * H])
        frames[f"{side}_upper_arm"] = R_ua
        frames[f"{side}_forearm"] = R_fa
        frames[f"{side}_thigh"] = R_th
        frames[f"{side}_foot"] = R_ft
        J.update({f"{side}_shoulder": sh, f"{side}_elbow": elbow, f"{side}_wrist": wrist,
                  f"{side}_hip": hip, f"{side}_knee": knee, f"{side}_ankle": ankle})
    joints = np.array([J[n] for n in JOINTS])
    return Skeleton(joints, frames, points)


def sole_height(shape: BodyShape, skel: Skeleton) -> float:
    """Height of the lowest point of the feet (heel and toe spheres)."""
    H = shape.height
    r_heel, r_toe = 0.020 * H, 0.016 * H
    return min(min(skel.points[f"{s}_heel"][2] - r_heel, skel.points[f"{s}_toe"][2] - r_toe) for s in "lr")


# -- flesh ------------------------------------------------------------------------------

def body_primitives(shape: BodyShape, skel: Skeleton):
    """The body's primitives: ``(kinds (M,), rows (M, 16), materials (M,))``."""
    H, b = shape.height, shape.build
    j = {n: skel.joints[i] for i, n in enumerate(JOINTS)}
    Rr, Rt, Rh = skel.frames["root"], skel.frames["torso"], skel.frames["head"]
    head_scale = (H / 1.75) ** 0.5
    kinds, rows, mats = [], [], []

    def cone(a, c, ra, rb, mat):
        kinds.append(CONE)
        rows.append(cone_row(a, c, ra, rb))
        mats.append(mat)

    def ell(c, R, s, mat):
        kinds.append(ELLIPSOID)
        rows.append(ellipsoid_row(c, R, s))
        mats.append(mat)

    root, neck = j["pelvis"], j["neck"]
    # head, nose, neck
    ell(j["head"], Rh, np.array([0.100, 0.080, 0.115]) * head_scale, MAT_HEAD)
    nose = j["head"] + Rh @ (np.array([0.098, 0.0, -0.012]) * head_scale)
    cone(nose, nose + Rh @ np.array([0.012, 0.0, -0.012]), 0.016, 0.013, MAT_SKIN)
    cone(neck - Rt @ np.array([0.0, 0.0, 0.02 * H]), j["head"] - Rh @ np.array([0.02, 0.0, 0.06 * head_scale]),
         0.029 * H * b ** 0.5, 0.027 * H, MAT_SKIN)
    # trunk: chest, abdomen (torso frame), pelvis (root frame), shoulder girdle
    spine = shape.spine
    ell(root + Rt @ np.array([-0.004 * H, 0.0, 0.66 * spine]), Rt,
        np.array([0.060 * H * b, 0.092 * H * b, 0.112 * H]), MAT_SHIRT)
    ell(root + Rt @ np.array([0.0, 0.0, 0.30 * spine]), Rt,
        np.array([0.058 * H * b * shape.belly, 0.082 * H * b, 0.105 * H]), MAT_SHIRT)
    ell(root + Rr @ np.array([-0.008 * H, 0.0, -0.022 * H]), Rr,
        np.array([0.061 * H * b, 0.098 * H * b, 0.066 * H]), MAT_PELVIS)
    cone(j["l_shoulder"] + Rt @ np.array([0.0, -0.02 * H, 0.004 * H]),
         j["r_shoulder"] + Rt @ np.array([0.0, 0.02 * H, 0.004 * H]), 0.030 * H * b ** 0.5, 0.030 * H * b ** 0.5,
         MAT_SHIRT)
    lower_arm = MAT_SKIN if shape.short_sleeves else MAT_SLEEVE
    for s in "lr":
        cone(j[f"{s}_shoulder"], j[f"{s}_elbow"], 0.031 * H * b ** 0.5, 0.023 * H * b ** 0.5, MAT_SLEEVE)
        cone(j[f"{s}_elbow"], j[f"{s}_wrist"], 0.022 * H * b ** 0.5, 0.0175 * H, lower_arm)
        cone(j[f"{s}_wrist"], skel.points[f"{s}_hand_tip"], 0.0185 * H, 0.015 * H, MAT_SKIN)
        cone(j[f"{s}_hip"], j[f"{s}_knee"], 0.050 * H * b, 0.032 * H * b ** 0.5, MAT_TROUSERS)
        cone(j[f"{s}_knee"], j[f"{s}_ankle"], 0.031 * H * b ** 0.5, 0.022 * H, MAT_TROUSERS)
        cone(skel.points[f"{s}_heel"], skel.points[f"{s}_toe"], 0.020 * H, 0.016 * H, MAT_SHOES)
    return (np.array(kinds, dtype=np.int64), np.array(rows, dtype=np.float64),
            np.array(mats, dtype=np.int64))


def body_centroid(kinds: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Volume-weighted centroid of the primitives (overlaps counted twice; a close
    approximation of the body volume's centroid)."""
    total, acc = 0.0, np.zeros(3)
    for k, p in zip(kinds, rows):
        if k == CONE:
            a, c, ra, rb = p[0:3], p[3:6], p[6], p[7]
            L = float(np.linalg.norm(c - a))
            vf = math.pi * L * (ra * ra + ra * rb + rb * rb) / 3.0
            if vf > 0:
                frac = (ra * ra + 2 * ra * rb + 3 * rb * rb) / (4 * (ra * ra + ra * rb + rb * rb))
            else:
                frac = 0.5
            va, vb = 2.0 / 3.0 * math.pi * ra ** 3, 2.0 / 3.0 * math.pi * rb ** 3
            acc += vf * (a + frac * (c - a)) + va * a + vb * c
            total += vf + va + vb
        else:
            v = 4.0 / 3.0 * math.pi * float(np.prod(p[12:15]))
            acc += v * p[0:3]
            total += v
    return acc / total


@dataclass
class FrameBodies:
    """Every visible body of one frame, flattened for the renderer."""

    ids: np.ndarray       # (P,) person ids
    kinds: np.ndarray     # (M,) primitive kinds
    prims: np.ndarray     # (M, 16) primitive rows
    owner: np.ndarray     # (M,) index into ids
    material: np.ndarray  # (M,) body material
    palette: np.ndarray   # (P, 8, 3) albedo per person and material slot
    hair: np.ndarray      # (P, 2) hairline front / back
    stripes: np.ndarray   # (P,) shirt stripe period (0 = plain)

    @classmethod
    def build(cls, people) -> "FrameBodies":
        """From ``[(id, shape, kinds, rows, materials), ...]``."""
        if not people:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 16)),
                       np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 8, 3)),
                       np.zeros((0, 2)), np.zeros(0))
        ids, kinds, rows, owner, mats, pal, hair, stripes = [], [], [], [], [], [], [], []
        for i, (pid, shape, k, r, m) in enumerate(people):
            ids.append(pid)
            kinds.append(k)
            rows.append(r)
            mats.append(m)
            owner.append(np.full(len(k), i, dtype=np.int64))
            pal.append(shape.palette())
            hair.append([shape.hair_front, shape.hair_back])
            stripes.append(shape.stripes)
        return cls(np.array(ids, dtype=np.int64), np.concatenate(kinds), np.ascontiguousarray(np.concatenate(rows)),
                   np.concatenate(owner), np.concatenate(mats), np.array(pal), np.array(hair, dtype=np.float64),
                   np.array(stripes, dtype=np.float64))
