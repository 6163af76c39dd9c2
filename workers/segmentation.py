"""Segmentation worker: one background model per camera, one or many cameras per
process. Publishes each camera's bit-packed foreground mask (at ``1/scale`` of the
image size) with the downscaled colour image that voxel colouring needs.

The background model starts from the recording's ``background/<cam>.png`` when there
is one; otherwise from the per-pixel temporal median of frames spread across the
recording (real sessions rarely have empty-room shots); live cameras learn it from
the stream.
"""
from __future__ import annotations

import cv2

from app.messages import Frame, Mask
from app.recording import Recording
from app.segmentation import CameraSegmenter, SegmentationParams, estimate_background, working_size
from workers.base import Worker


class Segmentation(Worker):
    KIND = "segmentation"
    ORDER = 1
    CONSUMES = ("frame",)
    PRODUCES = ("mask",)
    DEFAULTS = {
        "cameras": "all",
        "scale": 2,                  # masks at 1/scale of the image size
        "history": 500,
        "var_threshold": 16.0,
        "shadows": True,
        "shadow_threshold": 0.5,
        "learning_rate": -1.0,
        "open_px": 3,
        "close_px": 5,
        "colour_scale": 2,           # colour image sent at 1/colour_scale (0: no colour)
        "median_frames": 25,         # frames for the median background when there is no image
    }

    def setup(self) -> None:
        self.seg_params = SegmentationParams.from_params(self.params)
        self.segmenters: dict[str, CameraSegmenter] = {}
        self.recording = Recording(self.layout.run.recording) if self.layout.run.recording else None
        if self.recording is not None:  # build the models before the first frame arrives
            for cam in self.cameras() or self.recording.cameras:
                self._segmenter(cam)

    def _background(self, cam: str):
        if self.recording is None:
            self.log.info("camera %s: live, the background model learns from the stream", cam)
            return None
        background = self.recording.background(cam)
        if background is None:
            n = self.params["median_frames"]
            background = estimate_background(self.recording.sample(cam, n))
            self.log.warning("camera %s: no background image; estimated as the median of %d frames of the recording",
                             cam, n)
        return background

    def _segmenter(self, cam: str) -> CameraSegmenter:
        seg = self.segmenters.get(cam)
        if seg is None:
            seg = self.segmenters[cam] = CameraSegmenter(self.seg_params, self._background(cam))
        return seg

    def handle(self, key: str, msg: Frame) -> None:
        mask = self._segmenter(msg.camera).apply(msg.image)
        scale = self.params["colour_scale"]
        colour = None
        if scale == 1:
            colour = msg.image
        elif scale > 1:
            h, w = msg.image.shape[:2]
            colour = cv2.resize(msg.image, working_size(w, h, scale), interpolation=cv2.INTER_AREA)
        self.publish(self.keys.mask(msg.camera),
                     Mask.pack(mask, frame=msg.frame, stamp=msg.stamp, t=msg.t, camera=msg.camera,
                               colour_scale=max(1, scale), colour=colour))
