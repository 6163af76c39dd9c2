"""Markers worker: the colour markers each of its cameras sees (marker-based capture,
thesis §6.4.1.1, §6.6.2; :mod:`app.markers.detector`), published per camera as
:class:`~app.messages.Markers` for the pose stage's marker mode (``pose.mode: markers``).

It scales by camera like segmentation: several markers workers, each with
``cameras: [...]``. A segmentation worker with a ``markers`` model detects them in its
own process instead (``deploy/layouts/markers.yaml`` says both). ``colour``: the
markers' chroma model (``smartroom markers learn``); empty: the recording's
``markers.json``. The markers are a few pixels across, so the grabber sends this
worker's cameras at full size (``scale`` is the largest reduction allowed).
"""
from __future__ import annotations

import numpy as np

from app.messages import Frame, Markers
from workers.base import Worker


class MarkersWorker(Worker):
    KIND = "markers"
    ORDER = 1
    CONSUMES = ("frame",)
    PRODUCES = ("markers",)
    ACCEPTS = (Frame,)
    DEFAULTS = {
        "cameras": "all",
        "colour": "",     # the chroma model (JSON); "": the recording's markers.json
        "scale": 1,       # the frames may reach this worker reduced by at most this
    }
    RANGES = {"scale": (1, 16)}

    def setup(self) -> None:
        from app.errors import InputError
        from app.markers.detector import detect_markers, model_for_run

        self.model = model_for_run(str(self.params["colour"] or ""), self.layout.run.recording, "markers")
        self.calibration = self.run_calibration()
        if self.calibration is None:
            raise InputError("markers: no calibration (the recording's, or --calibration)")
        for cam in self.cameras() or []:
            self.calibration.camera(cam)   # an unknown camera is a one-line error
        detect_markers(np.zeros((8, 8, 3), np.uint8), self.model)
        self.found = [0, 0]   # detections, images

    def admit(self, key: str, msg: Frame) -> str | None:
        mine = self.cameras()
        if (mine is not None and msg.camera not in mine) or msg.camera not in self.calibration.names:
            return "unknown camera"
        return None

    def handle(self, key: str, msg: Frame) -> None:
        from app.markers.detector import frame_markers

        points = frame_markers(msg.image, self.model, msg.scale)
        self.found[0] += len(points)
        self.found[1] += 1
        self.publish(self.keys.markers(msg.camera),
                     markers_message(msg, self.name, points))

    def extra_figures(self) -> dict:
        n, images = getattr(self, "found", [0, 0])
        return {"markers_per_image": round(n / images, 1) if images else None}


def markers_message(frame: Frame, worker: str, points: np.ndarray) -> Markers:
    """The :class:`Markers` of ``frame``'s camera (shared with the segmentation worker)."""
    return Markers(frame=frame.frame, stamp=frame.stamp, t=frame.t, worker=worker, camera=frame.camera,
                   cameras=list(frame.cameras), points=np.asarray(points, np.float32).reshape(-1, 2))
