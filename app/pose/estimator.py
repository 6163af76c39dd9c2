"""Pose of every tracked person from one frame's voxels: one filter per track.

:class:`PoseEstimator` takes a frame's occupied voxels and the tracks (ids and
centroids), gives each voxel to the nearest track (in the floor plane, within
``reach``), so that each person's likelihood ignores the voxels owned by the others,
and steps that person's :class:`PersonPose`. A new track starts its filter from the
detections of :mod:`app.pose.detections` (all particles drawn from the importance
function); later frames draw a fraction of the first layer from it (IAPF). Limb
lengths follow the stature, estimated from the top of the person's blob over the
first ``height_frames`` frames (``1.02 H``: the top of the head is a little above the
stature of the model), near the body axis (``stature = "axis"``; ``"top"`` the highest
voxel, which a raised hand lifts), in the average proportions; ``proportions = "fit"``
reads legs and arms from the person's next ``proportion_frames`` frames
(:mod:`app.pose.proportions`; off by default: it is not reliable on hulls).

The likelihood is the thesis's (Eqs. 6.13-6.25) with three additions for the fat voxels
of a visual hull, all selectable (``coverage = 0, floor = 0, heading = 0`` is the
thesis's): the coverage term, the floor prior and the heading prior (the track's
walking direction) of :mod:`app.pose.coverage`. The IAPF arm proposals
solve the arm's inverse kinematics by look-up (``ik = "table"``, :mod:`app.pose.detections`;
``"straight"`` the earlier straight arm).

Methods: ``apf`` (§6.5, Alg. 3), ``shbm`` (SHBM-APF, §7.3), ``ddm`` (APF with DDM limb
switching, §7.4), ``shbm+ddm`` (both, the thesis's future work) and ``behaviour``
(Caillette, Galata and Howard's learnt behaviour model and Gaussian blobs,
:mod:`app.behaviour`: the first ``behaviour_start`` frames of a track are posed by SHBM-APF,
whose last estimate teaches the blobs, then :class:`~app.behaviour.tracker.BehaviourTracker`
poses it from the voxels and their colours).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
from numba import njit

from app.messages import JOINTS
from app.pose.detections import Importance, detect
from app.pose.filters import APF, SHBMAPF, LimbSwitch
from app.pose.flesh import build_flesh
from app.pose.likelihood import kernel_lut
from app.pose.coverage import CoverageScorer, crown_expectation
from app.pose.facing import FacingVote, floor_footprint, frame_vote
from app.pose.model import AVERAGE, BodyModel, Proportions, neutral_state, posed_tracks, stature_from_top
from app.pose.proportions import ProportionFit, on_body
from app.pose.observation import observe
from app.keypoints.fusion import keypoint_hands

__all__ = ["PoseSettings", "PersonPose", "PoseEstimator", "METHODS", "assign_voxels"]

METHODS = ("apf", "shbm", "ddm", "shbm+ddm", "behaviour")


@dataclass
class PoseSettings:
    method: str = "shbm"
    voxel_size: float = 0.02
    density: float = 2.0            # delta of Eq. 6.26
    likelihood: str = "partitioned"  # or "global"
    particles: int = 600            # APF: particles per layer
    layers: int = 6                 # APF: annealing layers
    alpha: float = 0.5              # survival rate per layer
    gamma: int = 50                 # SHBM-APF: particles per new DoF
    gamma_budget: int = 0           # SHBM-APF: gamma summed over the people posed in a frame; 0 = gamma each (thesis)
    gamma_min: int = 20             # SHBM-APF: the least gamma the budget gives a person
    importance_fraction: float = 0.2
    coverage: float = 0.003         # sigma^2 of the coverage term (app.pose.coverage); 0 = the thesis's likelihood
    coverage_partial: bool = True   # coverage also on SHBM-APF's partial models (H1, H2)
    floor: float = 0.02             # m: the floor prior's deviation (app.pose.coverage); 0 = none (the thesis)
    heading: float = 0.6            # rad: deviation of the yaw from the track's walking direction; 0 = none
    toes: float = 0.0               # rad: ... from the way the feet point while not walking (app.pose.facing); 0 = none
    ik: str = "table"               # IAPF arm proposals: look-up inverse kinematics (table) or straight arms
    lock_frames: int = 10           # DDM: no limb is switched off before the filter has locked on
    limb_criterion: str = "predicted"  # DDM lost-limb test: predicted (before the step) or thesis (after)
    surface: str = "outer"          # V^S of voxels without flags: outer (no cavities) or boundary (app.pose.observation)
    feet: float = 0.05              # m: while the track stands still, the higher ankle's floor prior too; 0 = off
    stature: str = "axis"           # the blob's top for the stature: near the body axis (axis) or anywhere (top)
    stance: float = 0.03            # m: while the track stands still, the ankles under the hips (app.pose.coverage); 0 = off
    ground: float = 0.0             # m: no ankle below its standing height (app.pose.coverage.ground_penalty); 0 = off
                                    # (the pose worker: 0.01, for the hulls; on true-body voxels it costs gesture1 0.01)
    anchor: float = 0.0             # m: the root within anchor_free of its track, beyond a Gaussian of this deviation; 0 = off
    anchor_free: float = 0.25       # m
    crown: float = 0.0              # m: the head under the top of the person's voxels (app.pose.coverage); 0 = off
    reach: float = 0.9              # voxels farther than this from every track (m) are nobody's
    silhouette: float = 0.0         # sigma^2 of the silhouette term (app.pose.silhouette); 0 = off (the thesis)
    silhouette_density: float = 2.0  # ... the model's points for it on a lattice of this many voxel sizes (Eq. 6.26's factor)
    silhouette_reach: float = 0.6   # m: a silhouette pixel is a track's when its ray passes this near the track only
    silhouette_fit: bool = True     # each person's silhouettes coarsened to the model points' lattice at its depth
                                    # (app.pose.silhouette.coarsening); False: as the reconstruction sends them
    keypoints: float = 0.0          # m: sigma of the 2D keypoint term (app.keypoints.fusion); 0 = off
    keypoint_gate: float = 0.3      # m: a keypoint's error is truncated here (a wrong detection costs at most this)
    keypoint_conf: float = 0.5      # keypoints less sure than this cost nothing
    keypoint_hands: bool = True     # wrists triangulated from the keypoints are the importance function's hands
    low_legs: float = 0.5           # share of the importance draws with a lowered root whose legs bend to the floor
                                    # (sitting, app.pose.detections.Importance); 0 = off
    height_frames: int = 5
    proportions: str = "average"    # limb lengths: the stature's average fractions (the thesis) or fit to the
                                    # person's voxels over their first proportion_frames (app.pose.proportions)
    proportion_frames: int = 40
    behaviour_start: int = 10       # behaviour: frames posed by SHBM-APF before the blobs are learnt
    behaviour_particles: int = 500  # behaviour: particles (the paper's Table 1: 100-1000)
    behaviour_lambda: float = 0.5   # behaviour: lambda of Eq. 4, the local dynamics' noise attenuation
    behaviour_evaluation: str = "model"  # behaviour: kl (the paper's blob fit and relative entropy), voxels (the
                                      # voxels' likelihood under the blobs) or model (the likelihood above; ours)
    behaviour_model: str = ""       # behaviour: the model file (smartroom train behaviour); "" the shipped one
    behaviour_temperature: float = 20.0  # behaviour, voxels evaluation: log-weight = this x the mean log-likelihood
    behaviour_recovery: str = "shbm"  # behaviour lost: SHBM-APF finds the person again (shbm) or the paper's
                                      # motion prototypes alone (prototypes)
    behaviour_layers: int = 3       # behaviour, model evaluation: 1 = the paper's one weighing; more: annealing layers
    behaviour_refine: float = 0.25  # ... their diffusion, times the APF's sigma_0 (Eq. 3.22)
    threads: int = 1                # people posed in parallel by this many threads (the kernels release the GIL)
    seed: int = 0
    room_lo: tuple = (0.0, 0.0, 0.0)
    room_hi: tuple = (5.0, 4.0, 2.5)

    @classmethod
    def from_params(cls, params: dict) -> "PoseSettings":
        """The settings a pose worker's parameters give (each cast to its field's type; the
        worker's other keys, voxel subset, share and snapshots, are not settings), as the
        worker and ``smartroom bench pose --replay`` build them."""
        kw = {}
        for f in fields(cls):
            if f.name in params and f.name not in ("voxel_size", "room_lo", "room_hi"):
                kind = type(f.default)
                kw[f.name] = kind(params[f.name]) if kind in (int, float, bool, str) else params[f.name]
        return cls(**kw)

    def validate(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"pose method {self.method!r} is not one of {', '.join(METHODS)}")
        if self.likelihood not in ("partitioned", "global"):
            raise ValueError(f"likelihood {self.likelihood!r} must be partitioned or global")
        if self.ik not in ("table", "straight"):
            raise ValueError(f"ik {self.ik!r} must be table or straight")
        if not (self.coverage >= 0 and self.floor >= 0 and self.heading >= 0 and self.toes >= 0 and self.feet >= 0
                and self.stance >= 0 and self.ground >= 0 and self.anchor >= 0 and self.anchor_free >= 0
                and self.crown >= 0):
            raise ValueError("coverage, floor, feet, heading, toes, stance, ground, anchor, anchor_free and crown "
                             "must be >= 0 (0 switches them off)")
        if self.stature not in ("axis", "top"):
            raise ValueError(f"stature {self.stature!r} must be axis or top")
        if self.proportions not in ("average", "fit") or self.proportion_frames < 1:
            raise ValueError(f"proportions {self.proportions!r} must be average or fit, proportion_frames >= 1")
        if self.surface not in ("outer", "boundary"):
            raise ValueError(f"surface {self.surface!r} must be outer or boundary")
        if not self.density >= 1:
            raise ValueError(f"density {self.density} must be >= 1")
        if not (self.silhouette >= 0 and self.silhouette_density >= 0.5 and self.silhouette_reach > 0):
            raise ValueError("silhouette must be >= 0 (0: off), silhouette_density >= 0.5, silhouette_reach > 0")
        if not (self.keypoints >= 0 and self.keypoint_gate > 0 and 0 <= self.keypoint_conf <= 1):
            raise ValueError("keypoints must be >= 0 (0: off), keypoint_gate > 0, keypoint_conf in 0..1")
        if not 0 <= self.low_legs <= 1:
            raise ValueError(f"low_legs {self.low_legs} must be in 0..1 (0: off)")
        if self.behaviour_recovery not in ("shbm", "prototypes"):
            raise ValueError(f"behaviour_recovery {self.behaviour_recovery!r} must be shbm or prototypes")
        from app.behaviour.tracker import EVALUATIONS
        if self.behaviour_evaluation not in EVALUATIONS:
            raise ValueError(f"behaviour_evaluation {self.behaviour_evaluation!r} must be one of {', '.join(EVALUATIONS)}")
        if self.behaviour_particles < 1 or self.behaviour_start < 1 or not self.behaviour_lambda >= 0:
            raise ValueError("behaviour_particles and behaviour_start must be >= 1, behaviour_lambda >= 0")
        if self.gamma < 1 or self.gamma_budget < 0 or self.gamma_min < 1:
            raise ValueError("gamma and gamma_min must be >= 1, gamma_budget >= 0 (0: gamma for everyone)")

    def shbm_gamma(self, people: int = 1) -> int:
        """SHBM-APF's particles per new DoF (Eq. 7.28) for each of ``people`` posed in one
        frame: the thesis's ``gamma``, or with a ``gamma_budget`` the budget shared among
        them, ``min(gamma, max(gamma_min, budget // people))``, so that the frame's cost
        stays about the same however many people there are (a real-time budget; the
        thesis poses one person). Measured through the pipeline's voxels at 4 cm
        (docs/history/pose-speed.md): meeting3's three people keep their MMTA with 25 each; one
        person alone (gesture1, walk1) loses 0.01-0.03 with 25-40, so alone keeps 50."""
        if self.gamma_budget <= 0 or people <= 1:
            return int(self.gamma)
        return int(min(self.gamma, max(self.gamma_min, self.gamma_budget // people)))


def assign_voxels(centres: np.ndarray, positions: np.ndarray, reach: float, wanted=None) -> np.ndarray:
    """Index of the owning track of every voxel (nearest in the floor plane, the first of
    equals), -1 for none. ``wanted``: indices of the tracks whose voxels are asked for (a
    pose shard's people), or None for all; a voxel farther than ``reach`` from every
    wanted track is -1 then, found without looking at the other tracks (only a voxel
    within ``reach`` of a track can be its own, so the wanted tracks' voxels are those of
    the full pass; a voxel near a wanted track keeps whichever owner it has)."""
    owner = np.full(len(centres), -1, dtype=np.int64)
    if len(positions) == 0 or len(centres) == 0:
        return owner
    pick = posed_tracks(len(positions), wanted)
    if not pick.any():
        return owner
    _owners(np.ascontiguousarray(centres, np.float64), np.ascontiguousarray(positions, np.float64), float(reach),
            pick, owner)
    return owner


@njit(cache=True, nogil=True)
def _owners(centres, positions, reach, pick, owner):
    """:func:`assign_voxels`' loop: the distances as ``np.linalg.norm`` computes them
    (``sqrt(dx * dx + dy * dy)``) and the first nearest as ``np.argmin`` picks it, in one
    pass without the (N, T) temporaries (at 2 cm, 16 ms a frame of crowd6 through numpy,
    done by every pose worker: issue 26). A voxel farther than ``reach`` from every
    ``pick``ed track is -1 without looking at the others (a shard posing one of six
    people: a sixth of the distances)."""
    everyone = True
    for k in range(pick.shape[0]):
        everyone = everyone and pick[k]
    for i in range(centres.shape[0]):
        if not everyone:
            near = False
            for k in range(positions.shape[0]):
                if pick[k]:
                    dx = centres[i, 0] - positions[k, 0]
                    dy = centres[i, 1] - positions[k, 1]
                    if math.sqrt(dx * dx + dy * dy) <= reach:
                        near = True
                        break
            if not near:
                owner[i] = -1
                continue
        best, nearest = -1, np.inf
        for k in range(positions.shape[0]):
            dx = centres[i, 0] - positions[k, 0]
            dy = centres[i, 1] - positions[k, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d < nearest or best < 0:
                best, nearest = k, d
        owner[i] = -1 if nearest > reach else best


def blob_top(centres: np.ndarray, axis: bool = True, band: float = 0.75, radius: float = 0.15) -> float:
    """The top of a person's voxels for the stature: with ``axis`` the highest voxel within
    ``radius`` (m, horizontally) of the body axis, the median of the voxels above ``band``
    times the blob's top, so that a hand raised above the head is not taken for the top of
    the head (on gesture1 the raised hand put the top 10 cm above the head, 1.81 m
    instead of 1.73 m of stature, when the track started with the arm up); without
    ``axis`` the highest voxel (the earlier estimate)."""
    top = float(centres[:, 2].max())
    if not axis:
        return top
    upper = centres[centres[:, 2] > band * top]
    ax = np.median(upper[:, :2], axis=0)
    near = centres[np.hypot(centres[:, 0] - ax[0], centres[:, 1] - ax[1]) < radius]
    return float(near[:, 2].max()) if len(near) else top


_FLESH_CACHE: dict = {}
_LUT_CACHE: dict = {}
_BEHAVIOUR_MODELS: dict = {}


def behaviour_model(path: str = ""):
    """The :class:`~app.behaviour.model.BehaviourModel` of ``path`` ("" the shipped one),
    read once a process (:class:`~app.errors.InputError` when it cannot be)."""
    if path not in _BEHAVIOUR_MODELS:
        from app.behaviour.model import DEFAULT_PATH, BehaviourModel
        _BEHAVIOUR_MODELS[path] = BehaviourModel.load(path or DEFAULT_PATH)
    return _BEHAVIOUR_MODELS[path]


def _body_key(height, voxel_size, density, proportions):
    return round(height, 2), round(voxel_size, 4), float(density), proportions


def _flesh(height, voxel_size, density, proportions: Proportions = AVERAGE):
    key = _body_key(height, voxel_size, density, proportions)
    if key not in _FLESH_CACHE:
        _FLESH_CACHE[key] = build_flesh(key[0], voxel_size, density, proportions)
    return _FLESH_CACHE[key]


def _lut(height, voxel_size, density, proportions: Proportions = AVERAGE):
    """:func:`~app.pose.likelihood.kernel_lut` of :func:`_flesh`, kept as it is."""
    key = _body_key(height, voxel_size, density, proportions)
    if key not in _LUT_CACHE:
        _LUT_CACHE[key] = kernel_lut(_flesh(height, voxel_size, density, proportions))
    return _LUT_CACHE[key]


class PersonPose:
    """One person's filter and body."""

    def __init__(self, settings: PoseSettings, track_id: int, rng: np.random.Generator):
        self.s = settings
        self.id = track_id
        self.rng = rng
        self.tops: list[float] = []
        self.height = None
        self.proportions = AVERAGE
        self.fit = ProportionFit(settings.proportion_frames) if settings.proportions == "fit" else None
        self.filter = None
        self.switch = None
        self.state = None
        self.last_position = None
        self.velocity = None
        self.frames = 0
        self.tracker = None     # behaviour: Caillette's tracker, once the blobs are learnt
        self.handback = 0       # behaviour: frames SHBM-APF still poses after the tracker was lost
        self.vote = FacingVote()  # the feet's vote for the way the person faces (app.pose.facing)

    def build(self, height: float, proportions: Proportions = AVERAGE) -> None:
        """The body, its fleshed model and scorer and a fresh filter for stature ``height``
        and limb ``proportions``."""
        s = self.s
        self.height = height
        self.proportions = proportions
        self.model = BodyModel(height, proportions)
        self.scorer = CoverageScorer(_flesh(height, s.voxel_size, s.density, proportions), s.likelihood, s.coverage,
                                     s.coverage_partial, s.floor)
        self.scorer.stance = s.stance
        self.scorer.ground = s.ground   # applied with the floor prior (CoverageScorer.log_weights)
        # the silhouette term's model points: a lattice of about one silhouette pixel (app.pose.silhouette)
        self.silhouette_lut = (_lut(height, s.voxel_size, s.silhouette_density, proportions)
                               if s.silhouette > 0 else None)
        kw = dict(rng=self.rng, importance_fraction=s.importance_fraction)
        if s.method.startswith("shbm") or s.method == "behaviour":   # behaviour: SHBM-APF's first frames
            self.filter = SHBMAPF(gamma=s.gamma, **kw)
        else:
            self.filter = APF(particles=s.particles, layers=s.layers, alpha=s.alpha, **kw)
        self.switch = LimbSwitch(rng=self.rng, criterion=s.limb_criterion) if s.method.endswith("ddm") else None

    def update(self, centres: np.ndarray, surface, position: np.ndarray, gamma: int | None = None,
               silhouettes=None, keypoints=None, colours=None):
        """One frame of this person: ``(joints (15, 3), active (15,))`` or None before the
        body is known; ``gamma``: SHBM-APF's particles per new DoF this frame (the
        estimator's budget, :meth:`PoseSettings.shbm_gamma`), None for the settings';
        ``silhouettes``: the person's :class:`~app.pose.silhouette.PersonSilhouettes`
        (scored when the settings' ``silhouette`` > 0) or None; ``keypoints``: the person's
        :class:`~app.keypoints.fusion.PersonKeypoints` (scored when the settings'
        ``keypoints`` > 0, their triangulated wrists the importance function's hands) or None;
        ``colours``: the voxels' RGB (N, 3) or None (the behaviour method's blobs)."""
        s = self.s
        velocity = None
        if self.last_position is not None:
            velocity = (position - self.last_position) * 25.0
            # smoothed for the heading prior (a tracker's centroid jitters by a centimetre a frame)
            self.velocity = velocity if self.velocity is None else 0.7 * self.velocity + 0.3 * velocity
        settling = self.filter is None or self.frames < s.height_frames
        top = blob_top(centres, s.stature == "axis") if len(centres) >= 30 and (settling or s.crown > 0) else None
        if top is not None and settling:
            self.tops.append(top)   # read while the stature is settled only
        if self.filter is None:
            if len(self.tops) < 1:
                return None
            self.build(stature_from_top(max(self.tops), s.voxel_size))
        elif self.frames < s.height_frames and len(self.tops):
            h = stature_from_top(max(self.tops), s.voxel_size)
            if abs(h - self.height) > 0.015:   # the stature grows with more views of the top
                keep = self.filter
                self.build(h, self.proportions)
                self.filter.particles = keep.particles
        if self.tracker is not None and not self.handback and s.behaviour_evaluation != "model":
            return self._behaviour(self.tracker.step(centres, colours, position), position)
        if gamma is not None and isinstance(self.filter, SHBMAPF):
            self.filter.set_gamma(gamma)
        obs = observe(centres, s.voxel_size, s.room_lo, s.room_hi, surface=surface, mode=s.surface)
        self.scorer.set_observation(obs)
        self.scorer.heading = None
        use = silhouettes is not None and s.silhouette > 0 and float(np.sum(silhouettes.counts)) > 0
        self.scorer.silhouette = (silhouettes, s.silhouette, self.silhouette_lut) if use else None
        self.scorer.anchor = (float(position[0]), float(position[1]), s.anchor_free, s.anchor) if s.anchor > 0 else None
        self.scorer.crown = (crown_expectation(top, self.height, s.voxel_size), s.crown) \
            if s.crown > 0 and top is not None else None
        # standing still (smoothed track speed < 0.3 m/s): both feet down (the k = 0 hull
        # often lacks a foot a camera sees behind furniture; gesture1's right ankle)
        standing = self.velocity is not None and np.hypot(*self.velocity[:2]) < 0.3
        self.scorer.both_feet = s.feet if (standing and s.floor > 0) else 0.0
        if s.heading > 0 and self.velocity is not None and np.hypot(*self.velocity[:2]) > 0.3:
            self.scorer.heading = (float(np.arctan2(self.velocity[1], self.velocity[0])), s.heading)
        elif s.toes > 0 and (yaw := self.vote.heading()) is not None:   # not walking: the way the feet point
            self.scorer.heading = (yaw, s.toes)
        use_kp = keypoints is not None and s.keypoints > 0
        self.scorer.keypoints = (keypoints, s.keypoints, s.keypoint_gate, s.keypoint_conf) if use_kp else None
        if self.tracker is not None and not self.handback:   # behaviour weighed by the likelihood set up above
            return self._behaviour(self.tracker.step(centres, colours, position, score=self.scorer.log_weights),
                                   position)
        det = detect(centres, self.height, velocity)
        if det is not None and use_kp and s.keypoint_hands:
            hands = keypoint_hands(keypoints, self.height, s.keypoint_conf)
            if len(hands):
                det.hands = hands
        importance = Importance(det, self.height, s.ik, s.low_legs) if det is not None else None
        if self.state is None:
            start = neutral_state(self.height, (position[0], position[1], None))
            self.filter.reset(start, importance=importance)
        elif self.handback == s.behaviour_start:   # behaviour lost: SHBM-APF searches afresh from the last pose
            self.filter.reset(self.state, importance=importance)
        elif self.last_position is not None:
            self.filter.shift(position - self.last_position)
        if self.switch is not None:
            if self.state is not None and self.last_position is not None and self.frames >= s.lock_frames:
                predicted = self.state.copy()
                predicted[:2] += position[:2] - self.last_position[:2]
                self.switch.precheck(self.scorer, predicted)
            self.filter.frozen = self.switch.frozen()
        active = self.switch.part_mask() if self.switch is not None else None
        if active is not None:
            self.scorer.expected = active
        est = self.filter.step(self.scorer, active=active, importance=importance)
        if self.switch is not None:
            est = self.switch.update(self.scorer, self.filter, est)
        if self.fit is not None and not self.fit.done and self.frames >= s.height_frames:
            est = self._fit_proportions(est)
        joints = None
        if s.toes > 0:   # a walker's feet (one lifting, one landing) say little: no vote, the old ones fade
            joints = self.model.joints(est)
            footprint = floor_footprint(obs.occ, obs.origin, obs.voxel_size, float(s.room_lo[2]))
            self.vote.add(frame_vote(joints, footprint, obs.origin, obs.voxel_size, self.height,
                                     float(s.room_lo[2])) if standing else np.zeros(2))
        if s.method == "behaviour" and self.tracker is None and self.frames + 1 >= max(s.behaviour_start,
                                                                                      s.height_frames):
            self.tracker = self.behaviour_tracker()
            self.tracker.start(est, centres, colours, position)
        elif self.handback:
            self.handback -= 1
            if not self.handback:
                self.tracker.restart(est, position)
        return self._posed(est, position, joints)

    def _fit_proportions(self, est: np.ndarray) -> np.ndarray:
        """One frame of :class:`~app.pose.proportions.ProportionFit` (its nudges drawn from
        a stream of the seed, the person and the frame, so the filter's own stays as it
        is); the fit done, the person's body becomes the chosen one (the filter's particles
        kept, as when the stature grows) and the estimate is moved onto it."""
        s, fit = self.s, self.fit
        sil = self.scorer.silhouette

        def score(states, body, active):
            return self.scorer.log_weights_as(states, _flesh(self.height, s.voxel_size, s.density, body),
                                              _lut(self.height, s.voxel_size, s.density, body),
                                              _lut(self.height, s.voxel_size, s.silhouette_density, body)
                                              if sil is not None else None, active)

        fit.weigh(est, self.height, self.proportions, score, np.random.default_rng([s.seed, self.id, self.frames]))
        choice = fit.choice()
        if not fit.done or choice == self.proportions:
            return est
        moved = on_body(est, self.height, self.proportions, choice)
        keep = self.filter
        self.build(self.height, choice)
        self.filter.particles = keep.particles
        return moved

    def _behaviour(self, est: np.ndarray, position):
        """A frame the behaviour tracker posed; lost, SHBM-APF poses the next
        ``behaviour_start`` frames (``behaviour_recovery: shbm``) and the tracker restarts
        from its pose, or the tracker spreads its particles over the motion prototypes alone
        (``prototypes``, the paper's §6.3)."""
        if self.tracker.lost_now and self.s.behaviour_recovery == "shbm":
            self.handback = self.s.behaviour_start
        return self._posed(est, position)

    def behaviour_tracker(self):
        """A :class:`~app.behaviour.tracker.BehaviourTracker` of the settings for this
        person's stature, drawing from the person's random stream."""
        from app.behaviour.tracker import BehaviourTracker
        s = self.s
        return BehaviourTracker(behaviour_model(s.behaviour_model), self.height, particles=s.behaviour_particles,
                                lam=s.behaviour_lambda, evaluation=s.behaviour_evaluation, rng=self.rng,
                                temperature=s.behaviour_temperature,
                                layers=s.behaviour_layers, refine=s.behaviour_refine)

    def _posed(self, est: np.ndarray, position, joints=None) -> tuple[np.ndarray, np.ndarray]:
        """The frame's outcome: the state kept, the joints (``joints`` when the caller has
        them already) and their flags."""
        self.state = est
        self.last_position = np.asarray(position, dtype=np.float64).copy()
        self.frames += 1
        joints = self.model.joints(est) if joints is None else joints
        flags = self.switch.joint_flags() if self.switch is not None else np.ones(len(JOINTS), dtype=bool)
        return joints, flags

    def corrupt(self, state: np.ndarray) -> None:
        """Replace the filter's belief by ``state`` (a test of recovery)."""
        if self.tracker is not None:
            self.tracker.filter.reset(state)
            self.state = state.copy()
            return
        n = len(self.filter.particles)
        self.filter.particles = np.tile(state, (n, 1))
        self.state = state.copy()


@dataclass
class PoseEstimator:
    """Every person's pose, frame after frame."""

    settings: PoseSettings = field(default_factory=PoseSettings)
    people: dict = field(default_factory=dict)

    def __post_init__(self):
        self.settings.validate()
        self.rng = np.random.default_rng(self.settings.seed)

    def _pool(self):
        pool = getattr(self, "_threads", None)
        if pool is None:
            from concurrent.futures import ThreadPoolExecutor
            pool = self._threads = ThreadPoolExecutor(self.settings.threads, thread_name_prefix="pose")
        return pool

    def update(self, centres: np.ndarray, surface, ids, positions, only=None, view=None, keypoints=None,
               colours=None) -> dict:
        """``{track id: (joints (15, 3), active (15,))}`` for every track with a body
        (``only``: a predicate on track ids; the others still own their voxels);
        ``view``: the frame's :class:`~app.pose.silhouette.SilhouetteView` or None;
        ``keypoints``: ``{track id: PersonKeypoints}`` (:mod:`app.keypoints.fusion`) or None;
        ``colours``: the voxels' RGB (N, 3) (the behaviour method) or None."""
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        colours = None if (colours is None or len(colours) != len(centres)
                           or self.settings.method != "behaviour") else np.asarray(colours)
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        ids = [int(i) for i in ids]
        # who this worker poses (``only``: a pose shard's share of the tracks); the frame's
        # voxels and silhouette pixels are split among every track, but only those of these
        # people are looked for (the same owners as the full split, a fraction of the work)
        mine_k = [k for k, tid in enumerate(ids) if only is None or only(tid)]
        wanted = None if len(mine_k) == len(ids) else mine_k
        owner = assign_voxels(centres, positions, self.settings.reach, wanted)
        surface = None if surface is None or len(surface) != len(centres) else np.asarray(surface, bool)
        out = {}
        # the budget is shared by every person of the frame, whoever poses them: a pose worker
        # posing its share of the tracks (``only``) gives each of its people what one worker
        # posing everyone would (a shard that counted its own people gave each twice or three
        # times the particles, so three shards cost what one worker did: issue 26), and the
        # poses of the sharded and the single layouts are the same
        gamma = self.settings.shbm_gamma(len(ids)) if self.settings.method.startswith("shbm") else None
        spacing = self.settings.silhouette_density * self.settings.voxel_size if self.settings.silhouette_fit else 0.0
        silhouettes = view.people(positions, spacing, wanted) if view is not None and mine_k else None
        jobs = []
        for k in mine_k:
            tid = ids[k]
            person = self.people.get(tid)
            if person is None:
                person = self.people[tid] = PersonPose(self.settings, tid, np.random.default_rng(
                    [self.settings.seed, tid]))
            mine = owner == k
            jobs.append((tid, person, (centres[mine], None if surface is None else surface[mine], positions[k], gamma,
                                       None if silhouettes is None else silhouettes[k],
                                       None if keypoints is None else keypoints.get(tid),
                                       None if colours is None else colours[mine])))
        if self.settings.threads > 1 and len(jobs) > 1:
            results = list(self._pool().map(lambda job: job[1].update(*job[2]), jobs))
        else:
            results = [person.update(*args) for _, person, args in jobs]
        for (tid, _, _), res in zip(jobs, results):
            if res is not None:
                out[tid] = res
        for gone in set(self.people) - set(ids):
            del self.people[gone]
        return out
