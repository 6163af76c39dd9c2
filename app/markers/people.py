"""Every tracked person's marker-based pose, frame after frame: the pose worker's
``mode: markers`` (thesis §6.4, §6.6; issue 28). One :class:`~app.markers.tracking.MarkerTracker`
per track, fed the frame's detections of every camera.

A person's filter starts without knowing the pose (a room has no true joints): the body
model of the person's stature (the top of their voxels near the body axis, as the
markerless estimator reads it: :func:`app.pose.estimator.blob_top`) stands at the track
facing the way, of eight, whose landmarks the detections explain best (the likelihood's
cost, Eq. 6.9 plus our detections' term), and the filter runs ``acquire`` times on that
first frame from the neutral pose's spread (the arms and legs find their markers there:
2.3 cm mean joint error after 4 runs on the simulated gesture1); the same is done facing
the other way round, both are followed for ``settle`` frames and the one the detections
fit better kept (:meth:`MarkerPeople.acquire`). Until then the filter anneals at the
survival rate 0.5 (:data:`SEARCH_ALPHA`: a wider search, the body still far from its
pose), afterwards at the settings' ``alpha`` (0.3: closer to the markers once near them).
Each track draws from
its own random stream (``seed`` and the track id), so sharded pose workers give the poses
of one.

:func:`state_arrays` and :func:`restore_people` keep the filters across a pose worker's
restart (plain arrays, no pickles), like :mod:`app.pose.snapshot` does for the
markerless estimator.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

from app.files import json_entry, read_json_entry
from app.markers.likelihood import COSTS, PICKS
from app.markers.tracking import MarkerTracker
from app.pose.estimator import blob_top
from app.pose.model import N_DOF, neutral_state, stature_from_top

__all__ = ["MarkerSettings", "MarkerPeople", "pose_marker_frame", "state_arrays", "restore_people", "SnapshotError"]

FORMAT = "smartroom-marker-state/1"
YAWS = 8
WALKED = 0.15     # m from where a track was acquired: it walks, and faces the way it goes
HEADING = 1.0     # the cost a settling hypothesis facing back from that way gains a frame
SEARCH_ALPHA = 0.5   # the survival rate while a track is acquired and settles (far from its pose yet)


class SnapshotError(ValueError):
    """A marker snapshot that cannot be taken over."""


@dataclass
class MarkerSettings:
    """The pose worker's ``marker_*`` parameters (defaults: :class:`MarkerTracker`'s, tuned
    on the simulated gesture1, statures3, meeting3, crowd6, still2 and enter2)."""

    particles: int = 700        # N_pL (the thesis's best, Fig. 6.13)
    layers: int = 3             # L
    alpha: float = 0.3          # the annealing's survival rate per layer (Eq. 3.21; 0.5 the markerless filter's)
    rho: float = 20.0           # px: a landmark's detection is the nearest within rho (Eq. 6.5)
    cost: str = "both_ways"     # thesis (Eqs. 6.6-6.9), reprojection or both_ways (app.markers.likelihood)
    proposals: float = 0.2      # share of the first layer drawn from the triangulated markers' limb proposals
    explain: float = 3.0        # both_ways: weight of the detections' term
    support_px: float = 6.0     # px: a detection is supported by agreeing detections of two more views
    acquire: int = 4            # filter runs on a track's first frame
    settle: int = 10            # frames a new track is followed facing either way (0: one frame's cost picks)
    floor: float = 0.1          # m: the lower ankle's prior (app.markers.likelihood); 0 = none (the thesis)
    polish: int = 3             # Gauss-Newton steps on the estimate's markers (app.markers.polish); 0: the thesis
    polish_rounds: int = 2      # the polish's rounds, each picking the detections again
    picks: str = "exclusive"    # a detection is one landmark's pick per view (ours); nearest: Eq. 6.5 (the thesis)
    threads: int = 1            # people posed in parallel (each their own filter and random stream: same poses)
    seed: int = 0

    def validate(self) -> None:
        if self.cost not in COSTS:
            raise ValueError(f"marker_cost {self.cost!r} must be one of {', '.join(COSTS)}")
        if self.picks not in PICKS:
            raise ValueError(f"marker_picks {self.picks!r} must be one of {', '.join(PICKS)}")
        if self.particles < 20 or self.layers < 1 or self.acquire < 1 or self.rho <= 0 or self.settle < 0 \
                or self.floor < 0 or self.threads < 1 or not 0 < self.alpha < 1 or self.polish < 0 \
                or self.polish_rounds < 1:
            raise ValueError("marker particles >= 20, layers >= 1, acquire >= 1, rho > 0, settle >= 0, floor >= 0, "
                             "0 < alpha < 1, polish >= 0, polish_rounds >= 1")


def person_stature(centres: np.ndarray, voxel_size: float) -> float | None:
    """The stature (m) of a person's voxel centres (N, 3), read as the markerless estimator
    does (:class:`app.pose.estimator.PersonPose`); None for fewer than 30 voxels."""
    if len(centres) < 30:
        return None
    return stature_from_top(blob_top(centres), voxel_size)


class MarkerPeople:
    """The tracked people's marker trackers; :meth:`update` poses one frame."""

    def __init__(self, cameras, settings: MarkerSettings | None = None):
        self.cameras = list(cameras)
        self.s = settings or MarkerSettings()
        self.s.validate()
        # per track: its hypotheses [tracker, summed cost], the better first; two (facing
        # either way) for the first ``settle`` frames, then the better one
        self.people: dict[int, list[list]] = {}
        self.frames: dict[int, int] = {}
        self.starts: dict[int, np.ndarray] = {}   # the track's position when it was acquired

    def tracker(self, track: int) -> MarkerTracker:
        """The track's filter (its better hypothesis so far)."""
        return self.people[track][0][0]

    def _tracker(self, track: int, height: float) -> MarkerTracker:
        s = self.s
        return MarkerTracker(self.cameras, height, particles=s.particles, layers=s.layers, alpha=s.alpha, rho=s.rho,
                             cost=s.cost, seed=s.seed * 1_000_003 + int(track), proposals=s.proposals,
                             support_px=s.support_px, explain=s.explain, floor=s.floor, polish=s.polish,
                             picks=s.picks, polish_rounds=s.polish_rounds)

    @staticmethod
    def _cost(tracker: MarkerTracker) -> float:
        """The likelihood's cost of the tracker's estimate on the detections it last saw."""
        return float(tracker.scorer.costs(tracker.state[None])[0])

    def acquire(self, track: int, height: float, detections, position) -> list[list]:
        """The track's hypotheses started on this frame: the neutral pose at ``position``
        facing the best of :data:`YAWS` ways by the likelihood's cost, and facing the other
        way round, each fitted by ``acquire`` filter runs on the frame's detections.
        Unlabelled markers on a body at rest look alike from the front and the back (only
        bent elbows and knees, and the head's few centimetres forward, tell them apart), and
        one frame's costs often pick the wrong one: both are followed for ``settle`` frames
        and the one of the lower summed cost kept, the cost raised for facing away from the
        way the track walks once it has gone :data:`WALKED` from its start."""
        probe = self._tracker(track, height)
        costs = []
        for k in range(YAWS):
            state = neutral_state(height, (float(position[0]), float(position[1]), None), 2 * np.pi * k / YAWS)
            probe.state = state
            probe.scorer.set_detections(probe._near_person(detections))
            costs.append((self._cost(probe), k))
        best = min(costs)[1]
        hypotheses = []
        for k in (best, best + YAWS // 2):
            tracker = self._tracker(track, height)
            tracker.start(neutral_state(height, (float(position[0]), float(position[1]), None), 2 * np.pi * k / YAWS))
            tracker.filter.reset(tracker.state)   # the whole spread of the filter's diffusion
            tracker.filter.alpha = SEARCH_ALPHA   # the wider search until the track has settled
            for _ in range(self.s.acquire):
                tracker.step(detections)
            hypotheses.append([tracker, self._cost(tracker)])
        return hypotheses if self.s.settle > 0 else [min(hypotheses, key=lambda h: h[1])]

    def _step(self, track: int, detections, position) -> None:
        hypotheses = self.people[track]
        moved = np.asarray(position[:2], float) - self.starts[track][:2]
        walking = len(hypotheses) > 1 and np.hypot(*moved) > WALKED
        for h in hypotheses:
            # a settling track still searches; a settled one anneals at the settings' alpha
            h[0].filter.alpha = SEARCH_ALPHA if len(hypotheses) > 1 else self.s.alpha
            h[0].step(detections)
            h[1] += self._cost(h[0])
            if walking:   # a walking person faces the way they go (the model faces +x at yaw 0)
                h[1] += HEADING * 0.5 * (1.0 - np.cos(h[0].state[3] - np.arctan2(moved[1], moved[0])))
        hypotheses.sort(key=lambda h: h[1])   # stable: the first of equals stays first
        self.frames[track] += 1
        if self.frames[track] >= self.s.settle:
            del hypotheses[1:]

    def update(self, detections, ids, positions, centres=None, owner=None, voxel_size: float = 0.04,
               only=None) -> dict:
        """One frame: ``{track id: (joints (15, 3), active (15,))}`` for the tracks posed.

        ``detections``: per camera of :attr:`cameras`, (Q, 2) pixels; ``ids``, ``positions``
        the frame's tracks; ``centres`` the voxel centres and ``owner`` their track index
        (:func:`app.pose.estimator.assign_voxels`), for the stature of a new track (one
        without 30 voxels waits); ``only(track id)``: the tracks to pose (a share)."""
        mine = [(k, int(t)) for k, t in enumerate(ids) if only is None or only(int(t))]

        def pose_one(k: int, tid: int):
            if tid not in self.people:
                body = centres[owner == k] if centres is not None and owner is not None else np.zeros((0, 3))
                height = person_stature(body, voxel_size)
                if height is None:
                    return None
                hypotheses = self.acquire(tid, height, detections, positions[k])
                hypotheses.sort(key=lambda h: h[1])
                self.people[tid], self.frames[tid] = hypotheses, 0
                self.starts[tid] = np.asarray(positions[k], float).copy()
            else:
                self._step(tid, detections, positions[k])
            joints = self.tracker(tid).joints()
            return joints, np.ones(len(joints), dtype=bool)

        if self.s.threads > 1 and len(mine) > 1:   # each person's filter alone: the kernels release the GIL
            results = list(self._pool().map(lambda kt: pose_one(*kt), mine))
        else:
            results = [pose_one(k, tid) for k, tid in mine]
        out = {tid: r for (_, tid), r in zip(mine, results) if r is not None}
        alive = {tid for _, tid in mine}
        for tid in [t for t in self.people if t not in alive]:
            del self.people[tid], self.frames[tid], self.starts[tid]
        return out

    def _pool(self):
        if getattr(self, "_threads", None) is None:
            from concurrent.futures import ThreadPoolExecutor
            self._threads = ThreadPoolExecutor(self.s.threads, thread_name_prefix="markers")
        return self._threads


def _settings_key(s: MarkerSettings) -> str:
    """What a snapshot must have been taken with (not the threads: they change no pose)."""
    return json.dumps({k: v for k, v in asdict(s).items() if k != "threads"}, sort_keys=True)


def state_arrays(people: MarkerPeople) -> dict[str, np.ndarray]:
    """Every person's filters as named arrays (stature, summed cost, state, particles,
    random stream of each hypothesis)."""
    arrays: dict[str, np.ndarray] = {}
    entries = []
    for tid, hypotheses in people.people.items():
        entry = {"id": int(tid), "frames": int(people.frames[tid]), "hypotheses": [],
                 "start": [float(v) for v in people.starts[tid]]}
        for n, (tr, cost) in enumerate(hypotheses):
            entry["hypotheses"].append({"height": float(tr.model.height), "cost": float(cost),
                                        "rng": tr.filter.rng.bit_generator.state})
            arrays[f"m{tid}.{n}.state"] = np.asarray(tr.state, np.float64)
            arrays[f"m{tid}.{n}.particles"] = np.asarray(tr.filter.particles, np.float64)
        entries.append(entry)
    arrays["markers"] = json_entry({"format": FORMAT, "settings": _settings_key(people.s), "people": entries})
    return arrays


def restore_people(cameras, settings: MarkerSettings, arrays) -> MarkerPeople:
    """The :class:`MarkerPeople` of a :func:`state_arrays` snapshot; :class:`SnapshotError`
    when it does not fit (another format or settings, missing or malformed arrays)."""
    try:
        head = read_json_entry(arrays, "markers")
    except (KeyError, ValueError, TypeError) as exc:
        raise SnapshotError(f"marker snapshot: {exc}") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise SnapshotError("marker snapshot: another format")
    if head.get("settings") != _settings_key(settings):
        raise SnapshotError("marker snapshot: taken with other settings")
    people = MarkerPeople(cameras, settings)
    try:
        for e in head["people"]:
            tid, hypotheses = int(e["id"]), []
            if not e["hypotheses"]:
                raise ValueError(f"track {tid}: no hypothesis")
            for n, h in enumerate(e["hypotheses"]):
                height = float(h["height"])
                if not 1.0 <= height <= 2.5:
                    raise ValueError(f"stature {height}")
                tr = people._tracker(tid, height)
                state = np.asarray(arrays[f"m{tid}.{n}.state"], np.float64)
                particles = np.asarray(arrays[f"m{tid}.{n}.particles"], np.float64)
                if state.shape != (N_DOF,) or particles.shape != (settings.particles, N_DOF) or \
                        not (np.isfinite(state).all() and np.isfinite(particles).all()):
                    raise ValueError(f"track {tid}: arrays of shapes {state.shape}, {particles.shape}")
                tr.state, tr.filter.particles = state, particles
                tr.filter.rng.bit_generator.state = h["rng"]
                hypotheses.append([tr, float(h["cost"])])
            start = np.asarray(e["start"], np.float64)
            if start.shape != (3,) or not np.isfinite(start).all():
                raise ValueError(f"track {tid}: start {e['start']!r}")
            people.people[tid], people.frames[tid] = hypotheses, int(e["frames"])
            people.starts[tid] = start
    except (KeyError, ValueError, TypeError) as exc:
        raise SnapshotError(f"marker snapshot: {exc}") from None
    return people


def pose_marker_frame(people: MarkerPeople, vox, ids, positions, detections: dict, reach: float,
                      only=None) -> dict:
    """One frame as the pose worker poses it in marker mode: ``detections`` ``{camera:
    (Q, 2)}`` (a camera missing: none), ``vox`` the frame's :class:`~app.messages.Voxels`
    (its consensus voxels, :data:`~app.messages.Voxels.misses` 0, give new tracks their
    stature)."""
    from app.pose.estimator import assign_voxels

    centres = owner = None
    if any(int(t) not in people.people and (only is None or only(int(t))) for t in ids):   # a new track's stature
        centres = vox.centres()
        if vox.misses is not None and len(vox.misses) == len(centres) and len(vox.cameras) > 1:
            centres = centres[np.asarray(vox.misses) == 0]
        owner = assign_voxels(centres, positions, reach)
    per_camera = [np.asarray(detections.get(c.name, np.zeros((0, 2))), np.float64).reshape(-1, 2)
                  for c in people.cameras]
    return people.update(per_camera, ids, positions, centres, owner, float(vox.voxel_size), only=only)
