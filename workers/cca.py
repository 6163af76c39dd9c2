"""CCA worker: connected components of each frame's voxels, their features (Table 4.1)
and the person / no-person verdict (thesis §4.2.3), published as :class:`~app.messages.Blobs`.

Its own process because the thesis found CCA the bottleneck of its live chain (§4.4.3).
The message carries the voxels too, so the tracker works on one consistent frame
without matching two streams.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.errors import InputError
from app.messages import Blobs, Voxels
from workers.base import RECENT_FRAMES, Worker


class ComponentAnalysis(Worker):
    KIND = "cca"
    ORDER = 3
    CONSUMES = ("voxels",)
    PRODUCES = ("blobs",)
    ACCEPTS = (Voxels,)
    DEFAULTS = {
        "connectivity": 26,        # 6, 18 or 26 (§4.2.3 uses 26)
        "classifier": "default",   # JSON decision tree; "default": app/tracking/person_tree.json; "none": all persons
    }
    CHOICES = {"connectivity": (6, 18, 26)}

    def setup(self) -> None:
        from app.tracking.classifier import DEFAULT_TREE, load_tree

        p = self.params
        if p["connectivity"] not in (6, 18, 26):
            raise InputError(f"cca: connectivity {p['connectivity']} is not 6, 18 or 26")
        name = p["classifier"]
        self.tree = None if name == "none" else load_tree(DEFAULT_TREE if name == "default" else name)
        from app.tracking.blobs import ComponentAnalysis as Core
        Core((4, 4, 4), (0, 0, 0), 0.1, self.tree)(np.zeros((1, 3), np.uint16))   # compile before frames flow
        self.cca = None
        self.grid_key = None
        self.components: deque = deque(maxlen=RECENT_FRAMES)   # per frame: components
        self.persons: deque = deque(maxlen=RECENT_FRAMES)      # ... and those called a person

    def _analysis(self, msg: Voxels):
        from app.tracking.blobs import ComponentAnalysis as Core

        key = (tuple(int(d) for d in msg.dims), tuple(float(o) for o in msg.origin), float(msg.voxel_size))
        if key != self.grid_key:
            self.cca = Core(key[0], key[1], key[2], self.tree, self.params["connectivity"])
            self.grid_key = key
        return self.cca

    def handle(self, key: str, msg: Voxels) -> None:   # validated by the base (indices inside the grid)
        idx = msg.indices.reshape(-1, 3)
        labels, feats, person = self._analysis(msg)(idx)
        self.components.append(len(feats))
        self.persons.append(int(person.sum()))
        colours = msg.colours if msg.colours is not None else np.zeros((0, 3), np.uint8)
        surface = msg.surface if msg.surface is not None else np.zeros(0, bool)
        self.publish(self.keys.blobs(), Blobs(
            epoch=msg.epoch, frame=msg.frame, stamp=msg.stamp, t=msg.t, voxel_size=msg.voxel_size, origin=list(msg.origin),
            dims=list(msg.dims), cameras=list(msg.cameras), indices=np.ascontiguousarray(idx, dtype=np.uint16),
            colours=colours, surface=surface, labels=labels, features=feats, person=person,
            silhouette_sizes=list(msg.silhouette_sizes),   # passed on packed, for the tracker's ghost test
            silhouettes=msg.silhouettes))

    def extra_figures(self) -> dict:
        c, p = getattr(self, "components", ()), getattr(self, "persons", ())
        return {"components": round(float(np.mean(c)), 1) if c else 0,
                "person_blobs": round(float(np.mean(p)), 1) if p else 0}
