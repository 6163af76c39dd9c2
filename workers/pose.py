"""Pose worker: the articulated pose of every tracked person (thesis Ch. 6-7) from a
frame's voxels and tracks; publishes :class:`~app.messages.Poses` (the recorder writes
``poses.jsonl``, the viewer draws skeletons).

Voxels and tracks of one frame arrive on their own keys (tracks later: they are made
from the voxels); the worker keeps the last few of each by frame and poses a frame as
soon as both are in. One filter per track (:class:`app.pose.estimator.PoseEstimator`);
each person's likelihood ignores the voxels owned by the other tracks. More people than
one worker carries in real time is a layout matter: several pose workers, each with
``share: [k, n]`` (the track ids with ``id % n == k``), and/or
``threads`` (people posed in parallel within the worker: the kernels release the GIL).
Each person draws from their own random stream and SHBM-APF's ``gamma_budget`` is shared
by every person of the frame, whoever poses them, so the poses of a sharded or threaded
layout are those of one worker, to the bit (``deploy/layouts/many_cores.yaml``, issue 26).

``method``: ``shbm`` (SHBM-APF, §7.3, default), ``apf`` (§6.5), ``ddm`` (APF with DDM
limb switching, §7.4), ``shbm+ddm`` or ``behaviour`` (Caillette's learnt behaviour model
and coloured Gaussian blobs, :mod:`app.behaviour`, docs/behaviour.md: ``behaviour_*``;
the voxels' colours are its evidence, so the reconstruction should colour them); ``density`` is the model's density factor
(Eq. 6.26); ``likelihood`` ``partitioned`` (Eqs. 6.23-6.25) or ``global`` (6.17-6.22);
``coverage``, ``floor``, ``heading`` and ``ik`` the additions for visual hulls
(:mod:`app.pose.coverage`, :mod:`app.pose.detections`; ``coverage: 0, floor: 0,
heading: 0, ik: straight`` is the thesis's likelihood with the earlier proposals).

``voxels``: ``consensus`` (default) poses every person on the voxels every camera of the
frame calls foreground (``Voxels.misses == 0``: the ``k = 0`` subset of the pipeline's
``k = 1`` hull, 1.4-2x the body instead of 5-7x, :mod:`app.reconstruction.consensus`),
their surface recomputed from the subset (``surface``: ``outer``, the occupied voxels next
to empty space reachable from outside, or ``boundary``, every voxel with an empty
6-neighbour; :mod:`app.pose.observation`) (the reconstruction's
visibility flags are the surface of the whole hull); ``all`` the whole hull with its
flags (the thesis: one hull for everything). The tracks still come from the whole hull
(the tracker and its person classifier need it). Voxels without ``misses`` (an older
reconstruction, ``misses: false``) are posed whole. ``tolerant`` is the consensus plus
the one-miss voxels below ``tolerant_low`` (m) within ``tolerant_near`` (m) of a track, in
frames where at least ``tolerant_views`` cameras still see them (the shins and feet the
consensus carves; :mod:`app.pose.selection`).

``silhouette`` (sigma^2; 0 = off) adds the silhouette term of :mod:`app.pose.silhouette`: the
reconstruction sends the frame's masks, reduced, with the voxels (its ``silhouettes``
parameter), and each person's model is also scored by how much of that person's
silhouettes in every camera its projection covers, which holds the limbs that one
camera's mask carves from the consensus voxels. The worker then needs the run's
calibration (the recording's, or ``--calibration``); voxels without silhouettes are posed
without the term (one warning).

``keypoints`` (sigma, m; 0 = off) fuses a learned detector's 2D body keypoints
(:mod:`app.keypoints.fusion`, issue 23): the layout's keypoints workers
(:mod:`workers.keypoints`) send every tracked person's keypoints in their cameras, the
worker waits for all of them with the voxels and tracks of a frame, and each person's
model is also scored by the distance of its joints to the keypoints' viewing rays; the
wrists triangulated from them are the importance function's hands
(``keypoint_hands``). It needs the run's calibration, and a keypoints worker in the
layout (``deploy/layouts/keypoints.yaml``).

``mode: markers`` is marker-based capture (thesis §6.4, §6.6, :mod:`app.markers.people`,
docs/markers.md): each person's pose is fitted by the annealed particle filter to the
colour markers the layout's markers workers (or segmentation workers with a ``markers``
model) detect in every camera of the frame; the voxels only give a new track its stature.
A frame waits for every camera's markers as for its voxels and tracks. ``marker_*`` are
:class:`~app.markers.people.MarkerSettings`. The output is the same ``Poses``.

A restarted pose worker carries every person's filter on: the estimator's state
(:mod:`app.pose.snapshot`) is saved with the frame it belongs to every
``snapshot_frames`` frames (and with the worker's state); the next incarnation restores
it with the first voxels and poses, without publishing, the frames its earlier
incarnation put out after the snapshot (the voxels and tracks sent again after the
restart, :meth:`Worker.catch_up`). Offline the poses are then those of an undisturbed
run, byte for byte.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.errors import InputError
from app.frame_shares import frame_share, owns, valid_share
from app.messages import Keypoints, Markers, Poses, Tracks, Voxels
from app.pose.selection import pose_frame
from workers.base import RECENT_FRAMES, Worker
from workers.restarts import REPLAY_FRAMES

KEEP_FRAMES = 8
CUE_FRAMES = "cue_frames"   # the state arrays' counts of frames posed with markers, keypoints, silhouettes


class Pose(Worker):
    KIND = "pose"
    ORDER = 5
    CONSUMES = ("voxels", "tracks")
    PRODUCES = ("poses",)
    ACCEPTS = (Voxels, Tracks, Keypoints, Markers)
    INBOX_DEPTH = 4
    ACK_ON_HANDLE = False   # a frame is finished once posed (its voxels and tracks are both in)
    DEFAULTS = {
        "mode": "markerless",       # markerless (voxels, Ch. 6-7) or markers (coloured markers, §6.4)
        "marker_particles": 700,    # markers: N_pL (app.markers.people.MarkerSettings)
        "marker_layers": 3,         # markers: L
        "marker_alpha": 0.3,        # markers: the annealing's survival rate per layer (Eq. 3.21)
        "marker_rho": 20.0,         # markers: px, a landmark's detection is the nearest within rho (Eq. 6.5)
        "marker_cost": "both_ways",  # markers: thesis (Eqs. 6.6-6.9), reprojection or both_ways
        "marker_proposals": 0.2,    # markers: share of the first layer from the triangulated markers
        "marker_acquire": 4,        # markers: filter runs on a track's first frame
        "marker_settle": 10,        # markers: frames a new track is followed facing either way
        "marker_floor": 0.1,        # markers: m, the lower ankle's floor prior; 0 = none (the thesis)
        "marker_polish": 3,         # markers: Gauss-Newton steps on the estimate's markers; 0 = none (the thesis)
        "marker_polish_rounds": 2,  # markers: the polish's rounds, each picking the detections again
        "marker_picks": "exclusive",  # markers: a detection is one landmark's pick per view; nearest (the thesis)
        "method": "shbm",           # shbm, apf, ddm, shbm+ddm, behaviour (Caillette's tracker, app.behaviour)
        "behaviour_start": 10,      # behaviour: a track's first frames posed by SHBM-APF, whose pose teaches the blobs
        "behaviour_particles": 500,  # behaviour: particles
        "behaviour_lambda": 0.5,    # behaviour: the local dynamics' noise attenuation (Eq. 4)
        "behaviour_evaluation": "model",  # behaviour: model (SHBM-APF's likelihood, annealed; ours), kl (the paper's
                                    # blob fit and relative entropy) or voxels (the voxels' likelihood under the blobs)
        "behaviour_layers": 3,      # behaviour, model: annealing layers about the prediction (1: the paper's SIR)
        "behaviour_refine": 0.25,   # behaviour, model: their diffusion, times the APF's sigma_0
        "behaviour_temperature": 20.0,  # behaviour, voxels: log-weight = this x the voxels' mean log-likelihood
        "behaviour_recovery": "shbm",  # behaviour lost: SHBM-APF finds the person again (shbm; ours) or the motion
                                    # prototypes alone (prototypes, the paper's §6.3)
        "behaviour_model": "",      # behaviour: the model file (smartroom train behaviour); "" = the shipped one
        "density": 2.0,             # delta of Eq. 6.26 (1 = the data's voxel size)
        "likelihood": "partitioned",  # or global
        "particles": 600,           # APF: particles per layer
        "layers": 6,                # APF: annealing layers
        "gamma": 50,                # SHBM-APF: particles per new DoF (Eq. 7.28)
        "gamma_budget": 75,         # SHBM-APF: gamma shared by the people posed in a frame (min gamma, >= gamma_min
                                    # each: 1 person 50, 2: 37, 3: 25); 0 = gamma for everyone (thesis)
        "gamma_min": 20,
        "importance_fraction": 0.35,  # IAPF: first-layer particles drawn from the detections (0.2 before round 2 of
                                      # issue 11: through the pipeline 0.35 gains on gesture1, walk1 and meeting3;
                                      # on true-body voxels, app.pose.estimator's 0.2 is better; docs/history/
                                      # pose-likelihood.md)
        "coverage": 0.003,          # sigma^2 of the coverage term for fat hulls (app.pose.coverage); 0 = thesis
        "coverage_partial": True,   # coverage also on SHBM-APF's partial models
        "floor": 0.02,              # m: floor prior on the lower ankle; 0 = none (thesis)
        "feet": 0.05,               # m: floor prior on the higher ankle too while the track stands; 0 = lower only
        "heading": 0.6,             # rad: yaw prior along the track's walking direction; 0 = none (thesis)
        "toes": 0.0,                # rad: yaw prior along the way the feet point while not walking (app.pose.facing);
                                    # 0 = none (the thesis)
        "ik": "table",              # IAPF arm proposals: table (look-up inverse kinematics) or straight
        "reach": 0.9,               # m: voxels farther from every track belong to nobody
        "share": None,              # [k, n]: pose the tracks with id % n == k (several pose workers)
        "surface": "outer",         # V^S of the consensus subset: outer (no enclosed cavities) or boundary (earlier)
        "stature": "axis",          # the blob's top for the stature: near the body axis, or top (anywhere; earlier)
        "proportions": "average",   # limb lengths: the stature's average fractions (the thesis), or fit: legs and arms
                                    # weighed on the person's voxels over their first proportion_frames
                                    # (app.pose.proportions)
        "proportion_frames": 40,
        "stance": 0.03,             # m: ankles under the hips while the track stands still; 0 = off
        "ground": 0.01,             # m: no ankle below its standing height (with floor > 0); 0 = off (the offline
                                    # core's default: on true-body voxels it costs gesture1 0.01;
                                    # docs/history/pose-likelihood.md)
        "anchor": 0.05,             # m: deviation of the root beyond anchor_free from its track; 0 = off (meeting3
                                    # 3 seeds 0.822 -> 0.842: the door phantom; gesture1, walk1 identical)
        "anchor_free": 0.25,        # m
        "crown": 0.015,             # m: the head no lower than the top of the person's voxels says (app.pose.coverage;
                                    # tuning seeds 0-15 MMTA 0.721 -> 0.758, docs/benchmarks.md); 0 = off
        "voxels": "consensus",      # consensus: the voxels no camera misses (Voxels.misses == 0); all: the hull;
                                    # tolerant: consensus + low one-miss voxels near a track (app.pose.selection)
        "tolerant_low": 0.2,        # m: tolerant keeps one-miss voxels below this height
        "tolerant_near": 0.6,       # m: ... within this distance (floor plane) of a track
        "tolerant_views": 3,        # ... where at least this many cameras see them (frames of >= views + 1 cameras)
        "silhouette": 0.0005,       # sigma^2 of the silhouette term (the masks the voxels carry, app.pose.silhouette;
                                    # walk1 2 cm MMTA 0.877 -> 0.92, meeting3 0.84 -> 0.86, docs/benchmarks.md, Pose);
                                    # 0 = off (the thesis)
        "silhouette_density": 2.0,  # the model's points for the term on a lattice of this many voxel sizes (about a
                                    # pixel of the silhouettes the reconstruction sends)
        "silhouette_reach": 0.6,    # m: a silhouette pixel is a person's when its ray passes this near only that track
        "silhouette_fit": True,     # silhouettes coarsened per person to the model points' lattice at its depth
                                    # (rho_Sil independent of the camera's distance and resolution); False: as sent
        "keypoints": 0.0,           # m: sigma of the 2D keypoint term (app.keypoints.fusion; the layout's keypoints
                                    # workers send them); 0 = off
        "keypoint_gate": 0.3,       # m: a keypoint's error is truncated here
        "keypoint_conf": 0.5,       # keypoints less sure than this cost nothing
        "keypoint_hands": True,     # triangulated wrists are the importance function's hands
        "low_legs": 0.5,            # importance draws with a lowered root whose legs reach the floor bent (a person
                                    # sitting down); 0 = off (legs near standing, the earlier proposal)
        "threads": 1,               # people posed in parallel by this many threads in the worker (issue 26)
        "snapshot_frames": 4,       # the estimator's state is saved every this many frames (and every 0.5 s)
        "seed": 0,
    }
    CHOICES = {"mode": ("markerless", "markers"), "marker_cost": ("thesis", "reprojection", "both_ways"),
               "marker_picks": ("nearest", "exclusive"),
               "method": ("shbm", "apf", "ddm", "shbm+ddm", "behaviour"), "likelihood": ("partitioned", "global"),
               "behaviour_evaluation": ("model", "kl", "voxels"), "behaviour_recovery": ("shbm", "prototypes"),
               "ik": ("table", "straight"), "voxels": ("consensus", "tolerant", "all"),
               "surface": ("outer", "boundary"), "stature": ("axis", "top"), "proportions": ("average", "fit")}
    RANGES = {"density": (1.0, 4.0), "particles": (20, 5000), "layers": (1, 12), "gamma": (2, 500),
              "gamma_budget": (0, 5000), "gamma_min": (2, 500), "proportion_frames": (1, 10000),
              "importance_fraction": (0.0, 1.0), "low_legs": (0.0, 1.0), "reach": (0.2, 3.0), "coverage": (0.0, 10.0),
              "floor": (0.0, 10.0),
              "heading": (0.0, 10.0), "toes": (0.0, 10.0), "feet": (0.0, 10.0), "stance": (0.0, 10.0),
              "ground": (0.0, 10.0),
              "anchor": (0.0, 10.0), "anchor_free": (0.0, 3.0), "crown": (0.0, 10.0),
              "tolerant_low": (0.0, 3.0), "tolerant_near": (0.0, 3.0), "tolerant_views": (1, 64),
              "silhouette": (0.0, 10.0), "silhouette_density": (0.5, 8.0), "silhouette_reach": (0.05, 3.0),
              "keypoints": (0.0, 10.0), "keypoint_gate": (0.01, 10.0), "keypoint_conf": (0.0, 1.0),
              "snapshot_frames": (1, 1000), "threads": (1, 64),
              "behaviour_start": (1, 1000), "behaviour_particles": (10, 20000), "behaviour_lambda": (0.0, 5.0),
              "behaviour_layers": (1, 12), "behaviour_refine": (0.0, 10.0), "behaviour_temperature": (0.0, 1e4),
              "marker_particles": (20, 20000), "marker_layers": (1, 20), "marker_alpha": (0.05, 0.95),
              "marker_rho": (1.0, 500.0), "marker_proposals": (0.0, 1.0), "marker_acquire": (1, 50),
              "marker_settle": (0, 1000), "marker_floor": (0.0, 10.0), "marker_polish": (0, 50),
              "marker_polish_rounds": (1, 10)}

    @classmethod
    def consumes(cls, spec) -> set[str]:
        """Voxels and tracks; the keypoints too when the keypoint term is on, the markers in
        marker mode."""
        on = float(spec.params.get("keypoints", 0) or 0) > 0
        markers = spec.params.get("mode") == "markers"
        extra = {"markers"} if markers else ({"keypoints"} if on else set())
        return set(cls.CONSUMES) | extra

    def setup(self) -> None:
        from app.pose.estimator import PoseSettings
        p = self.params
        try:
            self.settings = PoseSettings.from_params(p)
            self.settings.validate()
        except (TypeError, ValueError) as exc:
            raise InputError(f"pose: {exc}") from None
        share = p.get("share")
        if share is not None and not valid_share(share):
            raise InputError(f"pose: share must be [k, n] with 0 <= k < n, got {share!r}")
        self.share = frame_share(p)   # (k, n) of the track ids, or None
        self.marker_people = None
        self.markers: dict[int, dict[str, np.ndarray]] = {}
        self.markers_newest: dict[str, int] = {}   # the newest frame of each camera's markers
        self.marker_frames = [0, 0]   # frames posed with every camera's markers, frames posed
        markers = p.get("mode") == "markers"
        # the silhouette term projects the model into the cameras the voxels were carved from,
        # the keypoint term and marker mode into every camera of the run
        self.calibration = self.run_calibration() if (markers or self.settings.silhouette > 0
                                                      or self.settings.keypoints > 0) else None
        if markers:
            self._setup_markers()
        # the keypoints of a frame come from every keypoints worker of the layout
        from workers import producers_of
        self.keypoint_workers = set(producers_of(self.layout, "keypoints")) if self.settings.keypoints > 0 else set()
        if self.settings.keypoints > 0 and not self.keypoint_workers:
            raise InputError("pose: keypoints > 0 but the layout has no keypoints worker (kind: keypoints)")
        if self.settings.keypoints > 0 and self.calibration is None:
            raise InputError("pose: the keypoint term needs the run's calibration (the recording's, or --calibration)")
        self.keypoints: dict[int, dict[str, Keypoints]] = {}
        self.keypoints_newest: dict[str, int] = {}   # the newest frame each keypoints worker sent
        self.keypoint_frames = [0, 0]   # frames posed with keypoints of some person, frames posed
        self.silhouette_frames = [0, 0]   # frames posed with silhouettes, frames posed
        self.estimator = None
        self.grid = None
        self.voxels: dict[int, Voxels] = {}
        self.tracks: dict[int, Tracks] = {}
        self.done = -1
        self.people_counts: deque = deque(maxlen=RECENT_FRAMES)
        self.kept: deque = deque(maxlen=RECENT_FRAMES)    # share of the frame's voxels posed on (consensus)
        self.at = None                 # (epoch, frame, t, grid) of the last frame the estimator took in
        self.saved_at = None           # ... of the last snapshot saved
        self.catching = False          # restored: posing the frames put out before, unpublished
        from app.pose.model import BodyModel
        BodyModel(1.75).joints(np.zeros(27))   # compile (or load) the kernels before the first frame
        from app.pose.estimator import assign_voxels
        assign_voxels(np.zeros((1, 3)), np.zeros((1, 3)), 1.0)
        if markers:
            return   # the markerless filters' terms and tables are not used
        if self.settings.silhouette > 0:
            from app.pose.silhouette import warm_up
            warm_up()
        if self.settings.ik == "table":
            from app.pose.detections import arm_table
            arm_table("l"), arm_table("r")      # the inverse-kinematics tables, before the first frame
        if self.settings.method == "behaviour":
            from app.pose.estimator import behaviour_model
            behaviour_model(self.settings.behaviour_model)   # an unreadable model file: a clear error now

    def _marker_settings(self):
        from app.markers.people import MarkerSettings
        p = self.params
        return MarkerSettings(particles=int(p["marker_particles"]), layers=int(p["marker_layers"]),
                              alpha=float(p["marker_alpha"]), rho=float(p["marker_rho"]), cost=str(p["marker_cost"]),
                              proposals=float(p["marker_proposals"]), acquire=int(p["marker_acquire"]),
                              settle=int(p["marker_settle"]), floor=float(p["marker_floor"]),
                              polish=int(p["marker_polish"]), polish_rounds=int(p["marker_polish_rounds"]),
                              picks=str(p["marker_picks"]), seed=int(p["seed"]), threads=int(p["threads"]))

    def _setup_markers(self) -> None:
        """Marker mode: the run's cameras, a detector in the layout, the kernels compiled."""
        from app.markers.people import MarkerPeople
        from workers import producers_of
        if not producers_of(self.layout, "markers"):
            raise InputError("pose: mode markers but the layout detects no markers (a markers worker, or a "
                             "segmentation worker with a markers model: deploy/layouts/markers.yaml)")
        if self.calibration is None:
            raise InputError("pose: mode markers needs the run's calibration (the recording's, or --calibration)")
        self.marker_people = MarkerPeople(self.calibration.cameras, self._marker_settings())
        warm = MarkerPeople(self.calibration.cameras[:2], self._marker_settings())
        warm.s.particles, warm.s.acquire = 20, 1
        blob = np.random.default_rng(0).uniform([-.2, -.2, 0], [.2, .2, 1.7], (40, 3))
        warm.update([np.zeros((0, 2)), np.zeros((0, 2))], [0], np.zeros((1, 3)), blob, np.zeros(40, np.int64))

    def admit(self, key: str, msg) -> str | None:
        if isinstance(msg, Markers) and (self.marker_people is None
                                         or msg.camera not in self.calibration.names):
            return "unknown camera" if self.marker_people is not None else "markers outside marker mode"
        return None

    @staticmethod
    def _grid(msg: Voxels) -> tuple:
        return (round(float(msg.voxel_size), 6), tuple(float(v) for v in msg.origin), tuple(int(d) for d in msg.dims))

    def _settings_for(self, grid: tuple):
        s = self.settings
        s.voxel_size = grid[0]
        s.room_lo = tuple(grid[1])
        s.room_hi = tuple(np.asarray(grid[1]) + np.asarray(grid[2]) * grid[0])
        return s

    def _estimator(self, msg: Voxels):
        from app.pose.estimator import PoseEstimator
        grid = self._grid(msg)
        if grid != self.grid:
            self.estimator = PoseEstimator(self._settings_for(grid))
            self.grid = grid
        return self.estimator

    def new_epoch(self, epoch: int) -> None:
        self.done = -1
        self.voxels.clear()
        self.tracks.clear()
        self.keypoints.clear()
        self.keypoints_newest.clear()
        self.markers.clear()
        self.markers_newest.clear()
        self._take_over(None)   # a snapshot belongs to its epoch's frame numbers
        self.catching = False

    # -- the earlier incarnation's estimator ------------------------------------------
    def _take_over(self, msg: Voxels | None) -> None:
        """Restore the earlier incarnation's estimator if its snapshot fits this stream
        (epoch, grid, settings); otherwise say why, once, and start afresh."""
        if not self.earlier_pending:
            return
        grid = self._grid(msg) if msg is not None else None
        earlier = self.earlier_arrays(msg, "the pose filters", grid=grid)
        if earlier is None:
            return
        from app.pose.snapshot import SnapshotError, restore_estimator
        arrays, mine = earlier
        frame = mine["frame"]
        try:
            if self.marker_people is not None:
                from app.markers.people import restore_people
                est = self.marker_people = restore_people(self.calibration.cameras, self._marker_settings(),
                                                          arrays)
            else:
                est = restore_estimator(self._settings_for(grid), arrays)
        except (SnapshotError, ValueError) as exc:
            self.log.warning("%s: the pose filters start afresh", exc)
            return
        if self.marker_people is None:
            self.estimator = est
        self._restore_cue_frames(arrays)
        self.grid, self.done = grid, frame
        self.at = self.saved_at = (mine["epoch"], frame, mine["t"], grid)
        self.catching = True
        for d in (self.voxels, self.tracks):
            for f in [f for f in d if f <= frame]:
                del d[f]
        self.log.warning("pose estimator restored at frame %d: people %s", frame, sorted(est.people))

    def state_arrays(self) -> dict | None:
        people = getattr(self, "marker_people", None)
        if getattr(self, "at", None) is None or self.at == self.saved_at or (self.estimator is None and people is None):
            return None
        epoch, frame, t, grid = self.at
        self.saved_at = self.at
        if people is not None:
            from app.markers.people import state_arrays
            arrays = state_arrays(people)
        else:
            from app.pose.snapshot import estimator_state
            arrays = estimator_state(self.estimator)
        arrays[CUE_FRAMES] = np.array(self.marker_frames + self.keypoint_frames + self.silhouette_frames, np.int64)
        return self.stamp_arrays(arrays, epoch, frame, t, grid=grid)

    def _restore_cue_frames(self, arrays) -> None:
        """The counts of frames posed with each cue up to the snapshot's frame (the
        frames caught up on after it add theirs), so the figures cover every incarnation."""
        counts = arrays.get(CUE_FRAMES)
        if counts is None or counts.shape != (6,) or counts.dtype.kind not in "iu":
            return
        c = [max(0, int(v)) for v in counts]
        self.marker_frames, self.keypoint_frames, self.silhouette_frames = c[0:2], c[2:4], c[4:6]

    # -- frames ------------------------------------------------------------------------
    def catch_up(self, key: str, msg) -> None:
        """Voxels or tracks of a frame the earlier incarnation put out: the restored
        estimator poses it (if its snapshot is older), nothing is published."""
        if isinstance(msg, Voxels):
            self._take_over(msg)
        elif self.earlier_pending:   # tracks (keypoints) before the first voxels: kept for then
            self._store(msg)
            for d in (self.tracks, self.keypoints, self.markers):
                for f in sorted(d)[:-(KEEP_FRAMES + REPLAY_FRAMES)]:
                    del d[f]
            return
        if self.catching and self.at is not None and msg.epoch == self.at[0]:
            self._receive(msg)

    def handle(self, key: str, msg) -> None:   # validated by the base
        if isinstance(msg, Voxels):
            self._take_over(msg)
        self._receive(msg)

    def _store(self, msg) -> None:
        if isinstance(msg, Markers):
            if self.marker_people is not None:
                self.markers.setdefault(msg.frame, {})[msg.camera] = msg.points
                self.markers_newest[msg.camera] = max(msg.frame, self.markers_newest.get(msg.camera, -1))
        elif isinstance(msg, Keypoints):
            if self.settings.keypoints > 0 and msg.worker in self.keypoint_workers:
                self.keypoints.setdefault(msg.frame, {})[msg.worker] = msg
                self.keypoints_newest[msg.worker] = max(msg.frame, self.keypoints_newest.get(msg.worker, -1))
        else:
            (self.voxels if isinstance(msg, Voxels) else self.tracks)[msg.frame] = msg

    def _receive(self, msg) -> None:
        if msg.frame <= self.done:
            return
        self._store(msg)
        keep = KEEP_FRAMES + (REPLAY_FRAMES if self.catching else 0)   # what is sent again comes in two streams
        for d in (self.voxels, self.tracks, self.keypoints, self.markers):
            for f in sorted(d)[:-keep]:
                del d[f]
        ready = set(self.voxels) & set(self.tracks)
        if self.marker_people is not None:
            # a frame waits for the markers of every camera of its voxels, unless that camera
            # has sent a later frame's (they come in order: these were lost or refused)
            ready = {f for f in ready if all(c in self.markers.get(f, {}) or self.markers_newest.get(c, -1) > f
                                             for c in self.voxels[f].cameras)}
        if self.keypoint_workers:
            # a frame waits for every keypoints worker, unless one has sent a later frame
            # (what it sends comes in order: that frame's keypoints were lost or refused)
            ready = {f for f in ready if all(w in self.keypoints.get(f, {}) or self.keypoints_newest.get(w, -1) > f
                                             for w in self.keypoint_workers)}
        ready = sorted(ready)
        # catching up, every complete frame is posed in order (the estimator must see each
        # frame the undisturbed run saw); otherwise the newest: older ones are behind
        for frame in ready if self.catching else ready[-1:]:
            self._pose(self.voxels.pop(frame), self.tracks.pop(frame), self.keypoints.pop(frame, None),
                       self.markers.pop(frame, None))
            for d in (self.voxels, self.tracks, self.keypoints, self.markers):
                for f in [f for f in d if f <= frame]:
                    del d[f]

    def _pose(self, vox: Voxels, tracks: Tracks, keypoints: dict | None = None, markers: dict | None = None) -> None:
        publish = not self.put_out_before(vox.frame)   # put out by the earlier incarnation: catching up
        if self.catching and not self.caught_up_frames and vox.frame > self.done + 1:
            self.log.warning("frames %d-%d after the pose snapshot were not sent again: carrying on with a gap",
                             self.done + 1, vox.frame - 1)
            self.lost_after(self.done + 1, vox.frame - 1)
        if publish and self.catching:
            self.catching = False   # the caught-up frames are said when it publishes (Worker.publish)
        self.done = vox.frame
        try:
            self._estimate(vox, tracks, publish, keypoints, markers)
        finally:
            if publish:
                self.finished(vox.frame)   # older frames still waiting are given up with it
            else:
                self.caught_up_on(vox.frame)
        self.at = (vox.epoch, vox.frame, vox.t, self.grid)
        if publish and vox.frame % int(self.params["snapshot_frames"]) == 0:
            self.save_arrays()

    def _estimate(self, vox: Voxels, tracks: Tracks, publish: bool = True, keypoints: dict | None = None,
                  markers: dict | None = None) -> None:
        ids = np.asarray(tracks.ids, dtype=np.int64)
        positions = np.asarray(tracks.positions, dtype=np.float64).reshape(-1, 3)
        # every track takes part in the voxel ownership; only this worker's share is posed
        only = None if self.share is None else (lambda t: owns(self.share, t))
        if self.marker_people is not None:
            from app.markers.people import pose_marker_frame
            self.grid = self._grid(vox)   # the snapshot's stamp: the stream it belongs to
            markers = markers or {}
            if len(ids):
                self.marker_frames[1] += 1
                self.marker_frames[0] += all(c in markers for c in vox.cameras)
            result = pose_marker_frame(self.marker_people, vox, ids, positions, markers, float(self.params["reach"]),
                                       only=only)
            self._publish_poses(vox, result, publish)
            return
        people_kp = None
        if self.keypoint_workers:
            from app.keypoints.fusion import frame_keypoints
            people_kp = frame_keypoints(list((keypoints or {}).values()), self.calibration)
            if len(ids):   # frames with someone to pose
                self.keypoint_frames[1] += 1
                self.keypoint_frames[0] += bool(people_kp)
        result, kept, no_silhouettes = pose_frame(self._estimator(vox), vox, ids, positions, self.params,
                                                  only=only, calibration=self.calibration, keypoints=people_kp)
        if self.settings.silhouette > 0:
            self._count_silhouettes(vox.frame, no_silhouettes)
        if kept is not None:
            self.kept.append(kept)
        self._publish_poses(vox, result, publish)

    def _publish_poses(self, vox: Voxels, result: dict, publish: bool) -> None:
        order = sorted(result)
        self.people_counts.append(len(order))
        joints = np.array([result[t][0] for t in order], dtype=np.float64).reshape(-1, 15, 3)
        active = np.array([result[t][1] for t in order], dtype=bool).reshape(-1, 15)
        if not publish:
            return
        same = {"epoch": vox.epoch} if hasattr(vox, "epoch") else {}
        self.publish(self.keys.poses(), Poses(**same, frame=vox.frame, stamp=vox.stamp, t=vox.t, worker=self.name,
                                              tracks=np.array(order, dtype=np.int64), joints=joints, active=active))

    def _count_silhouettes(self, frame: int, why_not: str | None) -> None:
        """Frames posed with and without the silhouettes; the first without says why."""
        self.silhouette_frames[1] += 1
        self.silhouette_frames[0] += why_not is None
        if why_not is not None and self.silhouette_frames[1] - self.silhouette_frames[0] == 1:
            self.log.warning("frame %d: the silhouette term is off: %s", frame, why_not)

    def extra_figures(self) -> dict:
        c = getattr(self, "people_counts", ())
        kept = getattr(self, "kept", ())
        return {"people": int(c[-1]) if c else 0, "method": self.params.get("method"),
                "consensus_share": round(float(np.mean(kept)), 3) if kept else None,
                "silhouette_frames": list(getattr(self, "silhouette_frames", [0, 0])),
                "keypoint_frames": list(getattr(self, "keypoint_frames", [0, 0])),
                **({"mode": "markers", "marker_frames": list(self.marker_frames)}
                   if getattr(self, "marker_people", None) is not None else {})}
