"""Marker-based motion capture of one person: the annealed particle filter (§3.2,
:class:`app.pose.filters.APF`) over the body model's 27-DoF state, weighted by the
marker likelihood of §6.4.1.2 (:class:`app.markers.likelihood.MarkerScorer`). The
thesis's best setting (§6.6.1, Fig. 6.13): L = 3 layers of N_pL = 700 particles.

:func:`fit_state` poses the body model on 3D joints by least squares (the start of a
track: the true joints on simulated clips, triangulated markers in a room).
"""
from __future__ import annotations

import numpy as np

from app.markers.likelihood import MarkerScorer
from app.markers.polish import polish
from app.markers.proposals import LimbProposals, agreed_points
from app.pose.filters import APF
from app.pose.model import LIMITS_HI, LIMITS_LO, BodyModel, neutral_state

__all__ = ["MarkerTracker", "fit_state"]


def fit_state(height: float, joints: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """The state (27,) of a body model of ``height`` whose joints best match ``joints`` (15, 3)."""
    from scipy.optimize import least_squares

    model = BodyModel(height)
    joints = np.asarray(joints, float)
    if start is None:
        pelvis = joints[0]
        across = joints[12] - joints[9]          # r_hip - l_hip
        yaw = float(np.arctan2(across[1], across[0])) + np.pi / 2   # the model faces +x at yaw 0 (left +y)
        start = neutral_state(height, (pelvis[0], pelvis[1], pelvis[2]), yaw)
    lo = np.where(np.isfinite(LIMITS_LO), LIMITS_LO, -1e3)
    hi = np.where(np.isfinite(LIMITS_HI), LIMITS_HI, 1e3)
    x0 = np.clip(start, lo + 1e-6, hi - 1e-6)
    best = None
    for turn in (0.0, np.pi):                    # the yaw guess may face the wrong way
        x = x0.copy()
        x[3] += turn
        x = np.clip(x, lo + 1e-6, hi - 1e-6)
        r = least_squares(lambda s: (model.joints(s) - joints).ravel(), x, bounds=(lo, hi))
        if best is None or r.cost < best.cost:
            best = r
    return best.x


REACH = 0.8              # m: how far beyond its last pose a person's markers are looked for
CANDIDATE_RADIUS = 0.03   # m: triangulations of one marker from different pairs of views agree this well
POLISH_FOLLOW = 0.5       # share of the polish's correction the particles take into the next frame


class MarkerTracker:
    """One person's pose from frames of marker detections (per camera (Q_n, 2) pixels).

    Defaults (tuned on the simulated gesture1, statures3, meeting3, crowd6, still2 and
    enter2; reported on walk1 and occluded1, docs/benchmarks.md): our likelihood
    (``cost="both_ways"``, the detections' term weighted ``explain = 3``; the thesis's is
    ``cost="thesis"``), ``rho`` 20 px, detections supported within ``support_px`` 6 px,
    limb proposals for a fifth of the first layer (``proposals``; 0: the plain APF), and a
    survival rate ``alpha`` of 0.3 per layer (Eq. 3.21; with it the diffusion shrinks as
    ``alpha^m``, Eq. 3.22): with only three layers the filter settles closer to the markers
    than at the markerless estimator's 0.5 (tuning scenes, six filter seeds: MMTA 0.908 ->
    0.918, MMTP 28.8 -> 25.3 mm; 0.5 stays selectable). The estimate is then polished by
    ``polish`` (3) Gauss-Newton steps on the markers it found (:mod:`app.markers.polish`;
    0: the thesis's estimate), and the particles take :data:`POLISH_FOLLOW` of that
    correction into the next frame (tuning, six seeds: MMTA 0.918 -> 0.950, MMTP 25.3 ->
    16.2 mm; the estimate alone polished: 0.917, one run lost its person). Last, each
    detection is the pick of one landmark per view (``picks="exclusive"``; the thesis's
    ``"nearest"`` lets a limb whose markers are hidden sit on another landmark's) and the
    polish picks again for a second round of steps (``polish_rounds`` 2): tuning, six
    seeds, MMTA 0.943 -> 0.967 (exclusive alone 0.958, two rounds alone 0.947)."""

    def __init__(self, cameras, height: float, particles: int = 700, layers: int = 3, rho: float = 20.0,
                 sigma: float = 1.0, cost: str = "both_ways", alpha: float = 0.3, seed: int = 0,
                 proposals: float = 0.2, support_px: float = 6.0, explain: float = 3.0, floor: float = 0.1,
                 polish: int = 3, picks: str = "exclusive", polish_rounds: int = 2):
        self.model = BodyModel(height)
        self.scorer = MarkerScorer(cameras, height, rho=rho, sigma=sigma, cost=cost, candidates=proposals > 0,
                                   support_px=support_px, explain=explain, picks=picks)
        self.scorer.floor = float(floor)
        self.filter = APF(particles=particles, layers=layers, alpha=alpha, rng=np.random.default_rng(seed),
                          importance_fraction=proposals)
        self.polish = int(polish)
        self.polish_rounds = int(polish_rounds)
        self.state: np.ndarray | None = None

    def start(self, state: np.ndarray) -> None:
        self.state = np.asarray(state, float).copy()
        self.filter.reset(self.state, spread=0.25 * self.filter.sigma0)

    def step(self, detections) -> np.ndarray:
        """One frame: the estimated state (27,)."""
        if self.state is None:
            raise RuntimeError("MarkerTracker.start() first")
        self.scorer.set_detections(self._near_person(detections))
        estimate = self.filter.step(self.scorer, importance=self._proposals())
        self.state = polish(estimate, self.scorer, self.polish, rounds=self.polish_rounds)
        if self.polish:   # the cloud goes part of the way with the polished estimate
            self.filter.particles = self.filter.particles + POLISH_FOLLOW * (self.state - estimate)
        return self.state

    def _near_person(self, detections) -> list:
        """Per camera, the detections in the box around the person's last pose, widened by
        ``REACH`` metres at the person's depth (others' markers farther away cannot be this
        person's; the likelihood's cost grows with the detections it searches)."""
        X = self.model.joints(self.state)
        out = []
        for cam, d in zip(self.scorer.cameras, detections):
            d = np.asarray(d, float).reshape(-1, 2)
            uv, z = cam.project(X, return_depth=True)
            ok = np.isfinite(uv).all(axis=1) & (z > 0.1)
            if not ok.any() or not len(d):
                out.append(d)
                continue
            margin = REACH * cam.K[0, 0] / float(np.median(z[ok]))
            lo, hi = uv[ok].min(axis=0) - margin, uv[ok].max(axis=0) + margin
            out.append(d[np.all((d >= lo) & (d <= hi), axis=1)])
        return out

    def _proposals(self):
        """The limb proposals (:mod:`app.markers.proposals`) of this frame's supported
        detections around the person's last pose; None without candidates."""
        if self.filter.importance_fraction <= 0 or not (len(self.scorer.points) or len(self.scorer.pair_points)):
            return None
        return LimbProposals.of(agreed_points(self.scorer.points, CANDIDATE_RADIUS), self.model.joints(self.state),
                                self.model.height, float(self.state[3]), self.scorer.pair_points)

    def joints(self) -> np.ndarray:
        return self.model.joints(self.state)
