"""Tracking worker: one filter per person and the life of tracks (thesis §4.2-4.3) over
the components of each frame; publishes :class:`~app.messages.Tracks` (the recorder
writes ``tracks.jsonl``, the viewer draws them, the monitor shows how many).

``filter`` selects the thesis's filters: ``naive`` (§4.3.1), ``pf_raw`` / ``pf_colour``
(§4.3.2), ``ss_raw`` / ``ss_colour`` (§4.3.3, the default).

A restarted tracking worker keeps every person's identity: the tracker's whole state
(:mod:`app.tracking.snapshot`) is saved with the frame it belongs to every
``snapshot_frames`` frames (and with the worker's state); the next incarnation restores
it and advances it, without publishing, through the frames its earlier incarnation put
out after the snapshot (the blobs sent again after the restart, :meth:`Worker.catch_up`).
Offline the tracks are then those of an undisturbed run, byte for byte. Where frames
are missing between the snapshot and the restart (live: ~1 s), the tracker carries on
from the snapshot and first looks for every track's person within the distance a person
walks in the gap (:meth:`~app.tracking.tracker.MultiTracker.relocate`).
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.errors import InputError
from app.messages import Blobs, Tracks
from workers.base import RECENT_FRAMES, Worker


class Tracking(Worker):
    KIND = "tracking"
    ORDER = 4
    CONSUMES = ("blobs",)
    PRODUCES = ("tracks",)
    ACCEPTS = (Blobs,)
    INBOX_DEPTH = 2
    DEFAULTS = {
        "filter": "ss_colour",     # naive, pf_raw, pf_colour, ss_raw, ss_colour
        "samples": 400,            # N_s (Sparse Sampling)
        "particles": 100,          # N_p (particle filter)
        "classifier": "default",   # the person test of new tracks; "none": component verdicts only
        "candidate_min_z": 0.9,    # m: a new component's candidate placed by its voxels this high; -.inf: centroid
        "confirm_sure_frames": 2,  # a sure person in an empty room is a track after this many frames; 5: never sooner
        "same_place": 0.2,         # m: a younger track this close to an older one is a duplicate, however
                                   # dressed (two bodies do not fit; 0: off)
        "no_person_credit": 1.0,   # frames of patience a track earns by each frame it was a person, against
        "no_person_cap": 100,      # the classifier's no-person verdicts (crouching, sitting), at most this many
                                   # (0: the thesis, a track ends after 18 no-person frames)
        "vacated_frames": 50,      # no new track where a track stayed this many frames and then left (the
                                   # background's ghost of a person who stood still; app.tracking.tracker; 0: off)
        "ghosts": True,            # no new track on a blob where other people's silhouette cones cross
                                   # (app.tracking.ghosts; needs the run's calibration; false: the thesis)
        "ghost_silhouettes": True,  # ... a camera is its witness only where its silhouette shows it (the
                                    # silhouettes the voxels bring; false: the voxels' projections alone)
        "snapshot_frames": 4,      # the tracker's state is saved every this many frames (and every 0.5 s)
        "seed": 0,
    }
    RANGES = {"samples": (10, 5000), "particles": (5, 2000), "confirm_sure_frames": (1, 100), "same_place": (0.0, 2.0),
              "no_person_credit": (0.0, 100.0), "no_person_cap": (0, 100000), "vacated_frames": (0, 100000),
              "snapshot_frames": (1, 1000)}
    WALK_SPEED = 1.5         # m/s: how far a person may have gone in a gap the tracker did not see
    RELOCATE_AFTER_S = 0.2   # a gap shorter than this needs no wider search

    def setup(self) -> None:
        from app.tracking.classifier import DEFAULT_TREE, load_tree
        from app.tracking.tracker import MultiTracker, TrackerParams

        p = self.params
        try:
            params = TrackerParams.from_dict({k: p[k] for k in ("filter", "samples", "particles", "seed")}
                                             | {"candidate_min_z": float(p["candidate_min_z"]),
                                                "confirm_sure_frames": int(p["confirm_sure_frames"]),
                                                "same_place": float(p["same_place"]),
                                                "no_person_credit": float(p["no_person_credit"]),
                                                "no_person_cap": int(p["no_person_cap"]),
                                                "vacated_frames": int(p["vacated_frames"])})
        except (TypeError, ValueError) as exc:
            raise InputError(f"tracking: {exc}") from None
        name = p["classifier"]
        tree = None if name == "none" else load_tree(DEFAULT_TREE if name == "default" else name)
        from app.tracking.tracker import warm_up
        warm_up()
        self.tracker_params = params
        self.classifier = tree
        self.ghost_test = None
        if self.params["ghosts"]:
            from app.tracking.ghosts import GhostTest

            calibration = self.run_calibration()
            self.ghost_test = GhostTest(calibration.cameras) if calibration is not None else None
        self.tracker = MultiTracker(params, tree, self.ghost_test)
        self.occupancy = None
        self.grid_key = None
        self.counts: deque = deque(maxlen=RECENT_FRAMES)   # tracks per frame
        self.at = None           # (epoch, frame, t, dims) of the last frame the tracker took in
        self.saved_at = None     # ... of the last snapshot saved
        self.resumed = None      # (frame, t) of the snapshot restored, until the first frame after it

    def new_epoch(self, epoch: int) -> None:
        self._take_over(None)    # a snapshot belongs to its epoch's frame numbers

    def _stream(self, dims) -> dict:
        return {"dims": [int(d) for d in dims], "classifier": self.params["classifier"]}

    def _take_over(self, msg: Blobs | None) -> None:
        """Restore the earlier incarnation's tracker if its snapshot fits this stream
        (epoch, grid, parameters); otherwise say why, once, and start afresh."""
        if not self.earlier_pending:
            return
        earlier = self.earlier_arrays(msg, "the tracker", **self._stream(msg.dims if msg is not None else ()))
        if earlier is None:
            return
        from app.tracking.snapshot import SnapshotError, restore_tracker
        (arrays, mine), dims = earlier, [int(d) for d in msg.dims]
        try:
            self.tracker = restore_tracker(self.tracker_params, self.classifier, arrays, dims)
            self.tracker.ghost_test = self.ghost_test
        except SnapshotError as exc:
            self.log.warning("%s: the tracker starts afresh", exc)
            return
        self.at = self.saved_at = (msg.epoch, mine["frame"], mine["t"], tuple(dims))
        self.resumed = (mine["frame"], mine["t"])
        self.log.warning("tracker restored at frame %d: tracks %s, next id %d", mine["frame"],
                         [t.id for t in self.tracker.tracks], self.tracker.next_id)

    def state_arrays(self) -> dict | None:
        if getattr(self, "at", None) is None or self.at == self.saved_at:
            return None          # nothing tracked yet (or a snapshot still to take over), or saved already
        from app.tracking.snapshot import tracker_state
        epoch, frame, t, dims = self.at
        self.saved_at = self.at
        return self.stamp_arrays(tracker_state(self.tracker, dims), epoch, frame, t, **self._stream(dims))

    def _scene(self, msg: Blobs):
        from app.tracking.scene import OccupancyIndex, SceneFrame

        gkey = tuple(int(d) for d in msg.dims)
        if gkey != self.grid_key:
            self.occupancy = OccupancyIndex(gkey)
            self.grid_key = gkey
        masks = msg.silhouette_masks() if self.params["ghost_silhouettes"] and self.ghost_test is not None else []
        return SceneFrame(msg.frame, msg.t, msg.indices, msg.colours, msg.surface, msg.labels, msg.features,
                          msg.person, msg.origin, msg.voxel_size, self.occupancy,
                          dict(zip(msg.cameras, masks)) if masks else None)

    def _update(self, msg: Blobs):
        """The tracker takes in one frame (after a gap since a restored snapshot, it first
        looks for its people farther away); the earlier incarnation's tracker is taken
        over before (:meth:`handle`, :meth:`catch_up`)."""
        scene = self._scene(msg)
        if self.resumed is not None:
            frame, t = self.resumed
            self.resumed = None
            if msg.frame > frame + 1:
                gap = max(0.0, msg.t - t)
                self.log.warning("frames %d-%d after the tracker's snapshot were not sent again: carrying on after a "
                                 "gap of %.2f s", frame + 1, msg.frame - 1, gap)
                self.lost_after(frame + 1, msg.frame - 1)
                if gap > self.RELOCATE_AFTER_S:
                    self.tracker.relocate(scene, self.tracker.p.refine_radius + self.WALK_SPEED * gap)
        out = self.tracker.update(scene)
        self.at = (msg.epoch, msg.frame, msg.t, self.grid_key)
        return out

    def catch_up(self, key: str, msg: Blobs) -> None:
        """A frame the earlier incarnation put out: the restored tracker takes it in (if
        its snapshot is older), nothing is published."""
        self._take_over(msg)
        if self.at is None or self.at[0] != msg.epoch or msg.frame <= self.at[1]:
            return               # no snapshot (a fresh tracker: the old behaviour), or in it already
        self._update(msg)
        self.caught_up_on(msg.frame)

    def handle(self, key: str, msg: Blobs) -> None:
        self._take_over(msg)
        if self.at is not None and self.at[0] == msg.epoch and msg.frame <= self.at[1]:
            self.log.warning("frame %d is in the restored tracker already: not tracked again", msg.frame)
            return
        ids, positions = self._update(msg)
        self.counts.append(len(ids))
        same = {"epoch": msg.epoch} if hasattr(msg, "epoch") else {}
        self.publish(self.keys.tracks(), Tracks(**same, frame=msg.frame, stamp=msg.stamp, t=msg.t,
                                                ids=ids.astype(np.int64), positions=positions.astype(np.float64)))
        if msg.frame % int(self.params["snapshot_frames"]) == 0:
            self.save_arrays()

    def extra_figures(self) -> dict:
        c = getattr(self, "counts", ())
        return {"tracks": int(c[-1]) if c else 0,
                "tracks_created": int(getattr(self, "tracker", None).next_id - 1) if hasattr(self, "tracker") else 0,
                "ghost_sightings": int(self.tracker.ghosts) if hasattr(self, "tracker") else 0}
