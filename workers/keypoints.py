"""Keypoints worker: a learned detector's 2D body keypoints of every tracked person in
each of its cameras (issue 23; :mod:`app.keypoints.detector`), published as
:class:`~app.messages.Keypoints` for the pose stage's keypoint term.

Top-down: a frame's images wait for the same frame's tracks (made from them four stages
later); each track's body (a cylinder of the person's size at the track) is cropped from
each camera and run through the network, so the cost is bounded per person and camera
(about 15 ms on one core). It scales by camera like segmentation: several keypoints
workers, each with ``cameras: [...]``; the pose worker waits for all of them.

``model``: the landmark model file (default: the one the mediapipe 0.10.14 distribution
ships); ``threads``: the runtime's threads; ``scale``: the largest reduction of the
frames the grabber may send this worker (1: full size; 2 is enough for HD);
``max_views``: the cameras per person the network runs on, the nearest (0: all).
Without the optional extra the worker stops at start with one line naming it.
"""
from __future__ import annotations

import numpy as np

from app.errors import InputError
from app.messages import JOINTS, Frame, Keypoints, Tracks
from workers.base import Worker

KEEP_FRAMES = 16


class KeypointsWorker(Worker):
    KIND = "keypoints"
    ORDER = 5
    CONSUMES = ("frame", "tracks")
    PRODUCES = ("keypoints",)
    ACCEPTS = (Frame, Tracks)
    INBOX_DEPTH = 8
    ACK_ON_HANDLE = False   # a frame is finished once its tracks came and its crops were run
    DEFAULTS = {
        "cameras": "all",
        "model": "",          # the landmark model file; "": the one mediapipe 0.10.14 ships
        "threads": 1,
        "scale": 1,           # the frames may reach this worker reduced by at most this
        "margin": 1.2,        # the crop's side over the body's projected extent
        "min_side": 48,       # pixels: a camera where the body's axis is shorter gives nothing
        "max_views": 0,       # the network runs on at most this many cameras per person, those where the
                              # person is largest (nearest); 0 = every camera of this worker
    }
    RANGES = {"threads": (1, 64), "scale": (1, 16), "margin": (1.0, 3.0), "min_side": (8, 4096),
              "max_views": (0, 64)}

    def setup(self) -> None:
        from app.keypoints.detector import KeypointDetector

        self.calibration = self.run_calibration()
        if self.calibration is None:
            raise InputError("keypoints: no calibration (the recording's, or --calibration)")
        for cam in self.cameras() or []:
            self.calibration.camera(cam)   # an unknown camera is a one-line error
        self.detector = KeypointDetector(self.params["model"] or None, int(self.params["threads"]))
        self.detector.run(np.zeros((256, 256, 3), np.uint8))   # the runtime's first call, before frames flow
        self.images: dict[int, dict[str, Frame]] = {}
        self.tracks: dict[int, Tracks] = {}
        self.done = -1
        self.crops = [0, 0]     # crops run, camera views of tracks offered

    def new_epoch(self, epoch: int) -> None:
        self.images.clear()
        self.tracks.clear()
        self.done = -1

    def admit(self, key: str, msg) -> str | None:
        if isinstance(msg, Frame):
            mine = self.cameras()
            if (mine is not None and msg.camera not in mine) or msg.camera not in self.calibration.names:
                return "unknown camera"
        return None

    def _mine(self, frame_set) -> list[str]:
        mine = self.cameras()
        return [c for c in frame_set if c in self.calibration.names and (mine is None or c in mine)]

    def handle(self, key: str, msg) -> None:   # validated by the base
        if msg.frame <= self.done:
            return
        if isinstance(msg, Frame):
            self.images.setdefault(msg.frame, {})[msg.camera] = msg
        else:
            self.tracks[msg.frame] = msg
        for frame in sorted(self.tracks):
            views = self.images.get(frame, {})
            cams = self._mine(next(iter(views.values())).cameras) if views else None
            complete = cams is not None and all(c in views for c in cams)
            stale = frame < max(self.tracks) - KEEP_FRAMES   # its images will not come (a live drop)
            if not (complete or stale):
                break
            self._detect(self.tracks.pop(frame), self.images.pop(frame, {}))
        for f in [f for f in self.images if f <= self.done or f < msg.frame - 4 * KEEP_FRAMES]:
            del self.images[f]

    def _detect(self, tracks: Tracks, views: dict) -> None:
        from app.keypoints.detector import crop_top, person_crop

        self.done = tracks.frame
        ids = np.asarray(tracks.ids, dtype=np.int64)
        positions = np.asarray(tracks.positions, dtype=np.float64).reshape(-1, 3)
        cams = sorted(views)
        points = np.zeros((len(ids), len(cams), len(JOINTS), 3), dtype=np.float32)
        cameras = []
        for name in cams:
            camera = self.calibration.camera(name)
            h, w = views[name].image.shape[:2]
            cameras.append(camera.scaled(w, h) if (w, h) != (camera.width, camera.height) else camera)
        most = int(self.params["max_views"]) or len(cams)
        for k, pos in enumerate(positions):
            crops = []
            for c, name in enumerate(cams):
                self.crops[1] += 1
                crop = person_crop(cameras[c], pos, crop_top(pos[2]), margin=float(self.params["margin"]),
                                   min_side=float(self.params["min_side"]) / views[name].scale)
                if crop is not None:
                    crops.append((crop.side * views[name].scale, c, crop))
            for _, c, crop in sorted(crops, key=lambda x: (-x[0], x[1]))[:most]:   # the nearest views first
                frame, camera = views[cams[c]], cameras[c]
                self.crops[0] += 1
                kp = self.detector.detect(frame.image, crop)
                kp[:, :2] = (kp[:, :2] + 0.5) * frame.scale - 0.5   # back to the calibrated pixels
                far = 2 * max(camera.width, camera.height) * frame.scale
                points[k, c] = np.clip(kp, [-far, -far, 0.0], [far, far, 1.0])
        try:
            self.publish(self.keys.keypoints(), Keypoints(
                frame=tracks.frame, stamp=tracks.stamp, t=tracks.t, worker=self.name, cameras=cams,
                tracks=ids, points=points))
        finally:
            self.finished(tracks.frame)

    def flush(self) -> None:
        for frame in sorted(self.tracks):
            self._detect(self.tracks.pop(frame), self.images.pop(frame, {}))

    def extra_figures(self) -> dict:
        run, offered = getattr(self, "crops", [0, 0])
        return {"crops": run, "views_offered": offered}
