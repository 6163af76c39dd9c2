"""Tracking worker: one filter per person and the life of tracks (thesis §4.2-4.3) over
the components of each frame; publishes :class:`~app.messages.Tracks` (the recorder
writes ``tracks.jsonl``, the viewer draws them, the monitor shows how many).

``filter`` selects the thesis's filters: ``naive`` (§4.3.1), ``pf_raw`` / ``pf_colour``
(§4.3.2), ``ss_raw`` / ``ss_colour`` (§4.3.3, the default).
"""
from __future__ import annotations

import numpy as np

from app.errors import InputError
from app.messages import Blobs, Tracks
from workers.base import Worker


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
        "seed": 0,
    }
    RANGES = {"samples": (10, 5000), "particles": (5, 2000), "confirm_sure_frames": (1, 100)}

    def setup(self) -> None:
        from app.tracking.classifier import DEFAULT_TREE, load_tree
        from app.tracking.tracker import MultiTracker, TrackerParams

        p = self.params
        try:
            params = TrackerParams.from_dict({k: p[k] for k in ("filter", "samples", "particles", "seed")}
                                             | {"candidate_min_z": float(p["candidate_min_z"]),
                                                "confirm_sure_frames": int(p["confirm_sure_frames"])})
        except (TypeError, ValueError) as exc:
            raise InputError(f"tracking: {exc}") from None
        name = p["classifier"]
        tree = None if name == "none" else load_tree(DEFAULT_TREE if name == "default" else name)
        from app.tracking.tracker import warm_up
        warm_up()
        self.tracker = MultiTracker(params, tree)
        self.occupancy = None
        self.grid_key = None
        self.counts: list[int] = []

    def handle(self, key: str, msg: Blobs) -> None:
        from app.tracking.scene import OccupancyIndex, SceneFrame

        gkey = tuple(int(d) for d in msg.dims)
        if gkey != self.grid_key:
            self.occupancy = OccupancyIndex(gkey)
            self.grid_key = gkey
        scene = SceneFrame(msg.frame, msg.t, msg.indices, msg.colours, msg.surface, msg.labels, msg.features,
                           msg.person, msg.origin, msg.voxel_size, self.occupancy)
        ids, positions = self.tracker.update(scene)
        self.counts.append(len(ids))
        same = {"epoch": msg.epoch} if hasattr(msg, "epoch") else {}
        self.publish(self.keys.tracks(), Tracks(**same, frame=msg.frame, stamp=msg.stamp, t=msg.t,
                                                ids=ids.astype(np.int64), positions=positions.astype(np.float64)))

    def extra_figures(self) -> dict:
        c = getattr(self, "counts", [])
        return {"tracks": int(c[-1]) if c else 0,
                "tracks_created": int(getattr(self, "tracker", None).next_id - 1) if hasattr(self, "tracker") else 0}
