"""A likelihood for the fat voxels of a visual hull: the thesis's per-part scores
(Eqs. 6.13-6.16, :mod:`app.pose.likelihood`) times a *coverage* term, how much of the
person's data the model explains.

The thesis scores the model against the data only: the share of each part's voxels
that falls on data (occupancy, Eq. 6.15) and near the data's surface (Eq. 6.16). On the
true body that is enough, but a visual hull is larger than the body (1.4-1.5x for one
person seen by 5 cameras at k = 0, 5-7x at k = 1): any pose that keeps the parts
inside the hull is fully "occupied", an arm folded against the trunk scores as well as
the arm in the hull's protrusion where the real arm is, and the filter drifts.

The coverage term is the other direction, the share of the data voxels that the model
covers, ``rho_Cov = sum_q |Y_q in V| delta^3 / |V|``: every occupied model point of the
LUT stands for ``delta^3`` data voxels (Eq. 6.26), so it comes from the occupancy counts
the kernel already makes (parts overlapping are already punished by the double
occupancy term). It enters the log-likelihood as one more Gaussian term,
``-(1 - rho_Cov)^2 / (2 sigma_Cov^2)``; only the differences between particles matter
to the annealing, so the unexplained share that no pose can explain (the hull's excess)
costs every particle alike. SHBM-APF's partial models (the trunk of H1, H2 without
forearms and shins) cannot explain the limbs' data and are pushed a little towards
it; ``partial`` chooses whether they are scored with the term too (default in
:class:`app.pose.estimator.PoseSettings`: yes; measured over gesture1 and walk1, true
body and k = 0 hulls, 35 frames x 2 seeds each, with a floor prior of 0.05 m: MMTA
0.924 with it, 0.909 on the whole model only) or only the whole body (every part that DDM-APF
has not switched off). This is the voxel analogue of the bidirectional silhouette
likelihood of HumanEva-era trackers; ``coverage = 0`` is the thesis's likelihood.

A second optional term, the *floor* prior, keeps the lower foot on the floor: the
lower of the two ankles is expected at its standing height (0.039 H) with a one-sided
Gaussian of deviation ``floor`` (m) above it. A visual hull often loses the feet
(a camera that sees them behind furniture votes them out at k = 0) or widens them
into a cone at the floor (k = 1); without the prior the legs are pulled up into the
remaining data and the body with them (measured: pelvis 25-35 mm too high on
gesture1's k = 0 hull). Standing, walking and sitting keep a foot down; a jump does
not, and ``floor = 0`` switches the prior off (the thesis has none).
While the track stands still the estimator also sets ``both_feet`` (m): the higher
ankle gets the same one-sided prior, of that deviation (a person standing keeps both
feet down; on gesture1 the k = 0 hull has no right foot and the right leg drifted).

A third, the *heading* prior, takes the heading from the track (the issue's "tracks
give their heading"): while the person walks (the track's smoothed speed above 0.3
m/s), the root's yaw is expected along the velocity with a Gaussian of deviation
``heading`` (rad) on the wrapped difference. A body seen as a hull is nearly the same
from the front and from the back once the feet are gone (occluded1, walking between
tables: SHBM-APF faced backwards for the whole clip, MPJPE 275 mm); 0 switches it off.

A fourth, the *stance* prior, goes with ``both_feet`` (the track standing still): a
person standing still has the feet under the hips (simulated gesture1 and meeting3:
each ankle within 2 cm of under its hip in half the standing frames, 8 cm in 90 %, 18
cm at most). Each ankle whose hip is at least 0.9 of its standing height (an upright
leg; a particle sitting or kneeling is not held) moves freely within ``STANCE_FREE`` of
under its hip, horizontally, and beyond it costs a one-sided Gaussian of deviation
``stance`` (m). Without it the leg the hull has no foot of drifts: on gesture1 the k = 0
hull has no right foot and the right ankle sat 70 mm sideways (within 100 mm in
35-65 % of the frames, 91-94 % with the prior); 0 switches it off.

A fifth, the *ground* prior (``ground``, m; applied with the floor prior): no ankle below
its standing height, ``sum_ankles 0.5 ((0.039 H - z)_+ / ground)^2``. The floor prior only
pulls the lower ankle down; nothing held an ankle up, and on the pipeline's hulls (the
swing leg's shin carved by one camera) the posed ankles went 3-5 cm into the floor
(walk1: median 64 mm against the true 114 mm, 5 % under 38 mm where the true ones are
never under 69 mm; meeting3 5 % under 13 mm). Through the pipeline, 0.01 m: MMTP walk1
40-42 -> 36-39 mm, meeting3 43-45 -> 40-41 mm, MMTA meeting3 +0.02 (docs/history/pose-likelihood.md,
"Round 2"); 0 switches it off (the thesis has none).

A sixth, the *anchor* (``anchor``: (x, y, free, deviation) of the person's track, set by
the estimator when ``PoseSettings.anchor > 0``; on in the pose worker, 0.05 m, off in the
offline core): the root farther than
``free`` from its track, horizontally, costs a Gaussian of that deviation. Against a phantom
that holds the body away from its person (meeting3's door: with the ground prior the pose
stood in the phantom 0.5-0.7 m from the person for 12 frames); meeting3 0.822 -> 0.842,
gesture1 and walk1 unchanged.

A seventh, the *crown* (``crown``, m; on in the pose worker, 0.015 m, off in the offline
core): the head under the top of the person's own voxels. Nothing else holds the body
up: the scores count the model's points on data and the data the model covers, and a
body that sinks into a crouch inside its standing hull loses little on either (random
scenes 0-15, the pipeline's poses: 7 % of the matched person-frames had the pelvis more
than 12 cm or the head more than 15 cm below the truth while the stature was right, 6.7
points of MMTA, the largest loss after the ordinary errors: a standing person posed
squatting for the whole clip beside furniture, another whose grey shirt the masks lost
between chest and neck). The estimator reads each frame the top of the person's voxels
near the body axis (:func:`app.pose.estimator.blob_top`, as for the stature), capped at
the standing top (a hand raised above the head adds nothing), and expects the head
centre (0.935 H standing) as far below it as standing, ``z_exp = min(top, top_H) - (top_H
- 0.935 H)``; a head lower than ``z_exp - CROWN_FREE`` costs a one-sided Gaussian of
deviation ``crown``. Sitting, crouching and bending lower the top, and the expectation
with it; only a head below its own person's top is pushed.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from app.messages import JOINTS
from app.pose.flesh import PARTS
from app.pose.likelihood import Scorer, log_likelihood, normalise
from app.pose.model import (AVERAGE, Proportions, joints_subset, neutral_state, segments_needed,
                            standing_root_height, standing_top)
from app.pose.silhouette import silhouette_coverage
from app.keypoints.fusion import keypoint_penalty

__all__ = ["CoverageScorer", "coverage", "floor_penalty", "stance_penalty", "leg_penalties", "ground_penalty",
           "anchor_penalty", "crown_penalty", "crown_expectation", "STANCE_FREE", "CROWN_FREE"]

_ANKLES = np.array([JOINTS.index("l_ankle"), JOINTS.index("r_ankle")], dtype=np.int64)
_ANKLE_NEED = segments_needed(_ANKLES)   # forward kinematics of the legs only


def floor_penalty(states: np.ndarray, height: float, sigma: float, both: float = 0.0,
                  proportions: Proportions = AVERAGE) -> np.ndarray:
    """``0.5 ((z_low - 0.039 H)_+ / sigma)^2`` per state, ``z_low`` the lower ankle's height;
    ``both > 0`` adds ``0.5 ((z_high - 0.039 H)_+ / both)^2`` for the higher ankle (a
    person standing still keeps both feet down)."""
    z = joints_subset(states, height, _ANKLES, _ANKLE_NEED, proportions)[:, :, 2]
    rest = 0.039 * height
    out = 0.5 * (np.maximum(z.min(axis=1) - rest, 0.0) / sigma) ** 2
    if both > 0:
        out = out + 0.5 * (np.maximum(z.max(axis=1) - rest, 0.0) / both) ** 2
    return out


_LEGS = np.array([JOINTS.index(n) for n in ("l_hip", "l_ankle", "r_hip", "r_ankle")], dtype=np.int64)
_LEGS_NEED = segments_needed(_LEGS)
_LEGS_HEAD = np.array([JOINTS.index(n) for n in ("l_hip", "l_ankle", "r_hip", "r_ankle", "head")], dtype=np.int64)
_LEGS_HEAD_NEED = segments_needed(_LEGS_HEAD)
#: m: a standing ankle moves freely this far (horizontally) from under its hip
STANCE_FREE = 0.08


def stance_penalty(states: np.ndarray, height: float, sigma: float, free: float = STANCE_FREE,
                   proportions: Proportions = AVERAGE) -> np.ndarray:
    """``sum_sides 0.5 ((|ankle_xy - hip_xy| - free)_+ / sigma)^2`` over the sides whose
    hip is at least 0.9 of its standing height (an upright leg: a particle sitting or
    kneeling is not held): a person standing still has the feet under the hips."""
    j = joints_subset(states, height, _LEGS, _LEGS_NEED, proportions)
    upright_z = 0.9 * (standing_root_height(height, proportions) - 0.025 * height)
    out = np.zeros(len(j))
    for hip, ankle in ((0, 1), (2, 3)):
        d = np.hypot(j[:, ankle, 0] - j[:, hip, 0], j[:, ankle, 1] - j[:, hip, 1])
        pen = 0.5 * (np.maximum(d - free, 0.0) / sigma) ** 2
        out += np.where(j[:, hip, 2] >= upright_z, pen, 0.0)
    return out


def leg_penalties(states: np.ndarray, height: float, floor: float, both: float = 0.0, stance: float = 0.0,
                  ground: float = 0.0, crown=None, proportions: Proportions = AVERAGE):
    """:func:`floor_penalty` (deviation ``floor``, ``both``) and, when ``stance > 0``,
    :func:`stance_penalty` (else None) from one forward kinematics of the legs and one
    loop: the same numbers as the two functions (the ankles are the same whichever
    joints are asked for; the operations are numpy's, one by one). ``ground > 0`` adds
    :func:`ground_penalty` to the first, ``crown`` ``(expected, sigma)``
    :func:`crown_penalty` (the head from the same forward kinematics: the legs' and the
    head's chains share the root, and one pass costs less than two)."""
    if crown is not None:
        j = joints_subset(states, height, _LEGS_HEAD, _LEGS_HEAD_NEED, proportions)
    else:
        j = joints_subset(states, height, _LEGS, _LEGS_NEED, proportions)
    fl = np.empty(len(j))
    st = np.empty(len(j)) if stance > 0 else None
    _leg_penalties(j, 0.039 * height, float(floor), float(both),
                   0.9 * (standing_root_height(height, proportions) - 0.025 * height), float(stance), STANCE_FREE, fl,
                   st if st is not None else fl[:0])
    if ground > 0:
        fl += _ground(j[:, 1:4:2, 2], 0.039 * height, ground)
    if crown is not None:
        fl += _crown(j[:, 4, 2], *crown)
    return fl, st


def _ground(z: np.ndarray, rest: float, sigma: float) -> np.ndarray:
    return 0.5 * ((np.maximum(rest - z, 0.0) / sigma) ** 2).sum(axis=1)


def ground_penalty(states: np.ndarray, height: float, sigma: float, proportions: Proportions = AVERAGE) -> np.ndarray:
    """``sum_ankles 0.5 ((0.039 H - z)_+ / sigma)^2``: no ankle below its standing height
    (the foot is under it; the floor prior only pulls the lower ankle *down* to that
    height). On the pipeline's hulls the swing leg, its shin carved by one camera, was
    posed with the ankle 3-5 cm into the floor (walk1: 5 % of the posed ankles under
    38 mm, the true ones never under 69 mm; meeting3 13 mm)."""
    j = joints_subset(states, height, _ANKLES, _ANKLE_NEED, proportions)
    return _ground(j[:, :, 2], 0.039 * height, sigma)


_HEAD = np.array([JOINTS.index("head")], dtype=np.int64)
_HEAD_NEED = segments_needed(_HEAD)
#: m: the head moves freely this far below its expected height (a bow, a tilt)
CROWN_FREE = 0.06
#: the head centre's height standing straight, a share of the stature (the model's neutral pose, 0.935)
HEAD_STANDING = float(joints_subset(neutral_state(1.0)[None], 1.0, _HEAD, _HEAD_NEED)[0, 0, 2])


def crown_expectation(top: float, height: float, voxel_size: float) -> float:
    """The head centre's expected height below ``top``, the highest voxel centre near the
    body axis: as far below it as standing, the top capped at the standing one
    (:func:`app.pose.model.standing_top`, the inverse of the stature's reading)."""
    full = standing_top(height, voxel_size)
    return min(float(top), full) - (full - HEAD_STANDING * height)


def crown_penalty(states: np.ndarray, height: float, expected: float, sigma: float,
                  proportions: Proportions = AVERAGE) -> np.ndarray:
    """``0.5 ((expected - CROWN_FREE - z_head)_+ / sigma)^2``: the head no lower than the
    top of the person's voxels says (``expected`` from :func:`crown_expectation`)."""
    return _crown(joints_subset(states, height, _HEAD, _HEAD_NEED, proportions)[:, 0, 2], expected, sigma)


def _crown(z: np.ndarray, expected: float, sigma: float) -> np.ndarray:
    return 0.5 * (np.maximum(expected - CROWN_FREE - z, 0.0) / sigma) ** 2


def anchor_penalty(states: np.ndarray, x: float, y: float, free: float, sigma: float) -> np.ndarray:
    """``0.5 ((d - free)_+ / sigma)^2`` with ``d`` the root's horizontal distance from its
    track at ``(x, y)``: the pose stays with its person, not with a phantom beside it."""
    st = np.asarray(states)
    d = np.hypot(st[:, 0] - x, st[:, 1] - y)
    return 0.5 * (np.maximum(d - free, 0.0) / sigma) ** 2


@njit(cache=True, nogil=True)
def _leg_penalties(j, rest, floor, both, upright_z, stance, free, fl, st):
    """Per state the floor prior (lower ankle, and the higher one when ``both > 0``) and,
    when ``st`` has rows, the stance prior, from the joints ``(P, 4, 3)`` of
    :data:`_LEGS` (left hip, left ankle, right hip, right ankle)."""
    for p in range(j.shape[0]):
        zl, zr = j[p, 1, 2], j[p, 3, 2]
        low, high = min(zl, zr), max(zl, zr)
        x = max(low - rest, 0.0) / floor
        v = 0.5 * (x * x)
        if both > 0:
            x = max(high - rest, 0.0) / both
            v = v + 0.5 * (x * x)
        fl[p] = v
        if st.shape[0]:
            v = 0.0
            for hip, ankle in ((0, 1), (2, 3)):
                d = np.hypot(j[p, ankle, 0] - j[p, hip, 0], j[p, ankle, 1] - j[p, hip, 1])
                x = max(d - free, 0.0) / stance
                v += 0.5 * (x * x) if j[p, hip, 2] >= upright_z else 0.0
            st[p] = v


def coverage(counts: np.ndarray, active: np.ndarray, data_count: int, delta: float) -> np.ndarray:
    """``rho_Cov (P,)``: share of the ``data_count`` data voxels covered by the active
    parts' occupied model points (``counts (P, Q, 5)`` of :meth:`Scorer.counts`)."""
    out = np.empty(len(counts))
    _coverage(np.ascontiguousarray(counts, dtype=np.float64), np.flatnonzero(np.asarray(active, bool)),
              float(delta) ** 3, float(max(int(data_count), 1)), out)
    return out


@njit(cache=True, nogil=True)
def _coverage(counts, parts, cube, data, out):
    """:func:`coverage` in one loop: the occupied counts are whole numbers, so their sum is
    exact in any order (the same numbers as numpy's masked sum)."""
    for p in range(counts.shape[0]):
        occupied = 0.0
        for q in parts:
            occupied += counts[p, q, 2]
        out[p] = min(occupied * cube / data, 1.0)


class CoverageScorer(Scorer):
    """:class:`~app.pose.likelihood.Scorer` with the coverage term of variance
    ``sigma2`` and the floor prior of deviation ``floor`` (both 0: the thesis's
    likelihood, unchanged)."""

    def __init__(self, flesh, mode: str = "partitioned", sigma2: float = 0.0, partial: bool = False,
                 floor: float = 0.0):
        super().__init__(flesh, mode)
        self.floor = float(floor)
        self.sigma2 = float(sigma2)
        self.partial = bool(partial)   # also score partial models (SHBM-APF's H1, H2)
        self.expected = np.ones(len(PARTS), dtype=bool)   # the parts tracked (DDM-APF may switch some off)
        self.heading = None        # (yaw along the track's velocity, deviation rad) or None
        self.both_feet = 0.0       # m: deviation of the higher ankle's floor prior while standing; 0 = off
        self.stance = 0.0          # m: deviation of the stance prior while standing (set with both_feet); 0 = off
        self.ground = 0.0          # m: deviation of the ground prior (no ankle below its standing height); 0 = off
        self.anchor = None         # (track x, y, free radius m, deviation m) or None: the root near its track
        self.crown = None          # (expected head z m, deviation m) or None: the head under the voxels' top
        self.silhouette = None     # (PersonSilhouettes, sigma^2, Lut) or None: app.pose.silhouette's term
        self.keypoints = None      # (PersonKeypoints, sigma m, gate m, min confidence) or None: app.keypoints.fusion
        self._sil_stamp = None
        self._sil_token = 1

    def log_weights(self, states: np.ndarray, active=None) -> np.ndarray:
        act = np.ones(len(PARTS), dtype=bool) if active is None else np.asarray(active, dtype=bool)
        counts = self.counts(states, act)
        lw = log_likelihood(normalise(counts, self.flesh), self.flesh, act, self.mode)
        if self.sigma2 > 0 and self.obs is not None and (self.partial or np.all(act | ~self.expected)):
            delta = self.flesh.spacing / self.obs.voxel_size
            miss = 1.0 - coverage(counts, act, self.obs.count, delta)
            lw = lw - 0.5 * miss ** 2 / self.sigma2
        if self.silhouette is not None and np.all(act | ~self.expected):
            lw = lw - self._silhouette_penalty(states, act)
        if self.keypoints is not None:
            person, sigma, gate, conf = self.keypoints
            lw = lw - keypoint_penalty(states, self.flesh.height, person, sigma, gate, conf, act,
                                       self.flesh.proportions)
        crown = self.crown if act[PARTS.index("head")] else None
        if self.floor > 0 and act[PARTS.index("l_shin")] | act[PARTS.index("r_shin")]:
            floor, stance = leg_penalties(states, self.flesh.height, self.floor, self.both_feet,
                                          self.stance if self.both_feet > 0 else 0.0, self.ground, crown,
                                          self.flesh.proportions)
            crown = None   # counted with the legs
            lw = lw - floor
            if stance is not None:
                lw = lw - stance
        if crown is not None:
            lw = lw - crown_penalty(states, self.flesh.height, *crown, self.flesh.proportions)
        if self.anchor is not None:
            lw = lw - anchor_penalty(states, *self.anchor)
        if self.heading is not None:
            yaw, sigma = self.heading
            d = np.angle(np.exp(1j * (np.asarray(states)[:, 3] - yaw)))
            lw = lw - 0.5 * (d / sigma) ** 2
        return lw

    def log_weights_as(self, states: np.ndarray, flesh, lut, silhouette_lut=None, active=None) -> np.ndarray:
        """:meth:`log_weights` of another body of the same person (:mod:`app.pose.proportions`):
        this frame's observation and terms, that body's ``flesh`` with its kernel ``lut``
        (and ``silhouette_lut`` for the silhouette term), the ``active`` parts (None: all)."""
        keep = self.flesh, self.lut, self.silhouette, self.evaluations
        self.flesh, self.lut = flesh, lut
        if self.silhouette is not None:
            self.silhouette = self.silhouette[:2] + (silhouette_lut,)
        try:
            return self.log_weights(states, active)
        finally:
            self.flesh, self.lut, self.silhouette, self.evaluations = keep

    def _silhouette_penalty(self, states, act) -> np.ndarray:
        """``(1 - rho_Sil)^2 / (2 sigma^2)`` of :mod:`app.pose.silhouette` (whole model only)."""
        person, sigma2, lut = self.silhouette
        if self._sil_stamp is None or self._sil_stamp.shape != person.grids.shape:
            self._sil_stamp = np.zeros(person.grids.shape, np.int64)
        rho = silhouette_coverage(states, self.flesh.height, lut, act, person, self._sil_stamp, self._sil_token)
        self._sil_token += len(states)
        return 0.5 * (1.0 - rho) ** 2 / sigma2
